"""PlayCanvas SOG v2: ``meta.json`` and lossless WebP textures, or the same zipped as ``.sog``.

One texel per splat (row-major, Morton-ordered splats, width ceil(sqrt(N)/4)*4, height
ceil(N/width/4)*4), as splat-transform's ``write-sog.ts`` / ``read-sog.ts`` lay them out:

- ``means_l.webp`` / ``means_u.webp``: low / high bytes of 16-bit x y z of sign(v) log(|v| + 1),
  normalised to ``means.mins`` .. ``means.maxs``.
- ``quats.webp``: the unit quaternion (w, x, y, z) with its largest component made positive;
  the other three times sqrt(2) as 255 (v/2 + 1/2) in r g b, a = 252 + the dropped index.
- ``scales.webp``: r g b index the 256-entry ``scales.codebook`` of log-scales.
- ``sh0.webp``: r g b index ``sh0.codebook`` of f_dc values, a = sigmoid(opacity) * 255.
- ``shN_labels.webp`` / ``shN_centroids.webp`` (degree > 0): a palette of ``shN.count`` SH
  vectors (a two-level k-means, :func:`kmeans`, seeded), each splat's 16-bit label in r g; the palette's coefficients
  index ``shN.codebook``, 64 palette entries a texture row, one texel per coefficient.

Codebooks are weighted 1-D k-means (256 centres, :func:`codebook_1d`) over the values they code. The loss is the palette's:
higher SH are approximated by their cluster's centre.

Reading checks ``meta.json`` (version, count, codebook lengths, file names) and every texture's
size before decoding it, and a ``.sog`` archive's declared sizes before inflating anything.
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from pathlib import Path

import numpy as np

from ...errors import DataError
from ...gaussians import Gaussians
from ..files import atomic_path, atomic_write_bytes
from .common import (Splats, check_splats, from_gaussians, largest_component, logit, morton_order,
                     read_file, sigmoid, to_gaussians, unit_quats, with_largest)

MAX_TEXTURE = 16383
#: A .sog whose entries declare more than this many bytes, or more than RATIO times the archive, is refused.
MAX_UNZIPPED = 1 << 32
RATIO = 64
_SH_COEFFS = {0: 0, 1: 3, 2: 8, 3: 15}
#: Rows x centres up to which the SH palette is one flat k-means (a scene of a few thousand
#: splats); above it, two levels (:func:`kmeans`).
FLAT_KMEANS = 1 << 26
_FILES = ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp")


def texture_size(n: int) -> tuple[int, int]:
    """(width, height) of the textures of ``n`` splats."""
    width = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    return width, max(4, math.ceil(n / width / 4) * 4)


def palette_size(n: int) -> int:
    """Entries of the SH palette for ``n`` splats (splat-transform's rule)."""
    return int(min(64, 2 ** math.floor(math.log2(max(n, 1) / 1024))) * 1024)


# --- quantisers ----------------------------------------------------------------------


def codebook_1d(values: np.ndarray, size: int = 256, iterations: int = 10,
                density: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(centres float32 [size], labels uint8 like ``values``): a weighted 1-D k-means.

    Each value weighs (the count of its histogram bin) ** (``density`` - 1), so a region draws
    centres in proportion to its count ** ``density``. 1 is plain k-means (centres crowd the
    dense middle, every label about equally frequent); 0, the default, gives each bin the same
    weight: the tails keep their precision and the labels, fewer of them frequent, compress
    better in the lossless WebP. The values are sorted once; each iteration then finds its
    cells' bounds by bisection and their weighted sums from prefix sums.
    """
    flat = np.asarray(values, np.float64).reshape(-1)
    if flat.size == 0:
        return np.zeros(size, np.float32), np.zeros(np.shape(values), np.uint8)
    order = np.argsort(flat, kind="stable")
    ordered = flat[order]
    weight = _density_weights(ordered, density)
    cumulative = np.cumsum(weight)
    at = np.searchsorted(cumulative, (np.arange(size) + 0.5) / size * cumulative[-1])
    centres = ordered[np.minimum(at, len(flat) - 1)]  # weighted quantiles
    weight_sum = np.concatenate([[0.0], cumulative])
    value_sum = np.concatenate([[0.0], np.cumsum(weight * ordered)])
    for _ in range(iterations):
        centres = np.unique(centres)
        edges = (centres[1:] + centres[:-1]) / 2
        # cell i holds the values in (edges[i-1], edges[i]]: as searchsorted(edges, v) labels
        bounds = np.concatenate([[0], np.searchsorted(ordered, edges, side="right"), [len(flat)]])
        counts = np.diff(weight_sum[bounds])
        sums = np.diff(value_sum[bounds])
        centres = np.where(counts > 0, sums / np.where(counts > 0, counts, 1), centres)
    centres = np.sort(np.pad(np.unique(centres), (0, max(0, size - len(np.unique(centres)))), mode="edge"))
    edges = (centres[1:] + centres[:-1]) / 2
    labels = np.searchsorted(edges, flat).reshape(np.shape(values))
    return centres.astype(np.float32), labels.astype(np.uint8)


def _density_weights(ordered: np.ndarray, density: float, bins: int = 1024) -> np.ndarray:
    """float64 [N]: count(bin of each of the sorted values ``ordered``) ** (density - 1) over
    ``bins`` bins spaced halfway between equal width and equal count (the tails stay resolved)."""
    if density == 1.0:
        return np.ones_like(ordered)
    grid = np.linspace(0.0, 1.0, bins + 1)
    quantiles = np.interp(grid * (len(ordered) - 1), np.arange(len(ordered)), ordered)
    edges = 0.5 * (quantiles + (ordered[0] + grid * (ordered[-1] - ordered[0])))
    edges = np.unique(edges)
    index = np.clip(np.searchsorted(edges, ordered, side="right") - 1, 0, max(len(edges) - 2, 0))
    counts = np.bincount(index, minlength=max(len(edges) - 1, 1)).astype(np.float64)
    return counts[index] ** (density - 1.0)


def _nearest(x: np.ndarray, centres: np.ndarray, block: int = 2048) -> np.ndarray:
    """int [N]: index of the nearest row of ``centres`` [K, D] for each row of ``x`` [N, D]."""
    c2 = (centres.astype(np.float32) ** 2).sum(1)
    ct = np.ascontiguousarray(centres.T, np.float32)
    out = np.empty(len(x), np.int64)
    for i in range(0, len(x), block):
        d = x[i:i + block] @ ct  # |x - c|^2 - |x|^2 = |c|^2 - 2 x.c
        d *= np.float32(-2.0)
        d += c2
        out[i:i + block] = np.argmin(d, axis=1)
    return out


def _lloyd(x: np.ndarray, k: int, iterations: int, rng: np.random.Generator):
    """(centres float32 [k, D], labels int [N]): Lloyd's k-means from ``k`` of the rows drawn
    by ``rng`` (k < N); an emptied cluster keeps its centre."""
    centres = x[np.sort(rng.choice(len(x), k, replace=False))]
    labels = _nearest(x, centres)
    for _ in range(iterations):
        order = np.argsort(labels, kind="stable")
        counts = np.bincount(labels, minlength=k)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        filled = counts > 0
        sums = np.add.reduceat(x[order].astype(np.float64), starts[filled], axis=0)
        centres = centres.copy()
        centres[filled] = (sums / counts[filled, None]).astype(np.float32)
        moved = _nearest(x, centres)
        if np.array_equal(moved, labels):  # a fixed point: further steps change nothing
            break
        labels = moved
    return centres, labels


def kmeans(x: np.ndarray, k: int, *, iterations: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(centres float32 [k', D], labels int [N]), k' <= k: k-means in two levels.

    Where N k is at most :data:`FLAT_KMEANS` this is one flat k-means. Otherwise the rows are
    first split into about sqrt(k) clusters (k-means on a sample of 128 rows a cluster, then
    every row to its nearest); each cluster then gets a share of the k centres in proportion to
    its rows, found by k-means among its rows alone: about N sqrt(k) D an iteration where the
    flat k-means costs N k D. Seeded by ``seed`` alone.
    """
    x = np.ascontiguousarray(x, np.float32)
    n = len(x)
    if k >= n:
        return x.copy(), np.arange(n)
    groups = int(round(math.sqrt(k)))
    if groups < 8 or n * k <= FLAT_KMEANS:
        return _lloyd(x, k, iterations, np.random.default_rng([seed, 0]))
    rng = np.random.default_rng([seed, 0])
    sample = x[np.sort(rng.choice(n, min(n, 128 * groups), replace=False))]
    top = _nearest(x, _lloyd(sample, groups, iterations, rng)[0])
    sizes = np.bincount(top, minlength=groups)
    shares = _apportion(sizes, k)
    order = np.argsort(top, kind="stable")
    members = np.split(order, np.cumsum(sizes)[:-1])
    centres, labels, used = [], np.empty(n, np.int64), 0
    for j, (rows, share) in enumerate(zip(members, shares)):
        if share == 0:
            continue
        if share >= len(rows):  # every row its own centre
            c, lab = x[rows], np.arange(len(rows))
        else:
            c, lab = _lloyd(x[rows], int(share), iterations, np.random.default_rng([seed, 1, j]))
        centres.append(c)
        labels[rows] = lab + used
        used += len(c)
    return np.concatenate(centres), labels


def _apportion(sizes: np.ndarray, k: int) -> np.ndarray:
    """int [G]: ``k`` split in proportion to ``sizes`` (largest remainders; at least 1 for a
    non-empty group, at most its size)."""
    quota = k * sizes / sizes.sum()
    share = np.minimum(np.floor(quota).astype(np.int64), sizes)
    share = np.maximum(share, (sizes > 0).astype(np.int64))
    while share.sum() > k:  # the minimum of 1 overshot: take from the largest shares
        share[np.argmax(share)] -= 1
    spare = k - share.sum()
    if spare > 0:
        room = sizes - share
        rank = np.argsort(-(quota - np.floor(quota)), kind="stable")
        for j in rank:
            if spare == 0:
                break
            add = int(min(room[j], 1))
            share[j] += add
            spare -= add
    return share


# --- encoding ------------------------------------------------------------------------


def _webp(rgba: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba), "RGBA").save(buf, "WEBP", lossless=True, exact=True,
                                                             quality=75, method=4)
    return buf.getvalue()


def _log_transform(v):
    return np.sign(v) * np.log(np.abs(v) + 1.0)


def encode_files(s: Splats, *, iterations: int = 10, seed: int = 0) -> dict[str, bytes]:
    """{file name: bytes} of the SOG of ``s``: ``meta.json`` and its WebP textures.

    ``iterations`` of k-means build the SH palette from a sample drawn with ``seed``.
    """
    n = s.count
    width, height = texture_size(n)
    if width > MAX_TEXTURE or height > MAX_TEXTURE:
        raise DataError("sog", f"{n} splats need {width}x{height} textures, over WebP's {MAX_TEXTURE}")
    s = s.take(morton_order(s.means))

    def texture(channels):  # list of 4 uint8 [N] -> [H, W, 4]
        t = np.zeros((width * height, 4), np.uint8)
        t[:n] = np.stack(channels, 1)
        return t.reshape(height, width, 4)

    full = np.full(n, 255, np.uint8)
    logs = _log_transform(s.means.astype(np.float64))
    lo, hi = (logs.min(0), logs.max(0)) if n else (np.zeros(3), np.zeros(3))
    span = np.where(hi > lo, hi - lo, 1.0)
    q16 = np.clip(np.round((logs - lo) / span * 65535), 0, 65535).astype(np.uint32)
    files = {"means_l.webp": _webp(texture([*(q16 & 0xFF).astype(np.uint8).T, full])),
             "means_u.webp": _webp(texture([*(q16 >> 8).astype(np.uint8).T, full]))}

    index, q = largest_component(unit_quats(s.quats))
    keep = np.ones(q.shape, bool)
    keep[np.arange(n), index] = False
    three = np.clip(np.round(255 * (q[keep].reshape(n, 3) * math.sqrt(2) * 0.5 + 0.5)), 0, 255)
    files["quats.webp"] = _webp(texture([*three.astype(np.uint8).T, (252 + index).astype(np.uint8)]))

    scale_book, scale_labels = codebook_1d(s.log_scales)
    files["scales.webp"] = _webp(texture([*scale_labels.T, full]))
    dc_book, dc_labels = codebook_1d(s.sh[:, 0, :])
    alpha = np.clip(np.round(sigmoid(s.opacity_logits) * 255), 0, 255).astype(np.uint8)
    files["sh0.webp"] = _webp(texture([*dc_labels.T, alpha]))
    meta = {"version": 2, "asset": {"generator": "jaxedit"}, "count": n,
            "means": {"mins": lo.tolist(), "maxs": hi.tolist(), "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": dc_book.tolist(), "files": ["sh0.webp"]}}

    degree = s.sh_degree
    if degree > 0 and n:
        coeffs = _SH_COEFFS[degree]
        rest = s.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * coeffs)  # channel-major f_rest
        count = palette_size(n)
        centres, labels = kmeans(rest, count, iterations=iterations, seed=seed)
        book, centre_labels = codebook_1d(centres)  # [K', 3 * coeffs]
        rows = math.ceil(len(centres) / 64)
        cen = np.zeros((rows * 64, coeffs, 4), np.uint8)
        cen[:len(centres), :, :3] = centre_labels.reshape(-1, 3, coeffs).transpose(0, 2, 1)
        cen[:len(centres), :, 3] = 255
        files["shN_centroids.webp"] = _webp(cen.reshape(rows, 64 * coeffs, 4))
        files["shN_labels.webp"] = _webp(texture([(labels & 0xFF).astype(np.uint8),
                                                  (labels >> 8).astype(np.uint8),
                                                  np.zeros(n, np.uint8), full]))
        meta["shN"] = {"count": count, "bands": degree, "codebook": book.tolist(),
                       "files": ["shN_centroids.webp", "shN_labels.webp"]}
    files["meta.json"] = json.dumps(meta, separators=(",", ":")).encode()
    return files


