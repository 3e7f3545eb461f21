"""Local edits: relevance maps, regions and mask folders composed into the per-Gaussian
:func:`editable` mask; the rest is frozen."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError

#: ``--local`` values: ``auto`` (the editor's relevance) or ``off``.
LOCAL_MODES = ("auto", "off")
#: Editable at this lifted relevance; low, so Gaussians on the border get edited too.
GAUSSIAN_THRESHOLD = 0.1
#: A pixel's training image takes the edit when editable Gaussians hold this share of it.
OWNED = 0.5
MASK_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp")


def lift_relevance(gaussians, cameras, masks) -> jax.Array:
    """float32 [C]: each Gaussian's blending-weighted mean of ``masks`` float [B, H, W]
    over ``cameras`` [B] (0 where never drawn)."""
    from ..raster import accumulate_weights

    m = jnp.asarray(masks, jnp.float32)[..., None]
    sums = accumulate_weights(gaussians, cameras, jnp.concatenate([m, jnp.ones_like(m)], -1))
    return jnp.where(sums[:, 1] > 1e-8, sums[:, 0] / jnp.maximum(sums[:, 1], 1e-8), 0.0)


@dataclasses.dataclass(frozen=True)
class Region:
    """A box (``values`` = xmin, ymin, zmin, xmax, ymax, zmax) or a sphere (cx, cy, cz, r)."""

    kind: str
    values: tuple[float, ...]

    def spec(self) -> str:
        return f"{self.kind}:" + ",".join(f"{v:g}" for v in self.values)


_ARITY = {"box": 6, "sphere": 4}


def parse_region(text: str, where: str = "--region") -> Region:
    """``box:xmin,ymin,zmin,xmax,ymax,zmax`` or ``sphere:cx,cy,cz,r`` -> :class:`Region`."""
    kind, sep, rest = str(text).partition(":")
    kind = kind.strip().lower()
    if not sep or kind not in _ARITY:
        raise DataError(where, f"{text!r}: expected box:xmin,ymin,zmin,xmax,ymax,zmax or "
                               "sphere:cx,cy,cz,r")
    try:
        values = tuple(float(v) for v in rest.split(","))
    except ValueError:
        raise DataError(where, f"{text!r}: the values must be numbers") from None
    if len(values) != _ARITY[kind]:
        raise DataError(where, f"{text!r}: {kind} takes {_ARITY[kind]} numbers, "
                               f"got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise DataError(where, f"{text!r}: the values must be finite")
    if kind == "box" and not all(values[i] < values[i + 3] for i in range(3)):
        raise DataError(where, f"{text!r}: each min must be below its max")
    if kind == "sphere" and values[3] <= 0:
        raise DataError(where, f"{text!r}: the radius must be positive")
    return Region(kind, values)


def in_regions(regions, means) -> jax.Array:
    """bool [C]: the means [C, 3] inside the union of ``regions`` (all True for none)."""
    means = jnp.asarray(means)
    if not regions:
        return jnp.ones(means.shape[:1], bool)
    inside = jnp.zeros(means.shape[:1], bool)
    for r in regions:
        v = jnp.asarray(r.values, means.dtype)
        if r.kind == "box":
            inside |= jnp.all((means >= v[:3]) & (means <= v[3:]), -1)
        else:
            inside |= jnp.sum((means - v[:3]) ** 2, -1) <= v[3] ** 2
    return inside


def _mask_files(directory: Path) -> dict[str, Path]:
    files: dict[str, Path] = {}
    for p in sorted(directory.iterdir()):
        if p.is_file() and p.suffix.lower() in MASK_SUFFIXES:
            files.setdefault(p.stem, p)
    return files


def load_masks(directory, filenames, hw: tuple[int, int], originals=None) -> np.ndarray:
    """One mask per frame, float32 [N, H, W] in [0, 1] (the mean of its channels).

    Args:
      directory: the mask folder (a frame's mask has its file's stem, nerfstudio-style).
      filenames: the frames' ``file_path`` strings.
      hw: the views' (H, W); a mask at an integer multiple of it is box-averaged down.
      originals: per frame its ``original_file_path`` or None, the fallback mask name.

    Raises DataError for a missing folder or frame, a mask of another size, or all-empty masks.
    """
    from ..editors.masks import check_mask_file
    from ..io.images import read_image

    directory = Path(os.fspath(directory))
    if not directory.is_dir():
        raise DataError("--masks", f"{directory}: not a folder")
    files = _mask_files(directory)
    originals = list(originals) if originals is not None else [None] * len(filenames)

    def mask_of(frame, photo):
        for name in (frame, photo):
            if name is not None and Path(name).stem in files:
                return files[Path(name).stem]
        return None

    paths = [mask_of(f, o) for f, o in zip(filenames, originals)]
    missing = [(f, o) for f, o, p in zip(filenames, originals, paths) if p is None]
    if missing:
        (frame, photo), more = missing[0], len(missing) - 1
        also = f" or its photo {Path(photo).stem!r}" if photo else ""
        raise DataError("--masks", f"{directory}: no mask for frame {Path(frame).stem!r}{also}"
                                   + (f" and {more} more" if more else ""))
    out = np.zeros((len(filenames), *hw), np.float32)
    for path in paths:  # every file's size from its header, before any is decoded
        check_mask_file(path, hw)
    for i, path in enumerate(paths):
        img = np.asarray(read_image(path, background=(0.0, 0.0, 0.0)), np.float32)
        out[i] = _to_view_size(img.reshape(*img.shape[:2], -1).mean(-1), hw, path)
    if not np.any(out > 0.5):
        raise DataError("--masks", f"{directory}: every mask is empty (nothing to edit)")
    return out


def _to_view_size(mask: np.ndarray, hw: tuple[int, int], path) -> np.ndarray:
    """``mask`` float [h, w] box-averaged to (H, W) from an integer multiple of it."""
    (h, w), (H, W) = mask.shape, hw
    k = h // H if H else 0
    if (h, w) == (H, W):
        return mask
    if k > 1 and (h, w) == (k * H, k * W):
        return mask.reshape(H, k, W, k).mean(axis=(1, 3))
    raise DataError(path, f"mask is {w}x{h} px, its view {W}x{H} (or a whole multiple of it)")


def editable(gaussians, *, regions=(), relevance=None,
             threshold: float = GAUSSIAN_THRESHOLD) -> jax.Array:
    """bool [C]: alive, inside the regions and relevant (``relevance`` [C]); DataError if none."""
    inside = in_regions(regions, gaussians.means) & gaussians.alive
    if regions and not bool(jnp.any(inside)):
        raise DataError("--region", f"{' '.join(r.spec() for r in regions)}: contains no "
                                    "Gaussian of the scene")
    if relevance is not None:
        inside &= jnp.asarray(relevance) >= threshold
        if not bool(jnp.any(inside)):
            raise DataError("--local", f"no Gaussian has a relevance of {threshold:g} or more "
                                       "(inside the region)")
    return inside


def frozen_of(gaussians, editable_mask) -> jax.Array:
    """bool [C]: the alive Gaussians outside ``editable_mask`` (what the trainer freezes)."""
    return gaussians.alive & ~jnp.asarray(editable_mask, bool)


@dataclasses.dataclass(frozen=True)
class LocalSpec:
    """A run's ``--local`` mode, ``--region`` s (a union), ``--masks`` float [N, H, W] or None."""

    mode: str = "off"
    regions: tuple = ()
    masks: np.ndarray | None = None

    def __post_init__(self):
        if self.mode not in LOCAL_MODES:
            raise DataError("--local", f"must be one of {', '.join(LOCAL_MODES)}, "
                                       f"got {self.mode!r}")

    @property
    def active(self) -> bool:
        return self.mode == "auto" or bool(self.regions) or self.masks is not None


