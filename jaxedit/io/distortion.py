"""The OpenCV radial-tangential lens model, its inverse, and exact image undistortion.

A normalised undistorted point (x, y) = ((u - cx) / fx, (v - cy) / fy) maps to

    r2 = x^2 + y^2
    radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

Undistorting an image samples the input at ``K distort(K^-1 (u, v))`` (same K);
:func:`valid_rectangle` crops to the pixels that have a source.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Distortion(NamedTuple):
    """Radial (k1..k4, on r^2..r^8) and tangential (p1, p2) coefficients."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def is_zero(self) -> bool:
        return all(v == 0.0 for v in self)


def distort_points(xy: np.ndarray, d: Distortion) -> np.ndarray:
    """float [..., 2] normalised undistorted points -> distorted points [..., 2]."""
    xy = np.asarray(xy, np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * (d.k3 + r2 * d.k4)))
    xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
    return np.stack([xd, yd], axis=-1)


def _distort_jacobian(x, y, d: Distortion):
    r2 = x * x + y * y
    radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * (d.k3 + r2 * d.k4)))
    dradial_dr2 = d.k1 + r2 * (2.0 * d.k2 + r2 * (3.0 * d.k3 + r2 * 4.0 * d.k4))
    # d(r2)/dx = 2x, d(r2)/dy = 2y
    dxd_dx = radial + x * dradial_dr2 * 2.0 * x + 2.0 * d.p1 * y + d.p2 * 6.0 * x
    dxd_dy = x * dradial_dr2 * 2.0 * y + 2.0 * d.p1 * x + d.p2 * 2.0 * y
    dyd_dx = y * dradial_dr2 * 2.0 * x + d.p1 * 2.0 * x + 2.0 * d.p2 * y
    dyd_dy = radial + y * dradial_dr2 * 2.0 * y + d.p1 * 6.0 * y + 2.0 * d.p2 * x
    return dxd_dx, dxd_dy, dyd_dx, dyd_dy


def undistort_points(xy_d: np.ndarray, d: Distortion, *, iterations: int = 20,
                     tol: float = 1e-12) -> np.ndarray:
    """Invert :func:`distort_points` by Newton's method.

    Args:
      xy_d: float [..., 2] normalised distorted points.
      d: the distortion coefficients.
      iterations: Newton steps at most.
    Returns:
      float [..., 2] undistorted points p with ``distort_points(p) ~= xy_d`` (the last
      iterate where the model is not invertible).
    """
    xy_d = np.asarray(xy_d, np.float64)
    xy = xy_d.copy()
    for _ in range(iterations):
        x, y = xy[..., 0], xy[..., 1]
        res = distort_points(xy, d) - xy_d
        a, b, c, e = _distort_jacobian(x, y, d)
        det = a * e - b * c
        det = np.where(np.abs(det) < 1e-12, np.copysign(1e-12, det), det)
        step_x = (e * res[..., 0] - b * res[..., 1]) / det
        step_y = (-c * res[..., 0] + a * res[..., 1]) / det
        xy = xy - np.stack([step_x, step_y], axis=-1)
        if np.max(np.abs(res), initial=0.0) < tol:
            break
    return xy


def bilinear_sample(image: np.ndarray, u: np.ndarray, v: np.ndarray, fill) -> np.ndarray:
    """Sample ``image`` float [H, W, C] at continuous pixel coordinates.

    Pixel centres at integer + 0.5; samples inside [0, W] x [0, H] clamp to the edge
    pixels, outside get ``fill`` (float [C]). Returns float [*u.shape, C].
    """
    from scipy import ndimage  # scipy ships with scikit-image

    h, w = image.shape[:2]
    inside = (u >= 0.0) & (u <= w) & (v >= 0.0) & (v <= h)  # False for NaN too
    # Index coordinates (centre of pixel i at i); clamping = mode "nearest".
    coords = np.stack([np.where(inside, v, 0.5) - 0.5, np.where(inside, u, 0.5) - 0.5])
    image = image.reshape(h, w, -1)
    out = np.stack([ndimage.map_coordinates(image[:, :, c], coords, order=1, mode="nearest",
                                            prefilter=False) for c in range(image.shape[2])], -1)
    return np.where(inside[..., None], out, np.asarray(fill, out.dtype))


def _source_coords(height: int, width: int, fx, fy, cx, cy, d: Distortion, rows=None):
    """(u, v) float64 [R, W]: where undistorted pixels of rows ``rows`` (start, stop; all
    by default) take their colour in the distorted image."""
    r0, r1 = rows or (0, height)
    v, u = np.meshgrid(np.arange(r0, r1) + 0.5, np.arange(width) + 0.5, indexing="ij")
    xy = np.stack([(u - cx) / fx, (v - cy) / fy], axis=-1)
    with np.errstate(over="ignore", invalid="ignore"):  # absurd coefficients -> no source
        xy_d = distort_points(xy, d)
        return xy_d[..., 0] * fx + cx, xy_d[..., 1] * fy + cy


#: Rows of the output computed at once by the remap builders (bounds their float64 temporaries).
_ROWS = 64


def source_inside(height: int, width: int, fx: float, fy: float, cx: float, cy: float,
                  d: Distortion) -> np.ndarray:
    """bool [H, W]: the undistorted pixels whose source lies in the captured H x W image
    (the rectangle [0, W] x [0, H], where :func:`bilinear_sample` does not fill)."""
    out = np.empty((height, width), bool)
    for r in range(0, height, _ROWS):
        us, vs = _source_coords(height, width, fx, fy, cx, cy, d, rows=(r, min(r + _ROWS,
                                                                               height)))
        out[r:r + _ROWS] = (us >= 0.0) & (us <= width) & (vs >= 0.0) & (vs <= height)
    return out


