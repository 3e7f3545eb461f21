"""A NumPy ray caster of textured analytic shapes, the built-in scenes' ground truth; it
shares only the camera convention with the splatter, and its view-independent shading
(ambient plus shadowed Lambertian lights) lets degree-0 colours explain every view."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..camera import Camera
from ..errors import DataError
from . import textures as T

KINDS = ("ellipsoid", "box", "plane")
_EPS = 1e-6


def rotation_xyz(degrees) -> np.ndarray:
    """float [3, 3] rotation Rz @ Ry @ Rx from Euler angles (degrees) about x, y, z."""
    ax, ay, az = np.radians(np.asarray(degrees, np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


@dataclasses.dataclass(frozen=True)
class Decal:
    """A picture projected orthographically onto the front (+x local) of an ellipsoid,
    blended over the albedo with a soft elliptical mask (uv (0.5, 0.5) at the front pole).

    Attributes:
      texture: the picture (with ``wrap="clamp"`` usually).
      center: (u, v) centre of the mask ellipse.
      radii: (u, v) radii of the mask ellipse.
      feather: width of the soft edge, as a fraction of the radii.
      taper: fraction the u radius shrinks from the centre row to the bottom (a jaw).
    """

    texture: T.Texture
    center: tuple[float, float] = (0.5, 0.5)
    radii: tuple[float, float] = (0.45, 0.5)
    feather: float = 0.25
    taper: float = 0.0


@dataclasses.dataclass(frozen=True)
class Shape:
    """One analytic surface.

    Attributes:
      name: a label (shown to editors through the object id -> name table).
      kind: "ellipsoid" (spheres too), "box" or "plane" (a finite rectangle).
      center: (x, y, z) world position.
      size: ellipsoid radii, box or plane (x, y, ignored z) half-extents, on the local axes.
      rotation: float ``[3][3]`` local->world rotation (see rotation_xyz).
      color: RGB albedo when there is no texture.
      texture: optional albedo picture (spheres: equirectangular; boxes: per face).
      decal: optional front-projected picture (ellipsoids only).
    """

    name: str
    kind: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    rotation: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    color: tuple[float, float, float] = (0.8, 0.8, 0.8)
    texture: T.Texture | None = None
    decal: Decal | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise DataError(f"Shape {self.name!r}.kind", f"unknown kind {self.kind!r} ({', '.join(KINDS)})")
        size = np.asarray(self.size, np.float64)
        need = 2 if self.kind == "plane" else 3
        if size.shape != (3,) or not np.all(size[:need] > 0):
            raise DataError(f"Shape {self.name!r}.size", f"needs {need} positive extents, got {self.size}")
        rot = np.asarray(self.rotation, np.float64)
        if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6):
            raise DataError(f"Shape {self.name!r}.rotation", "must be a 3x3 rotation matrix")
        if self.decal is not None and self.kind != "ellipsoid":
            raise DataError(f"Shape {self.name!r}.decal", "decals are only supported on ellipsoids")

    @property
    def R(self) -> np.ndarray:
        return np.asarray(self.rotation, np.float64)

    @property
    def c(self) -> np.ndarray:
        return np.asarray(self.center, np.float64)

    @property
    def s(self) -> np.ndarray:
        return np.asarray(self.size, np.float64)


def sphere(name, center, radius, **kw) -> Shape:
    return Shape(name, "ellipsoid", tuple(center), (radius, radius, radius), **kw)


def ellipsoid(name, center, radii, *, euler=(0, 0, 0), **kw) -> Shape:
    return Shape(name, "ellipsoid", tuple(center), tuple(radii),
                 rotation=tuple(map(tuple, rotation_xyz(euler))), **kw)


def box(name, center, half_extents, *, euler=(0, 0, 0), **kw) -> Shape:
    return Shape(name, "box", tuple(center), tuple(half_extents),
                 rotation=tuple(map(tuple, rotation_xyz(euler))), **kw)


def plane(name, center, half_xy, *, euler=(0, 0, 0), **kw) -> Shape:
    return Shape(name, "plane", tuple(center), (half_xy[0], half_xy[1], 0.0),
                 rotation=tuple(map(tuple, rotation_xyz(euler))), **kw)


@dataclasses.dataclass(frozen=True)
class Light:
    """A directional light. ``direction`` points from the surface towards the light."""

    direction: tuple[float, float, float]
    intensity: float = 0.7
    shadows: bool = True

    @property
    def d(self) -> np.ndarray:
        d = np.asarray(self.direction, np.float64)
        return d / np.linalg.norm(d)


@dataclasses.dataclass(frozen=True)
class Rig:
    """Cameras on a spiral over a band of the sphere of ``radius`` around ``target`` (+z up),
    azimuths ``azimuth_deg`` (0 = +x), elevations ``elevation_deg``, horizontal ``fov_deg``."""

    radius: float
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fov_deg: float = 40.0
    elevation_deg: tuple[float, float] = (5.0, 60.0)
    azimuth_deg: tuple[float, float] = (0.0, 360.0)


@dataclasses.dataclass(frozen=True)
class Scene:
    """A built-in scene: shapes (the ray caster's ``ids``), lights, background, camera rig."""

    name: str
    shapes: tuple[Shape, ...]
    lights: tuple[Light, ...]
    rig: Rig
    ambient: float = 0.35
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    description: str = ""

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.shapes)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """float [3] min and max corners of the axis-aligned box around every shape."""
        lo, hi = [], []
        for s in self.shapes:
            ext = s.s.copy()
            half = np.abs(s.R) @ ext
            lo.append(s.c - half)
            hi.append(s.c + half)
        return np.min(lo, axis=0), np.max(hi, axis=0)