def render_editable(gaussians, cameras, editable_mask) -> np.ndarray:
    """float32 [B, H, W] in [0, 1]: each pixel's blending weight on editable Gaussians."""
    from ..raster import render
    from ..sh import C0

    e = jnp.asarray(editable_mask, gaussians.means.dtype)
    sh = jnp.zeros_like(gaussians.sh).at[:, 0, :].set(((e - 0.5) / C0)[:, None])
    g = dataclasses.replace(gaussians, sh=sh)
    out = [np.asarray(render(g, cameras[i], background=jnp.zeros(3)).rgb[..., 0])
           for i in range(len(cameras))]
    return np.clip(np.stack(out), 0.0, 1.0).astype(np.float32)


def training_masks(weights, owned: float = OWNED) -> np.ndarray:
    """float32 [B, H, W] of 0 / 1: ``weights`` >= ``owned`` (hard, since a soft blend keeps
    part of the photo in owned pixels)."""
    return (np.asarray(weights, np.float32) >= owned).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class LocalPlan:
    """``editable`` bool [C], view ``masks`` float [N, H, W], ``figures`` (schedule.json's
    ``"local"``) and lifted ``relevance`` float32 [C] (None for a region alone)."""

    editable: np.ndarray
    masks: np.ndarray
    figures: dict
    relevance: np.ndarray | None = None


def plan_local(spec: LocalSpec, gaussians, cameras, originals, *, editor=None, embedding=None,
               key=None) -> LocalPlan:
    """The :class:`LocalPlan` of a local edit: the editor's relevance of ``originals``
    [N, H, W, 3] (``auto``) times any user masks, lifted to the Gaussians."""
    import time

    from ..editors.base import relevance

    t0 = time.perf_counter()
    pixel = None if spec.masks is None else np.asarray(spec.masks, np.float32)
    if spec.mode == "auto":
        maps = np.stack([np.asarray(relevance(editor, originals[i], originals[i], embedding,
                                              jax.random.fold_in(key, i)), np.float32)
                         for i in range(len(originals))])
        pixel = maps if pixel is None else pixel * maps
    rel = None if pixel is None else lift_relevance(gaussians, cameras, pixel)
    ed = np.asarray(editable(gaussians, regions=spec.regions, relevance=rel))
    masks = training_masks(render_editable(gaussians, cameras, ed))
    figures = {"mode": spec.mode, "regions": [r.spec() for r in spec.regions],
               "user_masks": spec.masks is not None, "editable": int(ed.sum()),
               "frozen": int(np.sum(np.asarray(gaussians.alive) & ~ed)),
               "mask_fraction": float(masks.mean()),
               "seconds": time.perf_counter() - t0}
    return LocalPlan(ed, masks, figures, None if rel is None else np.asarray(rel, np.float32))


