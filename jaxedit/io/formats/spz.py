"""Niantic .spz (Scaniverse): v2-v3 (one gzip stream) and v4 (ZSTD streams), read and written.

Arrays, per splat, in this order (nianticlabs/spz ``load-spz.cc``; splat-transform's ``read-spz.ts``):
positions 3 x int24 fixed point (``fractionalBits``, 12 when we write), alphas u8 = sigmoid * 255,
colours u8 = dc * 0.15 * 255 + 127.5, scales u8 = (log s + 10) * 16, rotations (v2: x y z as
u8 = v * 127.5 + 127.5, w >= 0 derived; v3+: smallest three of (x, y, z, w) in 2 + 3 x 10 bits, a
sign and 9 magnitude bits each), SH u8 = round(v * 128) + 128 colour-interleaved (r, g, b of each
coefficient, unlike PLY's channel-major f_rest), rounded to 5 bits for degree 1 and 4 above.

Header: v2/v3, 16 bytes inside the gzip stream (magic "NGSP", version, count, SH degree,
fractional bits, flags, reserved); v4, 32 plain bytes (the same, then the stream count and the
offset of a table of (compressed, uncompressed) u64 sizes, one ZSTD stream per array).

Axes: the SPZ spec says RUB (OpenGL), PLY data is RDF, and a converter may flip y and z; the
Niantic library converts only when told the source's system, and splat-transform (and the web
viewers built on it) stores PLY axes unconverted. ``axes="ply"`` (the default) does the same;
``axes="rub"`` converts RDF <-> RUB (y, z negated; quaternion x kept, y, z negated; each SH
coefficient multiplied by its basis function's parity under (x, y, z) -> (x, -y, -z)).

SH degree 4 (a v4 extension): bands 0-3 are kept and band 4 is dropped with a warning.
"""

from __future__ import annotations

import gzip
import os
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from ...errors import DataError
from ...gaussians import Gaussians
from ..files import atomic_write_bytes
from ..ply import host_array
from .common import (Splats, check_splats, from_gaussians, largest_component, logit, need,
                     read_file, sigmoid, to_gaussians, unit_quats, with_largest)