def camera_rays(cam: Camera, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(origin float [3], unit directions float [H*s, W*s, 3]) through an s x s sub-grid
    of every pixel of one camera."""
    s = int(supersample)
    w2c = np.asarray(cam.world_to_camera, np.float64)
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    origin = -rot.T @ trans
    xs = (np.arange(cam.width * s) + 0.5) / s
    ys = (np.arange(cam.height * s) + 0.5) / s
    px, py = np.meshgrid(xs, ys)
    dirs_cam = np.stack([(px - float(cam.cx)) / float(cam.fx), (py - float(cam.cy)) / float(cam.fy),
                         np.ones_like(px)], axis=-1)
    dirs = dirs_cam @ rot  # camera->world is R^T: row vectors times R
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return origin, dirs


def _intersect_shape(shape: Shape, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Nearest hit distance t > eps of rays o [P,3] (or [3]) + t d [P,3]; inf where missed."""
    R, c, s = shape.R, shape.c, shape.s
    ol = (o - c) @ R  # world -> local: R^T x, with row vectors
    dl = d @ R
    ol = np.broadcast_to(ol, dl.shape)
    if shape.kind == "ellipsoid":
        os_, ds = ol / s, dl / s
        a = np.einsum("pi,pi->p", ds, ds)
        b = np.einsum("pi,pi->p", os_, ds)
        cc = np.einsum("pi,pi->p", os_, os_) - 1.0
        disc = b * b - a * cc
        ok = disc >= 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        t0 = (-b - sq) / a
        t1 = (-b + sq) / a
        t = np.where(t0 > _EPS, t0, np.where(t1 > _EPS, t1, np.inf))
        return np.where(ok, t, np.inf)
    if shape.kind == "box":
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            ta = (-s - ol) * inv
            tb = (s - ol) * inv
        par = dl == 0
        inside = np.abs(ol) <= s
        ta = np.where(par, -np.inf, ta)
        tb = np.where(par, np.where(inside, np.inf, -np.inf), tb)
        tnear = np.max(np.minimum(ta, tb), axis=-1)
        tfar = np.min(np.maximum(ta, tb), axis=-1)
        hit = tfar >= np.maximum(tnear, _EPS)
        t = np.where(tnear > _EPS, tnear, tfar)
        return np.where(hit, t, np.inf)
    # plane: local z = 0, |x| <= sx, |y| <= sy
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -ol[:, 2] / dl[:, 2]
    p = ol + t[:, None] * dl
    hit = (np.isfinite(t) & (t > _EPS) & (np.abs(p[:, 0]) <= s[0]) & (np.abs(p[:, 1]) <= s[1]))
    return np.where(hit, t, np.inf)


def _bounding_sphere(shape: Shape) -> tuple[np.ndarray, float]:
    return shape.c, float(np.linalg.norm(shape.s))


def _candidates(shape: Shape, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """bool [P]: rays that pass within the shape's bounding sphere (a cheap pre-test)."""
    c, r = _bounding_sphere(shape)
    oc = c - origins
    if oc.ndim == 1:  # one shared origin (a pinhole camera)
        along = dirs @ oc
        dist2 = oc @ oc - along * along
    else:
        along = np.einsum("pi,pi->p", oc, dirs)
        dist2 = np.einsum("pi,pi->p", oc, oc) - along * along
    return (dist2 <= r * r) & (along > -r)


def intersect(scene: Scene, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hits (t float [P], inf on a miss; ids int [P] into scene.shapes, -1 on a miss)
    of rays ``origins`` float [P, 3] or [3] + t ``dirs`` float [P, 3] (unit)."""
    dirs = np.asarray(dirs, np.float64).reshape(-1, 3)
    origins = np.asarray(origins, np.float64)
    best_t = np.full(dirs.shape[0], np.inf)
    best_id = np.full(dirs.shape[0], -1, np.int64)
    for i, shape in enumerate(scene.shapes):
        cand = np.flatnonzero(_candidates(shape, origins, dirs))
        if cand.size == 0:
            continue
        o = origins if origins.ndim == 1 else origins[cand]
        t = _intersect_shape(shape, o, dirs[cand])
        closer = t < best_t[cand]
        best_t[cand[closer]] = t[closer]
        best_id[cand[closer]] = i
    return best_t, best_id


def occluded(scene: Scene, points: np.ndarray, direction: np.ndarray, max_t: float = np.inf) -> np.ndarray:
    """bool [P]: does any shape block the ray from points [P, 3] along ``direction`` [3]?"""
    d = np.broadcast_to(np.asarray(direction, np.float64), points.shape)
    blocked = np.zeros(points.shape[0], bool)
    for shape in scene.shapes:
        cand = np.flatnonzero(_candidates(shape, points, d) & ~blocked)
        if cand.size:
            blocked[cand] = _intersect_shape(shape, points[cand], d[cand]) < max_t
    return blocked


@dataclasses.dataclass(frozen=True)
class _Local:
    normal: np.ndarray      # float [P, 3] world unit normals (outward)
    uv: np.ndarray          # float [P, 2] base texture coordinates (repetitions)
    chart: np.ndarray       # int [P] which uv chart (box face) a point is on
    decal_uv: np.ndarray | None  # float [P, 2] decal coordinates, or None
    front: np.ndarray | None     # float [P] local x of the unit-sphere point (decal side)


# Box faces: (axis, sign) -> (u, v) axes with u x v = -n, so pictures are not mirrored.
_BOX_FACES = {
    (0, 1): ((0, 1, 0), (0, 0, -1)), (0, -1): ((0, -1, 0), (0, 0, -1)),
    (1, 1): ((-1, 0, 0), (0, 0, -1)), (1, -1): ((1, 0, 0), (0, 0, -1)),
    (2, 1): ((0, 1, 0), (1, 0, 0)), (2, -1): ((1, 0, 0), (0, 1, 0)),
}


def _surface(shape: Shape, points: np.ndarray) -> _Local:
    """Normals and texture coordinates of world points [P, 3] lying on ``shape``."""
    R, c, s = shape.R, shape.c, shape.s
    q = (points - c) @ R
    tex = shape.texture
    if shape.kind == "ellipsoid":
        p = q / s
        p /= np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
        n_local = p / s  # gradient of |q/s|^2
        rep = np.asarray(tex.repeat if tex else (1.0, 1.0))
        u = (np.arctan2(p[:, 1], p[:, 0]) / (2 * np.pi) + 0.5) * rep[0]
        v = (np.arccos(np.clip(p[:, 2], -1.0, 1.0)) / np.pi) * rep[1]
        uv = np.stack([u, v], -1)
        chart = np.zeros(len(q), np.int64)
        decal_uv = front = None
        if shape.decal is not None:
            decal_uv = np.stack([0.5 + 0.5 * p[:, 1], 0.5 - 0.5 * p[:, 2]], -1)
            front = p[:, 0]
    elif shape.kind == "box":
        rel = q / s
        axis = np.argmax(np.abs(rel), axis=-1)
        sign = np.where(np.take_along_axis(rel, axis[:, None], 1)[:, 0] >= 0, 1, -1)
        n_local = np.zeros_like(q)
        n_local[np.arange(len(q)), axis] = sign
        uv = np.zeros((len(q), 2))
        chart = axis * 2 + (sign > 0)
        for (ax, sg), (ua, va) in _BOX_FACES.items():
            sel = (axis == ax) & (sign == sg)
            if not sel.any():
                continue
            ua, va = np.asarray(ua, np.float64), np.asarray(va, np.float64)
            hu, hv = np.abs(ua) @ s, np.abs(va) @ s
            cu, cv = q[sel] @ ua, q[sel] @ va
            if tex is not None and tex.tile is not None:
                uv[sel] = np.stack([(cu + hu) / tex.tile, (cv + hv) / tex.tile], -1)
            else:
                uv[sel] = np.stack([(cu + hu) / (2 * hu), (cv + hv) / (2 * hv)], -1)
        decal_uv = front = None
    else:  # plane
        n_local = np.broadcast_to(np.array([0.0, 0.0, 1.0]), q.shape)
        if tex is not None and tex.tile is not None:
            uv = np.stack([(q[:, 0] + s[0]) / tex.tile, (s[1] - q[:, 1]) / tex.tile], -1)
        else:
            uv = np.stack([(q[:, 0] + s[0]) / (2 * s[0]), (s[1] - q[:, 1]) / (2 * s[1])], -1)
        chart = np.zeros(len(q), np.int64)
        decal_uv = front = None
    normal = n_local @ R.T
    normal = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    return _Local(normal, uv, chart, decal_uv, front)


def _footprint(uv: np.ndarray, group: np.ndarray) -> np.ndarray:
    """float [H, W] texture footprint of ``uv`` [H, W, 2] from same-``group`` [H, W]
    neighbours (one-sided differences, so seams and silhouettes don't count)."""
    out = np.zeros(group.shape)
    for axis in (0, 1):
        diff = np.linalg.norm(np.diff(uv, axis=axis), axis=-1)
        same = np.diff(group, axis=axis) == 0
        diff = np.where(same, diff, np.inf)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 0)
        before = np.pad(diff, pad, constant_values=np.inf)
        pad[axis] = (0, 1)
        after = np.pad(diff, pad, constant_values=np.inf)
        d = np.minimum(before, after)
        out = np.maximum(out, np.where(np.isfinite(d), d, 0.0))
    return out


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _albedo(shape: Shape, local: _Local, sel_grid=None, footprint=None,
            decal_footprint=None) -> np.ndarray:
    """float [P, 3] albedo of points of one shape."""
    if shape.texture is None:
        base = np.broadcast_to(np.asarray(shape.color, np.float32), (len(local.uv), 3)).copy()
    else:
        base = T.sample(shape.texture, local.uv, footprint)
    if shape.decal is not None:
        dec = shape.decal
        col = T.sample(dec.texture, local.decal_uv, decal_footprint)
        dv = (local.decal_uv[:, 1] - dec.center[1]) / dec.radii[1]
        ru = dec.radii[0] * (1.0 - dec.taper * np.clip(dv, 0.0, 1.0))
        du = (local.decal_uv[:, 0] - dec.center[0]) / ru
        r = np.sqrt(du * du + dv * dv)
        # front half only: the projection is two-sided
        mask = _smoothstep((1.0 - r) / max(dec.feather, 1e-6)) * _smoothstep(local.front / 0.15)
        base = base * (1 - mask[:, None]) + col * mask[:, None]
    return base.astype(np.float32)


def _shade(scene: Scene, points: np.ndarray, normals: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
    """float [P] light factor: ambient + unshadowed Lambertian terms (two-sided normals)."""
    flip = np.einsum("pi,pi->p", normals, view_dirs) > 0
    n = np.where(flip[:, None], -normals, normals)
    shade = np.full(len(points), scene.ambient)
    offset = points + 1e-4 * n
    for light in scene.lights:
        lam = np.maximum(n @ light.d, 0.0)
        lit = lam > 0
        if light.shadows and lit.any():
            blocked = np.zeros(len(points), bool)
            blocked[lit] = occluded(scene, offset[lit], light.d)
            lam = np.where(blocked, 0.0, lam)
        shade += light.intensity * lam
    return shade


def _trace_grid(scene: Scene, origin: np.ndarray, dirs: np.ndarray, *, shading: bool = True):
    """Trace rays [H, W, 3] from one origin: dict of t, ids [H,W], points, normals [H,W,3],
    uv, decal_uv [H,W,2] (NaN off decals), and with ``shading`` rgb [H,W,3], hit [H,W]."""
    h, w = dirs.shape[:2]
    flat = dirs.reshape(-1, 3)
    t, ids = intersect(scene, origin, flat)
    hit = ids >= 0
    points = np.where(hit[:, None], origin + np.where(hit, t, 0.0)[:, None] * flat, np.nan)
    normals = np.full_like(points, np.nan)
    uv = np.full((len(flat), 2), np.nan)
    decal_uv = np.full((len(flat), 2), np.nan)
    chart = np.full(len(flat), -1, np.int64)
    locals_ = {}
    for i, shape in enumerate(scene.shapes):
        sel = ids == i
        if not sel.any():
            continue
        loc = _surface(shape, points[sel])
        locals_[i] = (sel, loc)
        normals[sel] = loc.normal
        uv[sel] = loc.uv
        chart[sel] = loc.chart
        if loc.decal_uv is not None:
            decal_uv[sel] = loc.decal_uv
    out = {"t": t.reshape(h, w), "ids": ids.reshape(h, w), "points": points.reshape(h, w, 3),
           "normals": normals.reshape(h, w, 3), "uv": uv.reshape(h, w, 2),
           "decal_uv": decal_uv.reshape(h, w, 2)}
    if not shading:
        return out
    group = (ids * 8 + chart).reshape(h, w)
    fp = _footprint(np.nan_to_num(uv).reshape(h, w, 2), group).reshape(-1)
    fpd = _footprint(np.nan_to_num(decal_uv).reshape(h, w, 2), group).reshape(-1)
    albedo = np.zeros((len(flat), 3), np.float32)
    for i, (sel, loc) in locals_.items():
        albedo[sel] = _albedo(scene.shapes[i], loc, footprint=fp[sel], decal_footprint=fpd[sel])
    rgb = np.broadcast_to(np.asarray(scene.background, np.float32), (len(flat), 3)).copy()
    if hit.any():
        shade = _shade(scene, points[hit], normals[hit], flat[hit])
        rgb[hit] = albedo[hit] * shade[:, None]
    out["rgb"] = np.clip(rgb, 0.0, 1.0).reshape(h, w, 3)
    out["hit"] = hit.reshape(h, w)
    return out


def _views(cameras: Camera):
    if cameras.batch_shape == ():
        return [cameras], False
    if len(cameras.batch_shape) != 1:
        raise DataError("cameras", f"expected one batch axis, got batch shape {cameras.batch_shape}")
    return [cameras[i] for i in range(len(cameras))], True


def render(scene: Scene, cameras: Camera, *, supersample: int = 2, alpha: bool = False) -> np.ndarray:
    """Ground-truth images of ``scene`` seen by ``cameras``.

    Args:
      scene: a :class:`Scene`.
      cameras: a batched Camera [N] (or a single one).
      supersample: every pixel averages s x s rays.
      alpha: also return coverage as a 4th channel (RGB is over ``scene.background``).
    Returns:
      float32 [N, H, W, 3] (or [N, H, W, 4]) in [0, 1] ([H, W, C] for a single camera).
    """
    if int(supersample) < 1:
        raise DataError("supersample", f"must be >= 1, got {supersample}")
    s = int(supersample)
    views, batched = _views(cameras)
    out = []
    for cam in views:
        origin, dirs = camera_rays(cam, s)
        g = _trace_grid(scene, origin, dirs)
        rgb = g["rgb"].reshape(cam.height, s, cam.width, s, 3).mean(axis=(1, 3))
        if alpha:
            a = g["hit"].astype(np.float32).reshape(cam.height, s, cam.width, s).mean(axis=(1, 3))
            rgb = np.concatenate([rgb, a[..., None]], -1)
        out.append(rgb.astype(np.float32))
    images = np.stack(out)
    return images if batched else images[0]


def surface_points_and_ids(scene: Scene, cameras: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What each pixel centre of ``cameras`` [N] sees: points float32 [N, H, W, 3] (NaN on
    background), ids int32 [N, H, W] into ``scene.shapes`` (-1 on background), uv float32
    [N, H, W, 2] (a decal's own where it has one; NaN on background)."""
    views, batched = _views(cameras)
    pts, ids, uvs = [], [], []
    for cam in views:
        origin, dirs = camera_rays(cam, 1)
        g = _trace_grid(scene, origin, dirs, shading=False)
        uv = g["uv"]
        has_decal = ~np.isnan(g["decal_uv"][..., 0])
        uv = np.where(has_decal[..., None], g["decal_uv"], uv)
        pts.append(g["points"].astype(np.float32))
        ids.append(g["ids"].astype(np.int32))
        uvs.append(uv.astype(np.float32))
    pts, ids, uvs = np.stack(pts), np.stack(ids), np.stack(uvs)
    return (pts, ids, uvs) if batched else (pts[0], ids[0], uvs[0])


def surface_area(shape: Shape) -> float:
    """Area of a shape's surface (ellipsoids: Knud Thomsen's approximation)."""
    a, b, c = shape.s
    if shape.kind == "ellipsoid":
        p = 1.6075
        return 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    if shape.kind == "box":
        return 8 * (a * b + a * c + b * c)
    return 4 * a * b


def sample_surface(shape: Shape, n: int, rng: np.random.Generator) -> np.ndarray:
    """float [n, 3] world points uniformly distributed (by area) on a shape's surface."""
    s = shape.s
    if shape.kind == "ellipsoid":
        bound = max(s[1] * s[2], s[0] * s[2], s[0] * s[1])
        out = []
        total = 0
        while total < n:
            u = rng.normal(size=(2 * n + 16, 3))
            u /= np.linalg.norm(u, axis=-1, keepdims=True)
            elem = np.sqrt((s[1] * s[2] * u[:, 0]) ** 2 + (s[0] * s[2] * u[:, 1]) ** 2
                           + (s[0] * s[1] * u[:, 2]) ** 2)
            keep = u[rng.uniform(size=len(u)) * bound < elem]
            out.append(keep)
            total += len(keep)
        local = np.concatenate(out)[:n] * s
    elif shape.kind == "box":
        areas = np.array([s[1] * s[2], s[1] * s[2], s[0] * s[2], s[0] * s[2], s[0] * s[1], s[0] * s[1]])
        face = rng.choice(6, size=n, p=areas / areas.sum())
        local = rng.uniform(-1.0, 1.0, size=(n, 3)) * s
        axis = face // 2
        sign = np.where(face % 2 == 0, -1.0, 1.0)
        local[np.arange(n), axis] = sign * s[axis]
    else:
        local = np.zeros((n, 3))
        local[:, :2] = rng.uniform(-1.0, 1.0, size=(n, 2)) * s[:2]
    return local @ shape.R.T + shape.c


def shaded_color(scene: Scene, points: np.ndarray, ids: np.ndarray, view_from: np.ndarray) -> np.ndarray:
    """float32 [P, 3] shaded colour of surface points [P, 3] on shapes ``ids`` [P] seen from
    positions ``view_from`` [P, 3] (sharpest texture level, no anti-aliasing)."""
    albedo = np.zeros((len(points), 3), np.float32)
    normals = np.zeros((len(points), 3))
    for i, shape in enumerate(scene.shapes):
        sel = ids == i
        if sel.any():
            loc = _surface(shape, points[sel])
            normals[sel] = loc.normal
            albedo[sel] = _albedo(shape, loc)
    view = points - view_from
    view /= np.maximum(np.linalg.norm(view, axis=-1, keepdims=True), 1e-12)
    shade = _shade(scene, points, normals, view)
    return np.clip(albedo * shade[:, None], 0.0, 1.0).astype(np.float32)