def encode_sog(s: Splats, **kwargs) -> bytes:
    """The bytes of a ``.sog`` archive (the files of :func:`encode_files`, stored in a zip)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        files = encode_files(s, **kwargs)
        for name in ["meta.json", *sorted(k for k in files if k != "meta.json")]:
            zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), files[name])
    return buf.getvalue()


# --- decoding ------------------------------------------------------------------------


def _number_list(where, meta, key, field, length):
    value = meta.get(key, {}).get(field) if isinstance(meta.get(key), dict) else None
    if (not isinstance(value, list) or len(value) != length
            or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value)):
        raise DataError(where, f"meta.json: {key}.{field} must be a list of {length} finite numbers")
    return np.asarray(value, np.float64)


def _file_names(where, meta, key, count):
    value = meta.get(key, {}).get("files") if isinstance(meta.get(key), dict) else None
    if not isinstance(value, list) or len(value) != count or not all(isinstance(v, str) for v in value):
        raise DataError(where, f"meta.json: {key}.files must list {count} file name(s)")
    for name in value:
        if "/" in name or "\\" in name or name.startswith("."):
            raise DataError(where, f"meta.json: {key}.files holds {name!r}, not a plain file name")
    return value


def _texture(where, read, name: str, min_texels: int, max_texels: int) -> np.ndarray:
    """[H, W, 4] uint8 of WebP ``name``; its size is checked before it is decoded."""
    from PIL import Image

    data = read(name)
    try:
        img = Image.open(io.BytesIO(data), formats=["WEBP"])
    except Exception:  # PIL raises several types for a file it cannot identify
        raise DataError(where, f"{name}: not a WebP image") from None
    w, h = img.size
    if w > MAX_TEXTURE or h > MAX_TEXTURE or not min_texels <= w * h <= max_texels:
        raise DataError(where, f"{name}: a {w}x{h} texture for {min_texels} entries "
                               f"(expected between {min_texels} and {max_texels} texels)")
    try:
        return np.asarray(img.convert("RGBA"))
    except Exception as e:
        raise DataError(where, f"{name}: corrupt WebP ({e})") from None


def decode_files(read, where: str | os.PathLike = "sog") -> Splats:
    """The splats of a SOG whose files ``read(name) -> bytes`` returns (``meta.json`` first)."""
    try:
        meta = json.loads(read("meta.json"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(where, f"meta.json is not JSON ({e})") from None
    if not isinstance(meta, dict) or not {"version", "count", "means"} & set(meta):
        got = (f"keys {', '.join(sorted(map(str, meta))[:5]) or 'none'}" if isinstance(meta, dict)
               else "not a JSON object")
        raise DataError(where, f"not a SOG meta.json ({got}; a SOG's has version, count, means, "
                               f"...; give a .sog, a SOG meta.json or another splat file)")
    if meta.get("version") != 2:
        raise DataError(where, f"unsupported SOG version {meta.get('version')!r} (reads version 2)")
    n = meta.get("count")
    if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= MAX_TEXTURE ** 2:
        raise DataError(where, f"meta.json: count must be an integer in [0, {MAX_TEXTURE ** 2}], got {n!r}")
    width, height = texture_size(n)
    lo, hi = _number_list(where, meta, "means", "mins", 3), _number_list(where, meta, "means", "maxs", 3)
    scale_book = _number_list(where, meta, "scales", "codebook", 256)
    dc_book = _number_list(where, meta, "sh0", "codebook", 256)
    names = (_file_names(where, meta, "means", 2) + _file_names(where, meta, "quats", 1)
             + _file_names(where, meta, "scales", 1) + _file_names(where, meta, "sh0", 1))
    limit = 4 * width * height

    def tex(name):
        return _texture(where, read, name, n, limit).reshape(-1, 4)[:n]

    m_lo, m_hi, quats, scales, sh0 = (tex(name) for name in names)
    q16 = m_lo[:, :3].astype(np.float64) + 256.0 * m_hi[:, :3].astype(np.float64)
    logs = lo + (hi - lo) * q16 / 65535.0
    means = (np.sign(logs) * (np.exp(np.abs(logs)) - 1.0)).astype(np.float32)
    tag = quats[:, 3].astype(np.int64)
    if n and not ((tag >= 252) & (tag <= 255)).all():
        raise DataError(where, f"quats texture: alpha {int(tag[(tag < 252) | (tag > 255)][0])} at splat "
                               f"{int(np.argmax((tag < 252) | (tag > 255)))} is not 252..255")
    three = ((quats[:, :3].astype(np.float32) / 255.0) * 2.0 - 1.0) / np.float32(math.sqrt(2))
    q = with_largest(tag - 252, three)
    log_scales = scale_book[scales[:, :3]].astype(np.float32)
    dc = dc_book[sh0[:, :3]].astype(np.float32)
    opacity = logit(sh0[:, 3] / 255.0)

    shn = meta.get("shN")
    degree = 0
    if shn is not None:
        degree = shn.get("bands") if isinstance(shn, dict) else None
        if degree not in (1, 2, 3):
            raise DataError(where, f"meta.json: shN.bands must be 1, 2 or 3, got {degree!r}")
    sh = np.zeros((n, (degree + 1) ** 2, 3), np.float32)
    sh[:, 0, :] = dc
    if degree:
        coeffs = _SH_COEFFS[degree]
        count = shn.get("count")
        if not isinstance(count, int) or not 1 <= count <= 1 << 16:
            raise DataError(where, f"meta.json: shN.count must be an integer in [1, 65536], got {count!r}")
        book = _number_list(where, meta, "shN", "codebook", 256)
        cen_name, lab_name = _file_names(where, meta, "shN", 2)
        rows = math.ceil(count / 64)
        cen = _texture(where, read, cen_name, 64 * coeffs, 64 * coeffs * rows)
        if cen.shape[1] != 64 * coeffs:
            raise DataError(where, f"{cen_name}: width {cen.shape[1]}, {degree} SH bands need {64 * coeffs}")
        labels = tex(lab_name)
        label = labels[:, 0].astype(np.int64) + 256 * labels[:, 1].astype(np.int64)
        entries = cen.reshape(-1, coeffs, 4)  # palette entry -> coefficients -> rgba
        if n and label.max() >= min(count, len(entries)):
            raise DataError(where, f"{lab_name}: label {int(label.max())} beyond the palette of "
                                   f"{min(count, len(entries))}")
        sh[:, 1:, :] = book[entries[label, :, :3]].astype(np.float32)
    s = Splats(means, log_scales, q[:, :], opacity, sh)
    check_splats(where, s)
    return s


def _zip_reader(where, data: bytes):
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except zipfile.BadZipFile as e:
        raise DataError(where, f"not a .sog (zip) archive ({e})") from None
    infos = {i.filename: i for i in zf.infolist()}
    declared = sum(i.file_size for i in infos.values())
    if declared > min(MAX_UNZIPPED, RATIO * len(data) + (1 << 20)):
        raise DataError(where, f"archive entries declare {declared} bytes unpacked from {len(data)} "
                               f"(over the cap; a zip bomb?)")

    def read(name):
        if name not in infos:
            raise DataError(where, f"archive has no {name!r} (entries: {sorted(infos)[:10]})")
        try:
            return zf.read(name)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, NotImplementedError) as e:
            raise DataError(where, f"{name}: corrupt archive entry ({e})") from None
    return read


def _folder_reader(path: Path):
    def read(name):
        if name == "meta.json":
            name = path.name
        file = path.parent / name
        return read_file(file, "a SOG texture")[1]
    return read


def load_sog(path: str | os.PathLike) -> Gaussians:
    """Read a SOG: a ``.sog`` archive, or a ``meta.json`` with its textures beside it."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        return to_gaussians(decode_files(_folder_reader(path), path))
    path, data = read_file(path, "a .sog file")
    return to_gaussians(decode_files(_zip_reader(path, data), path))


def save_sog(path: str | os.PathLike, gaussians: Gaussians, *, iterations: int = 10,
             seed: int = 0) -> Path:
    """Write the alive Gaussians as SOG: a ``.sog`` archive, or for a ``.json`` path that
    meta.json with its textures beside it (each file written atomically). Returns the path."""
    path = Path(path)
    s = from_gaussians(gaussians, path)
    if path.suffix.lower() == ".json":
        files = encode_files(s, iterations=iterations, seed=seed)
        for name, data in files.items():
            if name != "meta.json":
                atomic_write_bytes(path.parent / name, data)
        atomic_write_bytes(path, files["meta.json"])
        return path
    with atomic_path(path) as tmp:
        tmp.write_bytes(encode_sog(s, iterations=iterations, seed=seed))
    return path