MAGIC = 0x5053474E  # "NGSP" little-endian
VERSIONS = (2, 3, 4)
COLOR_SCALE = 0.15
FRACTIONAL_BITS = 12
#: The ZSTD level v4 streams are written at (level 6's lazier search finds little more in the
#: SH bytes and takes longer: benchmarks/formats.py), and the shortest match it looks for: the
#: arrays are quantised noise, where matches of 4-5 bytes rarely pay for themselves.
ZSTD_LEVEL = 5
ZSTD_MIN_MATCH = 6
_SH_COMPONENTS = {0: 0, 1: 9, 2: 24, 3: 45, 4: 72}
#: Most bytes one compressed byte inflates to: deflate's 258-byte matches at about 2 bits
#: each; ZSTD's RLE blocks (128 KiB from 4 bytes). A count needing more is refused unread.
DEFLATE_RATIO = 1040
ZSTD_RATIO = 1 << 15
#: Sign of each SH coefficient (k = 0..15) when y and z are negated: the parity of its basis
#: function (degree 1: y z x; degree 2: xy yz z2 xz x2-y2; degree 3 in the usual order).
RUB_SH_SIGNS = np.array([1, -1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)
_FLIP_YZ = np.array([1, -1, -1], np.float32)
_SH_TABLE = ((np.arange(256) - 128) / 128).astype(np.float32)
#: round(v * 128) + 128 -> the byte written, bucketed to 5 bits (degree 1, 8) or 4 bits (16).
_SH_BYTE = {b: np.minimum((np.arange(256) + b // 2) // b * b, 255).astype(np.uint8) for b in (8, 16)}


def flip_axes(s: Splats) -> Splats:
    """The splats under (x, y, z) -> (x, -y, -z), the RDF <-> RUB change (its own inverse)."""
    k = s.sh.shape[1]
    return Splats(s.means * _FLIP_YZ, s.log_scales,
                  s.quats * np.array([1, 1, -1, -1], np.float32), s.opacity_logits,
                  s.sh * RUB_SH_SIGNS[:k, None])


def _check_axes(axes: str) -> None:
    if axes not in ("ply", "rub"):
        raise DataError("axes", f"must be 'ply' or 'rub', got {axes!r}")


def _u8(x) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


# --- encoding ------------------------------------------------------------------------


def _arrays(s: Splats, version: int) -> list[bytes]:
    """The per-splat arrays (positions, alphas, colours, scales, rotations[, SH]) as bytes."""
    n = s.count
    # float32 is exact here: a power-of-two multiple, then rounded to an integer
    fixed = np.round(s.means * np.float32(1 << FRACTIONAL_BITS))
    if len(fixed) and np.abs(fixed).max() >= 1 << 23:
        raise DataError("spz", f"a position beyond +-{(1 << 23) / (1 << FRACTIONAL_BITS):g} does not fit "
                               f"SPZ's 24-bit fixed point with {FRACTIONAL_BITS} fractional bits")
    pos = fixed.astype("<i4").view(np.uint8).reshape(n, 3, 4)[:, :, :3].reshape(n, 9)
    alpha = _u8(sigmoid(s.opacity_logits) * 255.0)
    colour = _u8(s.sh[:, 0, :].astype(np.float64) * (COLOR_SCALE * 255.0) + 127.5)
    scale = _u8((s.log_scales.astype(np.float64) + 10.0) * 16.0)
    q = unit_quats(s.quats)[:, [1, 2, 3, 0]]  # (x, y, z, w)
    if version == 2:
        q = q * np.where(q[:, 3:] < 0, -1.0, 1.0)
        rot = _u8(q[:, :3] * 127.5 + 127.5)
    else:
        index, q = largest_component(q)
        word = np.zeros(n, np.uint32)
        for j in range(4):  # the three others in order, first in the highest bits
            v = q[:, j]
            code = ((v < 0).astype(np.uint32) << 9) | np.clip(
                np.round(np.abs(v) / np.sqrt(0.5) * 511), 0, 511).astype(np.uint32)
            word = np.where(index == j, word, (word << 10) | code)
        rot = (word | (index.astype(np.uint32) << 30)).astype("<u4")
    out = [pos.tobytes(), alpha.tobytes(), colour.tobytes(), scale.tobytes(), rot.tobytes()]
    if s.sh.shape[1] > 1:
        out.append(_sh_bytes(s.sh[:, 1:, :]).tobytes())
    return out


def _sh_bytes(rest: np.ndarray, step: int = 4096) -> np.ndarray:
    """uint8 [N, 3(K-1)]: ``rest`` [N, K-1, 3] (colour-interleaved already) as SPZ's SH bytes.

    Worked ``step`` rows at a time, in place, so each block stays in cache.
    """
    n, k = rest.shape[0], rest.shape[1]
    out = np.empty((n, 3 * k), np.uint8)
    first = 3 * min(k, 3)  # degree 1's bytes, 5 bits; the rest 4 bits
    for lo in range(0, n, step):
        rows = slice(lo, min(n, lo + step))
        t = rest[rows] * np.float32(128)
        np.rint(t, out=t)
        np.clip(t, -128, 127, out=t)
        t += np.float32(128)
        q = t.astype(np.uint8).reshape(len(t), 3 * k)
        out[rows, :first] = _SH_BYTE[8][q[:, :first]]
        out[rows, first:] = _SH_BYTE[16][q[:, first:]]
    return out


def encode(s: Splats, *, version: int = 4, axes: str = "ply", level: int | None = None) -> bytes:
    """The .spz bytes of ``s`` (finite values, non-zero quaternions).

    Args:
      version: 2 or 3 (one gzip stream) or 4 (ZSTD streams, the current version).
      axes: "ply" stores the PLY axes as they are (splat-transform's convention), "rub" converts.
      level: the compression level (gzip 1-9, default 6; ZSTD 1-22, default
        :data:`ZSTD_LEVEL`: splat-transform writes level 12, a smaller file written more slowly).
    """
    _check_axes(axes)
    if version not in VERSIONS:
        raise DataError("version", f"SPZ version must be one of {VERSIONS}, got {version}")
    if axes == "rub":
        s = flip_axes(s)
    degree, n = s.sh_degree, s.count
    arrays = _arrays(s, version)
    if version < 4:
        header = struct.pack("<IIIBBBB", MAGIC, version, n, degree, FRACTIONAL_BITS, 0, 0)
        return gzip.compress(header + b"".join(arrays), compresslevel=level or 6, mtime=0)
    import zstandard

    def compress(a: bytes) -> bytes:  # the level's parameters for this size, longer matches
        params = zstandard.ZstdCompressionParameters.from_level(
            level or ZSTD_LEVEL, source_size=len(a), min_match=ZSTD_MIN_MATCH, threads=-1)
        return zstandard.ZstdCompressor(compression_params=params).compress(a)

    streams = [compress(a) for a in arrays]
    toc = b"".join(struct.pack("<QQ", len(c), len(a)) for c, a in zip(streams, arrays))
    header = struct.pack("<IIIBBBBI", MAGIC, 4, n, degree, FRACTIONAL_BITS, 0, len(streams), 32)
    return header.ljust(32, b"\0") + toc + b"".join(streams)


# --- decoding ------------------------------------------------------------------------


def _header(where, data: bytes, size: int):
    if len(data) < size:
        raise DataError(where, f"{len(data)} bytes is too short for a {size}-byte SPZ header")
    magic, version, n, degree, frac, flags = struct.unpack_from("<IIIBBB", data)
    if magic != MAGIC:
        raise DataError(where, f"not an SPZ file (magic {magic:#010x}, expected {MAGIC:#010x} 'NGSP')")
    if version not in VERSIONS:
        raise DataError(where, f"unsupported SPZ version {version} (reads {VERSIONS})")
    if degree not in _SH_COMPONENTS:
        raise DataError(where, f"SPZ SH degree {degree} is not 0..4")
    if frac > 23:
        raise DataError(where, f"SPZ fractional bits {frac} > 23")
    return version, n, degree, frac, flags


def _sizes(n: int, degree: int, version: int) -> list[int]:
    sizes = [9 * n, n, 3 * n, 3 * n, (3 if version == 2 else 4) * n]
    return sizes + ([_SH_COMPONENTS[degree] * n] if degree else [])


def _gunzip(data: bytes, where) -> tuple[tuple, list[bytes]]:
    """(header fields, arrays) of a v2/v3 file: its header inflated first, then exactly the
    bytes its count implies (one more is a count/data disagreement, never inflated further)."""
    stream = zlib.decompressobj(wbits=31)
    try:
        head = stream.decompress(data, 16)
        version, n, degree, frac, flags = _header(where, head, 16)
        if version == 4:
            raise DataError(where, "SPZ version 4 inside a gzip stream (v4 files are not gzipped)")
        sizes = _sizes(n, degree, version)
        expected = sum(sizes)
        if expected > DEFLATE_RATIO * len(data):
            raise DataError(where, f"SPZ header declares {n} splats ({expected} bytes), more than "
                                   f"a {len(data)}-byte gzip stream can inflate to (a wrong count)")
        payload = stream.decompress(stream.unconsumed_tail, expected + 1)
    except zlib.error as e:
        raise DataError(where, f"corrupt gzip stream ({e})") from None
    if len(payload) > expected:
        raise DataError(where, f"SPZ payload holds more than the {expected} bytes {n} splats "
                               f"need (trailing data or a wrong count)")
    need(where, len(payload), n, sum(_sizes(1, degree, version)), "SPZ payload")
    if not stream.eof:
        raise DataError(where, "truncated gzip stream")
    if stream.unused_data:
        raise DataError(where, f"{len(stream.unused_data)} bytes after the gzip stream "
                               f"(trailing data)")
    out, offset = [], 0
    for size in sizes:
        out.append(payload[offset:offset + size])
        offset += size
    return (version, n, degree, frac, flags), out


def _unzstd(chunk: bytes, expected: int, where, i: int) -> bytes:
    """Stream ``i``: exactly ``expected`` bytes inflated from one ZSTD frame filling ``chunk``."""
    import zstandard

    try:  # a frame may declare its size (what decompress() would allocate): checked first
        declared = zstandard.frame_content_size(chunk)
    except zstandard.ZstdError:
        raise DataError(where, f"SPZ v4 stream {i} is not a ZSTD frame") from None
    if declared not in (-1, expected):
        raise DataError(where, f"SPZ v4 stream {i}'s frame declares {declared} bytes, "
                               f"the splats need {expected}")
    try:  # read_across_frames: bytes after the frame are read (and refused), not ignored
        reader = zstandard.ZstdDecompressor().stream_reader(chunk, read_across_frames=True)
        raw = reader.read(expected + 1)
    except zstandard.ZstdError as e:
        raise DataError(where, f"corrupt ZSTD stream {i} ({e})") from None
    if len(raw) != expected:
        more = "more than" if len(raw) > expected else f"{len(raw)} bytes,"
        raise DataError(where, f"SPZ v4 stream {i} holds {more} the {expected} bytes the "
                               f"count implies (a wrong count or a damaged stream)")
    return raw


def _streams(data: bytes, where) -> tuple[int, int, int, int, list[bytes]]:
    if data[:2] == b"\x1f\x8b":
        (version, n, degree, frac, _), out = _gunzip(data, where)
        return version, n, degree, frac, out
    version, n, degree, frac, _ = _header(where, data, 32)
    if version != 4:
        raise DataError(where, f"SPZ version {version} must be gzip-compressed (this file is not)")
    n_streams, toc = struct.unpack_from("<BI", data, 15)
    sizes = _sizes(n, degree, version)
    if n_streams != len(sizes):
        raise DataError(where, f"SPZ v4 declares {n_streams} streams, SH degree {degree} needs {len(sizes)}")
    need(where, len(data) - toc, n_streams, 16, "SPZ v4 stream table")
    if toc < 32:
        raise DataError(where, f"SPZ v4 stream table offset {toc} lies inside the header")
    # the whole table is checked against the count and the file before any stream is inflated
    chunks, offset = [], toc + 16 * n_streams
    for i, expected in enumerate(sizes):
        packed, unpacked = struct.unpack_from("<QQ", data, toc + 16 * i)
        if unpacked != expected:
            raise DataError(where, f"SPZ v4 stream {i} declares {unpacked} bytes, {n} splats need {expected}")
        need(where, len(data) - offset, packed, 1, f"SPZ v4 stream {i}")
        if expected > ZSTD_RATIO * packed + 64:
            raise DataError(where, f"SPZ v4 stream {i}: {packed} compressed bytes cannot inflate "
                                   f"to the {expected} bytes {n} splats need (a wrong count)")
        chunks.append((offset, packed, expected))
        offset += packed
    if offset != len(data):
        raise DataError(where, f"{len(data) - offset} bytes after the last SPZ v4 stream (trailing data)")
    out = [_unzstd(data[lo:lo + packed], expected, where, i)
           for i, (lo, packed, expected) in enumerate(chunks)]
    return version, n, degree, frac, out


def decode(data: bytes, where: str | os.PathLike = "spz", *, axes: str = "ply") -> Splats:
    """The splats of .spz bytes (any of v2-v4), in file order. DataError for a malformed file."""
    _check_axes(axes)
    version, n, degree, frac, (pos, alpha, colour, scale, rot, *sh) = _streams(data, where)
    # int24 little-endian -> the top three bytes of an int32, then an arithmetic shift
    word = np.zeros((n, 3, 4), np.uint8)
    word[..., 1:] = np.frombuffer(pos, np.uint8).reshape(n, 3, 3)
    fixed = word.view("<i4")[..., 0] >> 8
    means = fixed.astype(np.float32) * np.float32(1.0 / (1 << frac))  # exact: 24 bits, 2^-frac
    opacity = logit(np.frombuffer(alpha, np.uint8) / 255.0)
    dc = (np.frombuffer(colour, np.uint8).reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE
    log_scales = (np.frombuffer(scale, np.uint8).reshape(n, 3) / 16.0 - 10.0).astype(np.float32)
    if version == 2:
        xyz = np.frombuffer(rot, np.uint8).reshape(n, 3) / 127.5 - 1.0
        q = with_largest(np.full(n, 3), xyz.astype(np.float32))
    else:
        word = np.frombuffer(rot, "<u4").astype(np.uint32)
        index = (word >> 30).astype(np.int64)
        three = np.empty((n, 3), np.float32)
        for slot in range(3):  # the first component is in the highest bits
            code = (word >> (10 * (2 - slot))) & 0x3FF
            v = (code & 0x1FF).astype(np.float32) / 511 * np.float32(np.sqrt(0.5))
            three[:, slot] = np.where(code & 0x200, -v, v)
        q = with_largest(index, three)
    quats = q[:, [3, 0, 1, 2]]  # (x, y, z, w) -> (w, x, y, z)
    k = (min(degree, 3) + 1) ** 2
    coeffs = host_array((n, k, 3))  # filled once, in memory device_put adopts
    coeffs[:, 0, :] = dc
    if degree:
        rest = np.frombuffer(sh[0], np.uint8).reshape(n, -1, 3)[:, :k - 1]
        for lo in range(0, n, 4096):  # a block at a time: the table's output stays in cache
            coeffs[lo:lo + 4096, 1:, :] = _SH_TABLE[rest[lo:lo + 4096]]
        if degree == 4:
            warnings.warn(f"{where}: SPZ SH degree 4; band 4 dropped (jaxedit renders 0..3)",
                          stacklevel=2)
    s = Splats(means, log_scales, np.ascontiguousarray(quats), opacity, coeffs)
    check_splats(where, s)
    return flip_axes(s) if axes == "rub" else s


def load_spz(path: str | os.PathLike, *, axes: str = "ply") -> Gaussians:
    """Read a .spz file (v2-v4) into Gaussians (all alive, file order)."""
    path, data = read_file(path, "an .spz file")
    return to_gaussians(decode(data, path, axes=axes), owned=True)


def save_spz(path: str | os.PathLike, gaussians: Gaussians, *, version: int = 4,
             axes: str = "ply") -> Path:
    """Write the alive Gaussians as .spz (``version`` 2-4, ``axes`` as in :func:`encode`), atomically."""
    path = Path(path)
    atomic_write_bytes(path, encode(from_gaussians(gaussians, path), version=version, axes=axes))
    return path