def valid_rectangle(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): an axis-aligned rectangle ``mask[y0:y1, x0:x1]`` that is all True.

    Greedy (large, not always the largest): the side holding the most False pixels moves
    in; an all-False mask gives an empty rectangle (x0 == x1 or y0 == y1).
    """
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    bad = np.zeros((h + 1, w + 1), np.int64)  # summed-area table of the False pixels
    bad[1:, 1:] = np.cumsum(np.cumsum(~mask, axis=0), axis=1)

    def count(a, b, c, e):  # False pixels in rows a:c, columns b:e
        return int(bad[c, e] - bad[a, e] - bad[c, b] + bad[a, b])

    x0, y0, x1, y1 = 0, 0, w, h
    while x0 < x1 and y0 < y1 and count(y0, x0, y1, x1):
        sides = (count(y0, x0, y0 + 1, x1), count(y1 - 1, x0, y1, x1),
                 count(y0, x0, y1, x0 + 1), count(y0, x1 - 1, y1, x1))
        side = int(np.argmax(sides))
        if side == 0:
            y0 += 1
        elif side == 1:
            y1 -= 1
        elif side == 2:
            x0 += 1
        else:
            x1 -= 1
    return x0, y0, x1, y1


class Remap(NamedTuple):
    """A bilinear resampling of a fixed set of continuous pixel coordinates, computed once
    and applied to every image of one camera (:func:`remap_table`, :func:`apply_remap`).

    Attributes:
      matrix: scipy.sparse CSR float32 [M, S]: each output pixel's 4 bilinear weights.
      inside: bool [M], the samples inside the source rectangle (others get ``fill``).
      shape: the output's (height, width) and the source's (height, width).
    """

    matrix: object
    inside: np.ndarray
    shape: tuple


def _bilinear_rows(u, v, height: int, width: int):
    """(columns int32 [M, 4], weights float32 [M, 4], inside bool [M]) of samples u, v."""
    inside = (u >= 0.0) & (u <= width) & (v >= 0.0) & (v <= height)
    x = np.clip(np.where(inside, u, 0.5) - 0.5, 0.0, width - 1).reshape(-1)
    y = np.clip(np.where(inside, v, 0.5) - 0.5, 0.0, height - 1).reshape(-1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    ax, ay = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    columns = np.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], 1)
    weights = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], 1)
    return columns.astype(np.int32), weights, inside.reshape(-1)


def _remap(parts, out_shape, height: int, width: int) -> Remap:
    from scipy import sparse

    columns = np.concatenate([p[0] for p in parts]).reshape(-1)
    weights = np.concatenate([p[1] for p in parts]).reshape(-1)
    inside = np.concatenate([p[2] for p in parts])
    m = inside.size
    matrix = sparse.csr_matrix((weights, columns, np.arange(0, 4 * m + 1, 4, dtype=np.int32)),
                               shape=(m, height * width))
    return Remap(matrix, inside, (out_shape[0], out_shape[1], height, width))


def remap_table(u: np.ndarray, v: np.ndarray, height: int, width: int) -> Remap:
    """The :class:`Remap` of sampling a ``height`` x ``width`` image at pixel coordinates
    ``u``, ``v`` float [H', W'] exactly as :func:`bilinear_sample` does (centres at
    integer + 0.5, edge pixels clamped, outside the rectangle filled)."""
    return _remap([_bilinear_rows(u, v, height, width)], u.shape, height, width)


def apply_remap(image: np.ndarray, table: Remap, fill) -> np.ndarray:
    """float32 [H', W', C]: ``image`` float [H, W, C] resampled by ``table``."""
    h, w, src_h, src_w = table.shape
    if image.shape[:2] != (src_h, src_w):
        raise ValueError(f"remap table is for {src_w}x{src_h} images, got "
                         f"{image.shape[1]}x{image.shape[0]}")
    flat = np.asarray(image, np.float32).reshape(src_h * src_w, -1)
    out = np.asarray(table.matrix @ flat, np.float32)
    out[~table.inside] = np.asarray(fill, np.float32)
    return out.reshape(h, w, -1)


def undistortion_table(height: int, width: int, fx: float, fy: float, cx: float, cy: float,
                       d: Distortion) -> Remap:
    """The :class:`Remap` of :func:`undistort_image` for a ``height`` x ``width`` camera
    (built a block of rows at a time: its temporaries stay small beside the table)."""
    parts = [_bilinear_rows(*_source_coords(height, width, fx, fy, cx, cy, d,
                                            rows=(r, min(r + _ROWS, height))), height, width)
             for r in range(0, height, _ROWS)]
    return _remap(parts, (height, width), height, width)


def undistort_image(image: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                    d: Distortion, *, fill=(1.0, 1.0, 1.0), table: Remap | None = None
                    ) -> np.ndarray:
    """The pinhole image (same K) seen by a camera with distortion ``d``.

    Args:
      image: float [H, W, C], as captured through the distorting lens.
      fx, fy, cx, cy: intrinsics in pixels (pixel centres at integer + 0.5).
      d: distortion coefficients.
      fill: value [C] for pixels whose source falls outside the captured image.
      table: :func:`undistortion_table` to reuse over one camera's images (None: built here).
    Returns:
      float32 [H, W, C], :func:`bilinear_sample` at the distorted positions.
    """
    if d.is_zero():
        return np.asarray(image, np.float32)
    if table is None:
        table = undistortion_table(image.shape[0], image.shape[1], fx, fy, cx, cy, d)
    return apply_remap(image, table, fill)
