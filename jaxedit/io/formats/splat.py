"""antimatter15 .splat: no header, 32 bytes a splat, no view-dependent colour.

Per splat (little-endian): position 3 x float32, scale 3 x float32 (exp of the log-scale), colour
RGBA 4 x u8 (rgb = (0.5 + C0 * dc) * 255, a = sigmoid(opacity) * 255), rotation 4 x u8
(q / |q| * 128 + 128, w first). Writing drops SH above degree 0; reading gives degree 0.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...errors import DataError
from ...gaussians import Gaussians
from ..files import atomic_write_bytes
from .common import (C0, Splats, check_splats, from_gaussians, logit, read_file, sigmoid, to_gaussians,
                     unit_quats)

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def encode(s: Splats) -> bytes:
    """The .splat bytes of ``s`` (file order = ``s`` order; SH above the DC dropped)."""
    rec = np.empty(s.count, RECORD)
    rec["position"] = s.means
    rec["scale"] = np.exp(s.log_scales.astype(np.float64))
    rgb = (0.5 + C0 * s.sh[:, 0, :].astype(np.float64)) * 255.0
    rec["rgba"] = np.clip(np.round(np.concatenate([rgb, sigmoid(s.opacity_logits)[:, None] * 255.0], 1)),
                          0, 255).astype(np.uint8)
    rec["rot"] = np.clip(np.round(unit_quats(s.quats) * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return rec.tobytes()


def decode(data: bytes, where: str | os.PathLike = "splat") -> Splats:
    """The splats of .splat bytes. DataError when the length is not a multiple of 32 or a
    record is bad (a zero rotation, a scale that is not positive and finite)."""
    if len(data) % RECORD.itemsize:
        raise DataError(where, f"{len(data)} bytes is not a whole number of {RECORD.itemsize}-byte "
                               f"splats (truncated or not a .splat file)")
    rec = np.frombuffer(data, RECORD)
    scale = rec["scale"].astype(np.float64)
    bad = ~(np.isfinite(scale) & (scale > 0)).all(axis=1)
    if bad.any():
        raise DataError(where, f"scale that is not positive and finite at splat {int(np.argmax(bad))} "
                               f"({int(bad.sum())} bad; not a .splat file?)")
    rgba = rec["rgba"].astype(np.float32) / 255.0
    dc = ((rgba[:, :3] - 0.5) / C0)[:, None, :]
    quats = (rec["rot"].astype(np.float32) - 128.0) / 128.0
    s = Splats(np.ascontiguousarray(rec["position"]), np.log(scale).astype(np.float32), quats,
               logit(rgba[:, 3]), dc.astype(np.float32))
    check_splats(where, s)
    return s


def load_splat(path: str | os.PathLike) -> Gaussians:
    """Read an antimatter15 .splat file into Gaussians (SH degree 0, all alive)."""
    path, data = read_file(path, "a .splat file")
    return to_gaussians(decode(data, path))


def save_splat(path: str | os.PathLike, gaussians: Gaussians) -> Path:
    """Write the alive Gaussians as an antimatter15 .splat (SH above the DC dropped), atomically."""
    path = Path(path)
    atomic_write_bytes(path, encode(from_gaussians(gaussians, path)))
    return path