def heat_overlay(image, weight, colour=(1.0, 0.15, 0.0), strength: float = 0.6) -> np.ndarray:
    """float32 [H, W, 3]: ``image`` with ``weight`` [H, W] laid over it in ``colour``."""
    w = strength * np.clip(np.asarray(weight, np.float32), 0.0, 1.0)[..., None]
    return ((1.0 - w) * np.asarray(image, np.float32)
            + w * np.asarray(colour, np.float32)).astype(np.float32)


def write_overlays(folder, gaussians, cameras, images, editable_mask, relevance=None) -> list:
    """Write the relevance over ``images`` float [B, H, W, 3] as ``folder/view_XX.png`` (and
    :func:`save_gaussian_relevance`); the PNGs' paths."""
    from ..io import write_image

    folder = Path(os.fspath(folder))
    folder.mkdir(parents=True, exist_ok=True)
    weights = render_editable(gaussians, cameras, editable_mask)
    paths = []
    for i, (image, w) in enumerate(zip(images, weights)):
        paths.append(folder / f"view_{i:02d}.png")
        write_image(paths[-1], heat_overlay(image, w))
    save_gaussian_relevance(folder, gaussians, editable_mask, relevance)
    return paths


#: In a run's ``local/`` folder: the input scene's alive Gaussians' relevance.
GAUSSIANS_FILE = "gaussians.npz"


def save_gaussian_relevance(folder, gaussians, editable_mask, relevance=None) -> Path:
    """Write (and return) ``folder/gaussians.npz``: alive ``means`` float32 [K, 3],
    ``editable`` bool [K], ``relevance`` float32 [K]."""
    from ..io.files import atomic_write_bytes

    alive = np.asarray(gaussians.alive, bool)
    ed = np.asarray(editable_mask, bool)[alive]
    rel = ed.astype(np.float32) if relevance is None else \
        np.asarray(relevance, np.float32)[alive]
    import io

    buf = io.BytesIO()
    np.savez(buf, means=np.asarray(gaussians.means, np.float32)[alive], editable=ed,
             relevance=rel, lifted=np.asarray(relevance is not None))
    path = Path(os.fspath(folder)) / GAUSSIANS_FILE
    atomic_write_bytes(path, buf.getvalue())
    return path


def load_gaussian_relevance(folder) -> dict | None:
    """:func:`save_gaussian_relevance`'s arrays (``means``, ``editable``, ``relevance``,
    ``lifted``), or None when ``folder`` has none (a global edit); unreadable: DataError."""
    path = Path(os.fspath(folder)) / GAUSSIANS_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            out = {k: np.asarray(z[k]) for k in ("means", "editable", "relevance", "lifted")}
    except (OSError, ValueError, KeyError) as e:
        raise DataError(path, f"unreadable per-Gaussian relevance ({e})") from None
    n = len(out["means"])
    if out["means"].shape != (n, 3) or out["editable"].shape != (n,) or \
            out["relevance"].shape != (n,):
        raise DataError(path, "per-Gaussian relevance arrays of mismatched shapes")
    return out


#: The viewer's colours: relevance 0 .. 1, and Gaussians the input had not.
COLD, HOT, CHANGED = (0.15, 0.3, 0.9), (1.0, 0.15, 0.0), (1.0, 0.85, 0.0)


def relevance_colours(saved: dict, means) -> np.ndarray:
    """float32 [N, 3] colours of ``means`` [N, 3] by relevance; :data:`CHANGED` if not saved."""
    means = np.ascontiguousarray(np.asarray(means, np.float32))
    known = {row.tobytes(): i for i, row in
             enumerate(np.ascontiguousarray(np.asarray(saved["means"], np.float32)))}
    index = np.array([known.get(row.tobytes(), -1) for row in means], np.int64)
    rel = np.zeros(len(means), np.float32)
    rel[index >= 0] = np.asarray(saved["relevance"], np.float32)[index[index >= 0]]
    t = np.clip(rel, 0.0, 1.0)[:, None]
    out = (1.0 - t) * np.asarray(COLD, np.float32) + t * np.asarray(HOT, np.float32)
    out[index < 0] = CHANGED
    return out.astype(np.float32)


def blend(inside, outside, mask):
    """``mask`` [H, W] * inside + (1 - mask) * outside, images [H, W, 3]."""
    m = jnp.asarray(mask)[..., None]
    return m * jnp.asarray(inside) + (1.0 - m) * jnp.asarray(outside)
