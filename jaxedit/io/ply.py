"""PLY files: 3D Gaussian splats (the INRIA 3DGS layout) and coloured point clouds.

Splat files (:func:`load_ply`, :func:`save_ply`) use the layout INRIA's 3DGS, gsplat,
nerfstudio and the web viewers share: ``binary_little_endian``, one ``vertex``
element, one float property per value::

    x y z [nx ny nz] f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3

Fields are looked up by name (normals optional). ``f_rest`` is channel-major: with
K = (d+1)^2, ``f_rest_{c*(K-1)+k} = sh[:, 1+k, c]`` for ``Gaussians.sh`` [C, K, 3].
``opacity`` is the logit, ``scale_i`` the log standard deviations, ``rot_0..3`` the
raw quaternion (w, x, y, z). Point clouds (:func:`load_points_ply`,
:func:`save_points_ply`) are COLMAP / nerfstudio initial points, ascii or binary.
A malformed file raises :class:`jaxedit.errors.DataError`; writes are atomic.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import sh as shlib
from ..errors import DataError
from ..gaussians import Gaussians
from .files import atomic_path

# PLY scalar type names (both spellings of the spec) -> numpy kind+size.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
_MAX_HEADER = 1 << 20  # a header longer than this is not a PLY header
_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest fields -> SH degree
_ALIGN = 64  # bytes: jax.device_put on CPU adopts a C-ordered array this aligned, uncopied


def host_array(shape, dtype=np.float32) -> np.ndarray:
    """An uninitialised C-ordered array whose data is 64-byte aligned.

    ``jax.device_put`` on the CPU backend takes such an array as the device buffer without
    copying it, so a reader that fills one and hands it over (keeping no reference) pays for
    one copy of the data instead of two.
    """
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = np.empty(nbytes + _ALIGN, np.uint8)
    start = -raw.ctypes.data % _ALIGN
    return raw[start:start + nbytes].view(dtype).reshape(shape)


def device_arrays(arrays: dict, *, owned: bool = False) -> dict:
    """``jax.device_put`` of {name: NumPy array}, each copied once into aligned memory.

    ``owned``: the arrays are the caller's own and never written again, so those already
    C-ordered and aligned are handed over without a copy (the device buffer is their memory).
    """
    def ready(a):
        a = np.asarray(a)
        if owned and a.flags.c_contiguous and a.ctypes.data % _ALIGN == 0:
            return a
        out = host_array(a.shape, a.dtype)
        np.copyto(out, a)
        return out

    return jax.device_put({k: ready(v) for k, v in arrays.items()})


@dataclass(frozen=True)
class _Property:
    name: str
    kind: str  # numpy kind+size, e.g. "f4"
    list_count_kind: str | None = None  # for list properties: the type of the count


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: tuple[_Property, ...]

    @property
    def has_lists(self) -> bool:
        return any(p.list_count_kind is not None for p in self.properties)


@dataclass(frozen=True)
class _Header:
    format: str
    elements: tuple[_Element, ...]
    data_offset: int  # byte offset of the body


def _parse_header(path: Path, data: bytes) -> _Header:
    """Parse the ASCII header of a PLY file held in ``data``."""
    if not data.startswith(b"ply"):
        raise DataError(path, "not a PLY file (it does not start with 'ply')")
    end = -1
    for marker in (b"end_header\n", b"end_header\r\n"):
        end = data.find(marker, 0, _MAX_HEADER)
        if end >= 0:
            end += len(marker)
            break
    if end < 0:
        raise DataError(path, "PLY header has no 'end_header' line")
    try:
        text = data[:end].decode("ascii")
    except UnicodeDecodeError:
        raise DataError(path, "PLY header is not ASCII text") from None
    lines = [ln.strip() for ln in text.splitlines()]
    if lines[0] != "ply":
        raise DataError(path, "first PLY header line must be exactly 'ply'")
    fmt = None
    elements: list[list] = []  # [name, count, [properties]]
    for number, line in enumerate(lines[1:-1], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise DataError(path, f"unsupported PLY format line {line!r} (header line {number})")
            if words[2] != "1.0":
                raise DataError(path, f"unsupported PLY version {words[2]!r}")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not re.fullmatch(r"\d+", words[2]):
                raise DataError(path, f"malformed element line {line!r} (header line {number})")
            elements.append([words[1], int(words[2]), []])
        elif key == "property":
            if not elements:
                raise DataError(path, f"property before any element (header line {number})")
            props = elements[-1][2]
            if len(words) == 3 and words[1] in _PLY_TYPES:
                prop = _Property(words[2], _PLY_TYPES[words[1]])
            elif (len(words) == 5 and words[1] == "list" and words[2] in _PLY_TYPES
                  and words[3] in _PLY_TYPES and _PLY_TYPES[words[2]][0] in "iu"):
                prop = _Property(words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]])
            else:
                raise DataError(path, f"malformed property line {line!r} (header line {number})")
            if any(p.name == prop.name for p in props):
                raise DataError(path, f"element {elements[-1][0]!r} declares property "
                                      f"{prop.name!r} twice")
            props.append(prop)
        else:
            raise DataError(path, f"unknown PLY header keyword {key!r} (header line {number})")
    if fmt is None:
        raise DataError(path, "PLY header has no 'format' line")
    return _Header(fmt, tuple(_Element(n, c, tuple(p)) for n, c, p in elements), end)


def _read_bytes(path) -> tuple[Path, bytes]:
    path = Path(path)
    try:
        return path, path.read_bytes()
    except FileNotFoundError:
        raise DataError(path, "file not found") from None
    except IsADirectoryError:
        raise DataError(path, "is a directory, expected a .ply file") from None
    except OSError as e:
        raise DataError(path, f"cannot read file ({e.strerror or e})") from None


def _binary_dtype(element: _Element, endian: str) -> np.dtype:
    return np.dtype([(p.name, endian + p.kind) for p in element.properties])


def _skip_binary_element(path: Path, data: bytes, offset: int, element: _Element,
                         endian: str) -> int:
    """Byte offset just past ``element`` (walks list properties item by item)."""
    if not element.has_lists:
        return offset + element.count * _binary_dtype(element, endian).itemsize
    # Each item takes at least its fixed-size parts: refuse impossible counts
    # before walking them one by one.
    min_item = sum(int((p.list_count_kind or p.kind)[1]) for p in element.properties)
    if offset + element.count * min_item > len(data):
        raise DataError(path, f"truncated PLY data: element {element.name!r} cannot hold "
                              f"{element.count} items")
    for _ in range(element.count):
        for p in element.properties:
            if p.list_count_kind is None:
                offset += int(p.kind[1])
                continue
            size = int(p.list_count_kind[1])
            if offset + size > len(data):
                raise DataError(path, f"PLY data ends inside element {element.name!r}")
            n = int(np.frombuffer(data, endian + p.list_count_kind, 1, offset)[0])
            offset += size + n * int(p.kind[1])
    return offset


def _read_vertex_table(path: Path) -> tuple[_Header, _Element, dict[str, np.ndarray],
                                           np.ndarray | None]:
    """Parse ``path`` and return its ``vertex`` element.

    Returns (header, element, {property name: column [N]}, records) where
    ``records`` is the structured array [N] of a binary file (None for ascii).
    """
    path, data = _read_bytes(path)
    header = _parse_header(path, data)
    names = [e.name for e in header.elements]
    if names.count("vertex") != 1:
        raise DataError(path, f"expected exactly one 'vertex' element, found elements {names}")
    if header.format == "ascii":
        element, table = _read_ascii_vertices(path, data, header)
        return header, element, table, None
    endian = _FORMATS[header.format]
    offset = header.data_offset
    for element in header.elements:
        if element.name != "vertex":
            offset = _skip_binary_element(path, data, offset, element, endian)
            continue
        if element.has_lists:
            raise DataError(path, "the 'vertex' element has list properties")
        dtype = _binary_dtype(element, endian)
        need = element.count * dtype.itemsize
        if offset + need > len(data):
            raise DataError(path, f"truncated PLY data: {element.count} vertices need {need} bytes, "
                                  f"{max(len(data) - offset, 0)} present")
        rows = np.frombuffer(data, dtype, element.count, offset)
        return header, element, {p.name: rows[p.name] for p in element.properties}, rows
    raise AssertionError("unreachable")


def _read_ascii_vertices(path: Path, data: bytes, header: _Header):
    try:
        tokens = data[header.data_offset:].decode("ascii").split()
    except UnicodeDecodeError:
        raise DataError(path, "ascii PLY body is not ASCII text") from None
    pos = 0
    for element in header.elements:
        if element.name != "vertex":
            if element.count * len(element.properties) > len(tokens) - pos:
                raise DataError(path, f"truncated ascii PLY: element {element.name!r} cannot hold "
                                      f"{element.count} items")
            # Walk the element token by token (list lengths vary per item).
            for _ in range(element.count):
                for p in element.properties:
                    if p.list_count_kind is None:
                        pos += 1
                    else:
                        try:
                            pos += 1 + int(tokens[pos])
                        except (IndexError, ValueError):
                            raise DataError(path, f"malformed list in element {element.name!r}") from None
            continue
        if element.has_lists:
            raise DataError(path, "the 'vertex' element has list properties")
        width = len(element.properties)
        chunk = tokens[pos:pos + element.count * width]
        if len(chunk) < element.count * width:
            raise DataError(path, f"truncated ascii PLY: {element.count} vertices of {width} values "
                                  f"need {element.count * width} numbers, {len(chunk)} present")
        try:
            values = np.array(chunk, dtype=np.float64).reshape(element.count, width)
        except ValueError:
            raise DataError(path, "ascii PLY vertex data contains a value that is not a number") from None
        table = {p.name: values[:, i].astype(p.kind) for i, p in enumerate(element.properties)}
        return element, table
    raise AssertionError("unreachable")


# -- Gaussian splats --


def _rest_field_count(path: Path, names: set[str]) -> int:
    rest = sorted(int(n[7:]) for n in names if re.fullmatch(r"f_rest_\d+", n))
    if rest != list(range(len(rest))):
        missing = sorted(set(range(max(rest) + 1)) - set(rest)) if rest else []
        raise DataError(path, f"f_rest fields are not numbered 0..{len(rest) - 1} "
                              f"(missing f_rest_{missing[0] if missing else '?'})")
    if len(rest) not in _REST_COUNTS:
        raise DataError(path, f"{len(rest)} f_rest fields is not 3((d+1)^2-1) for an SH degree d "
                              f"in 0..3 (expected 0, 9, 24 or 45)")
    return len(rest)


def load_ply(path: str | os.PathLike) -> Gaussians:
    """Read a 3DGS .ply file (INRIA layout) into a :class:`Gaussians` with all slots alive.

    Args:
      path: a ``binary_little_endian`` PLY with one ``vertex`` element whose
        float32 (or float64) properties include ``x y z f_dc_0..2 opacity
        scale_0..2 rot_0..3`` and 0, 9, 24 or 45 ``f_rest_*`` fields.
    Returns:
      Gaussians with capacity N (the vertex count), float32, SH degree from the
      number of ``f_rest`` fields, ``alive`` all True.
    Raises:
      DataError: missing/unreadable file, another PLY format, missing or
        non-float fields, a bad f_rest count, truncated data, non-finite values.
    """
    path = Path(path)
    header, element, table, records = _read_vertex_table(path)
    if header.format != "binary_little_endian":
        raise DataError(path, f"3DGS PLY must be binary_little_endian, this one is {header.format}")
    names = set(table)
    required = (["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
                + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
    missing = [n for n in required if n not in names]
    if missing and "packed_position" in names:
        raise DataError(path, "a PlayCanvas compressed PLY, not the INRIA layout: read it with "
                              "jaxedit.io.load_scene")
    if missing:
        raise DataError(path, f"not a 3DGS PLY: vertex element lacks field(s) {', '.join(missing)}")
    n_rest = _rest_field_count(path, names)
    rest_names = [f"f_rest_{i}" for i in range(n_rest)]
    kinds = {p.name: p.kind for p in element.properties}
    for name in required + rest_names:
        if kinds[name] not in ("f4", "f8"):
            raise DataError(path, f"field {name!r} must be float, it is {kinds[name]}")

    order = [p.name for p in element.properties]
    matrix = None
    if records is not None and all(p.kind == "f4" for p in element.properties):
        # Every field float32: the records are a float32 matrix [N, F] and picking columns
        # is one gather, not a stack of strided per-field views.
        matrix = records.view(np.dtype("<f4")).reshape(element.count, len(order))

    def cols(fields):  # [N, F] float32 (a slice where the fields are adjacent)
        if not fields:
            return slice(0, 0) if matrix is not None else np.zeros((element.count, 0), np.float32)
        if matrix is not None:
            idx = [order.index(f) for f in fields]
            if idx == list(range(idx[0], idx[0] + len(idx))):
                return slice(idx[0], idx[0] + len(idx))
            return idx
        return np.stack([np.asarray(table[f], np.float32) for f in fields], axis=-1).reshape(
            element.count, len(fields))

    n, k_rest = element.count, n_rest // 3
    # Filled once, in memory device_put adopts: [N, 3], [N, 3], [N, 4], [N], [N, K, 3].
    means, log_scales, quats = host_array((n, 3)), host_array((n, 3)), host_array((n, 4))
    opacity, sh = host_array((n,)), host_array((n, 1 + k_rest, 3))
    sources = [(means, cols(["x", "y", "z"])), (log_scales, cols([f"scale_{i}" for i in range(3)])),
               (quats, cols([f"rot_{i}" for i in range(4)])), (opacity, cols(["opacity"])),
               (sh[:, 0, :], cols(["f_dc_0", "f_dc_1", "f_dc_2"])), (None, cols(rest_names))]
    # A few thousand rows at a time, so that each block of the file is read from cache for all
    # the fields it feeds (the rows are hundreds of bytes apart).
    step = n if matrix is None else 4096
    for lo in range(0, n, step):
        rows = slice(lo, min(n, lo + step))
        for out, where in sources:
            block = where[rows] if matrix is None else matrix[rows, where]
            if out is None:  # channel-major file layout [N, 3, K-1] -> coefficient-major
                sh[rows, 1:, :] = block.reshape(len(block), 3, k_rest).transpose(0, 2, 1)
            else:
                out[rows] = block.reshape(out[rows].shape)
    for label, arr in (("x/y/z", means), ("scale", log_scales), ("rot", quats),
                       ("opacity", opacity), ("f_dc/f_rest", sh)):
        bad = ~np.isfinite(arr)
        if bad.any():
            row = int(np.argwhere(bad.reshape(len(arr), -1).any(axis=1))[0, 0]) if len(arr) else 0
            raise DataError(path, f"non-finite {label} value (NaN or inf) at vertex {row} "
                                  f"({int(bad.reshape(len(arr), -1).any(axis=1).sum())} bad vertices)")
    # device_put, not jnp.asarray: the latter compiles a copy program per array shape
    arrays = dict(means=means, log_scales=log_scales, quats=quats, opacity_logits=opacity,
                  sh=sh, alive=np.ones((element.count,), bool))
    return Gaussians(**device_arrays(arrays, owned=True))


def ply_fields(sh_degree: int, *, normals: bool = True) -> list[str]:
    """Property names, in file order, of a 3DGS PLY of the given SH degree (INRIA order)."""
    k = (sh_degree + 1) ** 2
    return (["x", "y", "z"] + (["nx", "ny", "nz"] if normals else [])
            + [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(3 * (k - 1))]
            + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])


def _alive_fields(g: Gaussians) -> tuple[np.ndarray, ...]:
    """(means, sh, opacity, log_scales, quats) of the alive Gaussians, float32 NumPy."""
    alive = np.asarray(g.alive, bool)
    fields = [np.asarray(a, np.float32) for a in (g.means, g.sh, g.opacity_logits,
                                                   g.log_scales, g.quats)]
    if not alive.all():
        fields = [a[alive] for a in fields]
    return tuple(fields)


def _fill_rows(out: np.ndarray, fields: tuple, rows: slice) -> None:
    """Write ``rows`` of ``fields`` into ``out`` [len(rows), F] in the INRIA column order."""
    means, sh, opacity, log_scales, quats = fields  # sh [N, K, 3]
    k = sh.shape[1]
    rest = 9 + 3 * (k - 1)  # columns: x y z, normals, f_dc, f_rest, opacity, scales, rot
    out[:, 0:3] = means[rows]
    out[:, 3:6] = 0.0  # normals, as INRIA writes them
    out[:, 6:9] = sh[rows, 0, :]
    out[:, 9:rest].reshape(len(out), 3, k - 1)[...] = sh[rows, 1:, :].transpose(0, 2, 1)
    out[:, rest] = opacity[rows]
    out[:, rest + 1:rest + 4] = log_scales[rows]
    out[:, rest + 4:rest + 8] = quats[rows]


def _ply_dtype(sh_coeffs: int) -> np.dtype:
    return np.dtype([(name, "<f4") for name in ply_fields(int(round(np.sqrt(sh_coeffs))) - 1)])


def gaussians_to_table(g: Gaussians) -> np.ndarray:
    """The alive Gaussians as a float32 structured array with the INRIA PLY fields [N]."""
    fields = _alive_fields(g)
    n, dtype = len(fields[0]), _ply_dtype(fields[1].shape[1])
    table = np.empty((n, dtype.itemsize // 4), np.float32)
    # A few thousand rows at a time, so that each block of the table is written in cache.
    step = 4096
    for lo in range(0, n, step):
        rows = slice(lo, min(n, lo + step))
        _fill_rows(table[rows], fields, rows)
    return table.view(dtype).reshape(n)


def save_ply(path: str | os.PathLike, gaussians: Gaussians) -> Path:
    """Write the alive Gaussians, in slot order, as a 3DGS .ply (normals zero), atomically;
    float32, so a float32 pytree round-trips bit-exactly through :func:`load_ply`. Returns the path.

    The rows are made and written a block at a time (no table of the whole file in memory); a
    non-finite value removes the partial file and raises DataError.
    """
    path = Path(path)
    n_coeffs = np.shape(gaussians.sh)[-2]
    if n_coeffs not in (1, 4, 9, 16):
        raise DataError("gaussians.sh", f"{n_coeffs} SH coefficients is not (d+1)^2 for d in 0..3")
    fields = _alive_fields(gaussians)
    n, dtype = len(fields[0]), _ply_dtype(n_coeffs)
    header = ["ply", "format binary_little_endian 1.0", "comment written by jaxedit",
              f"element vertex {n}"]
    header += [f"property float {name}" for name in dtype.names]
    header.append("end_header")
    step = 16384
    buffer = np.empty((min(n, step), dtype.itemsize // 4), np.float32)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            for lo in range(0, n, step):
                rows = slice(lo, min(n, lo + step))
                block = buffer[:rows.stop - lo]
                _fill_rows(block, fields, rows)
                if not np.isfinite(block.sum(dtype=np.float64)):  # finite iff all are
                    bad = ~np.isfinite(np.concatenate([f.reshape(n, -1) for f in (
                        fields[0], fields[1].reshape(n, -1), fields[2][:, None], fields[3],
                        fields[4])], 1)).all(axis=1)
                    # load_ply refuses such files, so never write one.
                    raise DataError(path, f"{int(bad.sum())} alive Gaussians have non-finite "
                                          f"values (first at alive index {int(np.argmax(bad))}); "
                                          f"nothing written")
                f.write(memoryview(block.view(np.uint8)))
    return path


# -- point clouds --


def _color_scale(kind: str) -> float:
    if kind in ("u1", "i1"):
        return 255.0
    if kind in ("u2", "i2"):
        return 65535.0
    return 1.0  # float colours are taken to be in [0, 1] already


def load_points_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a coloured point cloud (COLMAP / nerfstudio ``sparse_pc.ply`` style).

    Ascii or binary, a ``vertex`` element with ``x y z`` and optional ``red green blue``
    (or ``r g b``, ``diffuse_red ...``): uchar colours / 255, ushort / 65535, floats as
    they are. A 3DGS file gives its centres and DC colours; anything else is ignored.

    Returns:
      (points float32 [P, 3], colors float32 [P, 3] in [0, 1]); no colours: grey 0.5.
    Raises:
      DataError: unreadable/malformed file, missing x/y/z, non-finite values.
    """
    path = Path(path)
    _, element, table, _ = _read_vertex_table(path)
    missing = [n for n in ("x", "y", "z") if n not in table]
    if missing:
        raise DataError(path, f"point cloud vertex element lacks field(s) {', '.join(missing)}")
    points = np.stack([np.asarray(table[n], np.float32) for n in "xyz"], axis=-1).reshape(-1, 3)
    kinds = {p.name: p.kind for p in element.properties}
    colors = np.full_like(points, 0.5)
    for names in (("red", "green", "blue"), ("r", "g", "b"),
                  ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(n in table for n in names):
            colors = np.stack([np.asarray(table[n], np.float64) / _color_scale(kinds[n])
                               for n in names], axis=-1).astype(np.float32).reshape(-1, 3)
            break
    else:
        if all(f"f_dc_{i}" in table for i in range(3)):  # a 3DGS file: its DC colour
            dc = np.stack([np.asarray(table[f"f_dc_{i}"], np.float64) for i in range(3)], axis=-1)
            colors = shlib.dc_to_rgb(dc).astype(np.float32).reshape(-1, 3)
    if not np.isfinite(points).all():
        raise DataError(path, "point cloud has non-finite (NaN or inf) coordinates")
    if not np.isfinite(colors).all():
        raise DataError(path, "point cloud has non-finite colours")
    return points, np.clip(colors, 0.0, 1.0)


def save_points_ply(path: str | os.PathLike, points, colors) -> Path:
    """Write a point cloud as binary PLY (``x y z`` float, ``red green blue`` uchar), atomically.

    Args:
      points: float [P, 3].
      colors: float [P, 3] in [0, 1] (uint8 [P, 3] is written as is).
    """
    path = Path(path)
    points = np.asarray(points, np.float32)
    colors = np.asarray(colors)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError("points", f"expected shape [P, 3], got {list(points.shape)}")
    if colors.shape != points.shape:
        raise DataError("colors", f"expected shape {list(points.shape)}, got {list(colors.shape)}")
    if not np.isfinite(points).all():
        raise DataError("points", "non-finite coordinates")
    if colors.dtype != np.uint8:
        colors = np.asarray(colors, np.float64)
        if not np.isfinite(colors).all():
            raise DataError("colors", "non-finite colours")
        colors = np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                      ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    table = np.empty(len(points), dtype)
    for i, n in enumerate("xyz"):
        table[n] = points[:, i]
    for i, n in enumerate(("red", "green", "blue")):
        table[n] = colors[:, i]
    header = ("ply\nformat binary_little_endian 1.0\ncomment written by jaxedit\n"
              f"element vertex {len(table)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(table.tobytes())
    return path
