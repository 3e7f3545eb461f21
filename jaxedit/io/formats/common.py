"""What every splat format shares: the NumPy splat table, byte checks, quantisation helpers.

The formats in this package convert between their bytes and :class:`Splats`, a frozen dataclass
of NumPy arrays in the INRIA 3DGS parameterisation (the fields of ``jaxedit.Gaussians`` without
the capacity and alive mask), and the ``load_*`` / ``save_*`` functions convert between
:class:`Splats` and ``Gaussians`` at the edge. Axes are the PLY's (x right, y down, z forward,
"RDF"); SH coefficients are [N, K, 3] (coefficient-major, channel last, DC first).

Every check of a reader raises :class:`jaxedit.errors.DataError` naming the file and the problem;
sizes declared by a file are checked against its length before anything is allocated.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import jax
import numpy as np

from ...errors import DataError
from ...gaussians import Gaussians
from ..ply import device_arrays

#: The SH DC normalisation (rgb = 0.5 + C0 * dc).
C0 = 0.28209479177387814

#: Largest file a reader reads whole (a scene of about 100 M Gaussians at SH degree 3 as a PLY).
MAX_FILE_BYTES = 1 << 35


@dataclasses.dataclass(frozen=True)
class Splats:
    """N Gaussians as float32 NumPy arrays (no capacity, no alive mask).

    Attributes:
      means: [N, 3] centres.
      log_scales: [N, 3] log standard deviations.
      quats: [N, 4] rotations (w, x, y, z), not necessarily unit.
      opacity_logits: [N] logit of opacity.
      sh: [N, K, 3] SH coefficients, K = (d+1)^2, DC first.
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    @property
    def count(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    def take(self, index: np.ndarray) -> "Splats":
        """The splats at ``index`` (an int array [M] or a bool mask [N]), in that order."""
        index = np.asarray(index)
        if index.dtype == bool:
            return Splats(*(np.ascontiguousarray(a[index]) for a in dataclasses.astuple(self)))
        # np.take, not a[index]: several times faster on rows of a few values
        return Splats(*(np.take(a, index, axis=0) for a in dataclasses.astuple(self)))


def from_gaussians(g: Gaussians, where: str | os.PathLike = "gaussians") -> Splats:
    """The alive Gaussians of ``g`` in slot order, as float32 NumPy arrays.

    Raises DataError (naming ``where``) when an alive Gaussian has a non-finite value or a zero
    quaternion: no format can store those faithfully, so nothing is written.
    """
    alive = np.asarray(g.alive, bool)
    fields = (g.means, g.log_scales, g.quats, g.opacity_logits, g.sh)
    if alive.all():  # the usual case: views of the arrays, no copy
        s = Splats(*(np.asarray(a, np.float32) for a in fields))
    else:
        s = Splats(*(np.asarray(a, np.float32)[alive] for a in fields))
    if s.sh.shape[1] not in (1, 4, 9, 16):
        raise DataError(where, f"{s.sh.shape[1]} SH coefficients is not (d+1)^2 for d in 0..3")
    check_splats(where, s, "alive Gaussian")
    return s


def check_splats(where, s: Splats, noun: str = "splat") -> None:
    """DataError naming ``where`` and the first bad ``noun``: a non-finite value or a zero quaternion."""
    for label, arr in (("position", s.means), ("scale", s.log_scales), ("rotation", s.quats),
                       ("opacity", s.opacity_logits), ("colour/SH", s.sh)):
        if np.isfinite(arr.sum(dtype=np.float64)):  # float32 values: finite iff all are
            continue
        bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
        if bad.any():
            raise DataError(where, f"non-finite {label} (NaN or inf) at {noun} {int(np.argmax(bad))} "
                                   f"({int(bad.sum())} bad); nothing written or read")
    zero = ~(np.abs(s.quats) > 0).any(axis=1)
    if zero.any():
        raise DataError(where, f"zero rotation quaternion at {noun} {int(np.argmax(zero))} "
                               f"({int(zero.sum())} bad)")


def to_gaussians(s: Splats, *, owned: bool = False) -> Gaussians:
    """A :class:`Gaussians` of capacity N with every slot alive.

    ``owned``: ``s`` is a reader's own and never written again, so its aligned arrays become
    the device buffers uncopied (:func:`jaxedit.io.ply.device_arrays`); otherwise each is copied.
    """
    arrays = dict(means=s.means, log_scales=s.log_scales, quats=s.quats,
                  opacity_logits=s.opacity_logits, sh=s.sh, alive=np.ones((s.count,), bool))
    # device_put, not jnp.asarray: the latter compiles a copy program per array shape
    return Gaussians(**device_arrays(arrays, owned=owned))


# --- bytes ---------------------------------------------------------------------------


def read_file(path: str | os.PathLike, what: str) -> tuple[Path, bytes]:
    """(path, its bytes); DataError for a missing, unreadable, oversized file or a folder."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if path.is_dir():
            raise DataError(path, f"is a directory, expected {what}")
        if size > MAX_FILE_BYTES:
            raise DataError(path, f"file of {size} bytes is larger than the {MAX_FILE_BYTES} "
                                  f"bytes a scene file may have")
        return path, path.read_bytes()
    except FileNotFoundError:
        raise DataError(path, "file not found") from None
    except OSError as e:
        raise DataError(path, f"cannot read file ({e.strerror or e})") from None


def need(where, available: int, count: int, item_bytes: int, what: str) -> None:
    """DataError unless ``count`` items of ``item_bytes`` fit in ``available`` bytes.

    Called before allocating anything sized by a count read from a file.
    """
    if count < 0 or count * item_bytes > available:
        raise DataError(where, f"{what}: {count} items of {item_bytes} bytes need "
                               f"{count * item_bytes} bytes, {max(available, 0)} present "
                               f"(truncated file or a wrong count)")


# --- shared encodings ----------------------------------------------------------------


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def logit(p: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """float32 logit of ``p`` clipped to [eps, 1 - eps] (a byte of 0 or 255 stays finite)."""
    p = np.clip(np.asarray(p, np.float64), eps, 1.0 - eps)
    return np.log(p / (1.0 - p)).astype(np.float32)


def unit_quats(q: np.ndarray) -> np.ndarray:
    """float64 [N, 4] quaternions divided by their norm (callers rule out zero ones)."""
    q = np.asarray(q, np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def largest_component(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index [N] of the largest |component|, the quaternions [N, 4] signed so it is >= 0).

    Ties go to the lowest index, as in the tools' smallest-three encoders.
    """
    index = np.argmax(np.abs(q), axis=1)
    sign = np.where(np.take_along_axis(q, index[:, None], 1) < 0, -1.0, 1.0)
    return index, q * sign


#: For each dropped component 0..3, the other three in order.
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def others(index: np.ndarray, q: np.ndarray) -> np.ndarray:
    """[N, 3]: the three components of each quaternion other than ``index``, in order."""
    return np.take_along_axis(q, _OTHERS[index], axis=1)


def with_largest(index: np.ndarray, three: np.ndarray) -> np.ndarray:
    """Inverse of :func:`others`: [N, 4] with the dropped component sqrt(1 - |three|^2) >= 0."""
    n = len(three)
    q = np.empty((n, 4), np.float32)
    index = np.asarray(index, np.int64)
    np.put_along_axis(q, _OTHERS[index], three, axis=1)
    largest = np.sqrt(np.maximum(0.0, 1.0 - (three.astype(np.float64) ** 2).sum(1)))
    np.put_along_axis(q, index[:, None], largest[:, None], axis=1)
    return q


def morton_order(means: np.ndarray, bits: int = 10) -> np.ndarray:
    """int [N] permutation sorting the points along a Z-order curve over their bounding box.

    Each axis is quantised to ``bits`` bits over [min, max] and the bits interleaved (x lowest),
    so that splats close in space land close in the file: what the chunked formats compress.
    """
    means = np.asarray(means, np.float32)
    if len(means) == 0:
        return np.zeros((0,), np.int64)
    lo, hi = means.min(0), means.max(0)
    extent = np.where(hi - lo > 0, hi - lo, 1.0).astype(np.float32)
    top = (1 << bits) - 1
    code = np.zeros(len(means), np.uint32 if bits <= 10 else np.uint64)
    for axis in range(3):
        v = np.clip((means[:, axis] - lo[axis]) / extent[axis] * top, 0, top).astype(code.dtype)
        code |= _spread_bits(v, bits) << code.dtype.type(axis)
    if bits > 10 or len(means) >= 1 << 32:
        return np.argsort(code, kind="stable")
    # The stable argsort as one sort of distinct keys (code, index): a few times faster.
    key = (code.astype(np.uint64) << np.uint64(32)) | np.arange(len(code), dtype=np.uint64)
    key.sort()
    return (key & np.uint64(0xFFFFFFFF)).astype(np.int64)


def _spread_bits(v: np.ndarray, bits: int) -> np.ndarray:
    """``v`` with bit b moved to bit 3b (the Morton interleave of one axis)."""
    if bits <= 10:  # the usual shift-and-mask spread of a 10-bit value over 30 bits
        v = v.astype(np.uint32)
        for shift, mask in ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249)):
            v = (v | (v << np.uint32(shift))) & np.uint32(mask)
        return v
    out = np.zeros_like(v)
    for b in range(bits):
        out |= ((v >> b) & 1) << (3 * b)
    return out
