"""Pinhole cameras as pytrees, in the OpenCV convention (x right, y down, +z forward), pixel
centres at integer + 0.5; a batch has a leading axis on every array field."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .errors import DataError

#: float32 dots at DEFAULT precision run in TF32 (10-bit mantissa) on NVIDIA GPUs.
_EXACT = jax.lax.Precision.HIGHEST

# nerfstudio / OpenGL camera axes (x right, y up, looking down -z) to OpenCV's.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera (or a batch of them along a leading axis).

    Attributes:
      world_to_camera: float [..., 4, 4], OpenCV world->camera rigid transform.
      fx, fy, cx, cy: float [...], focal lengths and principal point in pixels.
      width, height: static ints, image size in pixels.
    """

    world_to_camera: jax.Array
    fx: jax.Array
    fy: jax.Array
    cx: jax.Array
    cy: jax.Array
    width: int = dataclasses.field(metadata=dict(static=True))
    height: int = dataclasses.field(metadata=dict(static=True))

    def __post_init__(self):
        # Accept Python floats / lists; keep jax tracers untouched.
        for name in ("world_to_camera", "fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, (int, float, list, tuple)):
                object.__setattr__(self, name, np.asarray(value, np.float32))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.world_to_camera.shape[:-2])

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("a single Camera has no length")
        return self.batch_shape[0]

    def __getitem__(self, index) -> "Camera":
        return jax.tree_util.tree_map(lambda a: a[index], self)

    @property
    def rotation(self) -> jax.Array:
        """float [..., 3, 3], world->camera rotation."""
        return self.world_to_camera[..., :3, :3]

    @property
    def translation(self) -> jax.Array:
        """float [..., 3], world->camera translation."""
        return self.world_to_camera[..., :3, 3]

    def center(self) -> jax.Array:
        """float [..., 3], camera centre in world coordinates, -R^T t."""
        r, t = self.rotation, self.translation
        return -jnp.einsum("...ji,...j->...i", r, t, precision=_EXACT)

    def camera_to_world(self) -> jax.Array:
        """float [..., 4, 4], OpenCV camera->world transform."""
        return rigid_inverse(self.world_to_camera)

    def intrinsics(self) -> jax.Array:
        """float [..., 3, 3], the K matrix."""
        zero, one = jnp.zeros_like(self.fx), jnp.ones_like(self.fx)
        return jnp.stack([
            jnp.stack([self.fx, zero, self.cx], -1),
            jnp.stack([zero, self.fy, self.cy], -1),
            jnp.stack([zero, zero, one], -1),
        ], -2)

    def project(self, points: jax.Array) -> tuple[jax.Array, jax.Array]:
        """World points float [N, 3] -> (pixels float [N, 2], depth float [N]); one camera."""
        cam = jnp.matmul(points, self.rotation.T, precision=_EXACT) + self.translation
        z = cam[:, 2]
        safe = jnp.where(jnp.abs(z) > 1e-12, z, 1e-12)
        u = self.fx * cam[:, 0] / safe + self.cx
        v = self.fy * cam[:, 1] / safe + self.cy
        return jnp.stack([u, v], -1), z

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 halves it)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return dataclasses.replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx,
                                   cy=self.cy * sy, width=w, height=h)


def rigid_inverse(m):
    """Inverse of rigid 4x4 transforms [..., 4, 4] (rotation transposed)."""
    xp = jnp if isinstance(m, jax.Array) else np
    r = xp.swapaxes(m[..., :3, :3], -1, -2)
    t = -(jnp.einsum("...ij,...j->...i", r, m[..., :3, 3], precision=_EXACT) if xp is jnp
          else np.einsum("...ij,...j->...i", r, m[..., :3, 3]))
    top = xp.concatenate([r, t[..., None]], axis=-1)
    bottom = xp.broadcast_to(xp.asarray([0.0, 0.0, 0.0, 1.0], dtype=top.dtype),
                             top.shape[:-2] + (1, 4))
    return xp.concatenate([top, bottom], axis=-2)


#: Camera centres farther than this from the origin leave float32 too little precision.
MAX_DISTANCE = 1e6
#: Focal lengths beyond this many image widths: a vanishing field of view.
MAX_FOCAL_WIDTHS = 1e4
#: ... and below this fraction of the image size, one near 180 degrees.
MIN_FOCAL_WIDTHS = 1e-3


def check_cameras(cameras: Camera, where) -> None:
    """Raise :class:`DataError` naming ``where`` for cameras (one or a batch) no image can be
    rendered from: empty size, non-finite values, an absurd focal length, a far centre."""
    if cameras.width < 1 or cameras.height < 1:
        raise DataError(where, f"camera image size {cameras.width}x{cameras.height} has no pixels")
    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    intr = np.stack([np.asarray(getattr(cameras, k), np.float64).reshape(-1)
                     for k in ("fx", "fy", "cx", "cy")], -1)
    if not (np.isfinite(w2c).all() and np.isfinite(intr).all()):
        raise DataError(where, "a camera has a non-finite (NaN or inf) pose or intrinsic")
    size = max(cameras.width, cameras.height)
    for k, name in ((0, "fx"), (1, "fy")):
        f = intr[:, k]
        i = int(np.argmax(np.abs(f - np.clip(f, MIN_FOCAL_WIDTHS * size,
                                             MAX_FOCAL_WIDTHS * size))))
        if f[i] <= 0:
            raise DataError(where, f"camera {i}: focal length {name}={f[i]:g} px must be positive")
        if f[i] > MAX_FOCAL_WIDTHS * size:
            raise DataError(where, f"camera {i}: focal length {name}={f[i]:g} px for a {size} px "
                            "image is a field of view of almost zero: nothing would be visible")
        if f[i] < MIN_FOCAL_WIDTHS * size:
            raise DataError(where, f"camera {i}: focal length {name}={f[i]:g} px for a {size} px "
                            "image is a field of view of almost 180 degrees")
    centres = rigid_inverse(w2c)[:, :3, 3]
    dist = np.linalg.norm(centres, axis=-1)
    if dist.max() > MAX_DISTANCE:
        i = int(np.argmax(dist))
        raise DataError(where, f"camera {i} is {dist[i]:.3g} units from the origin: too far for "
                        f"float32 arithmetic (keep cameras within {MAX_DISTANCE:g})")


def stack(cameras: list[Camera]) -> Camera:
    """A batched Camera from single cameras of one size."""
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"cannot batch cameras of different sizes {sorted(sizes)}")
    return jax.tree_util.tree_map(lambda *a: np.stack([np.asarray(x) for x in a]), *cameras)


def opengl_c2w_to_opencv_w2c(c2w) -> np.ndarray:
    """nerfstudio/OpenGL camera-to-world [..., 4, 4] (or [..., 3, 4]) -> OpenCV world-to-camera."""
    c2w = np.asarray(c2w, np.float64)
    if c2w.shape[-2] == 3:
        bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], c2w.shape[:-2] + (1, 4))
        c2w = np.concatenate([c2w, bottom], axis=-2)
    return rigid_inverse(c2w @ OPENGL_TO_OPENCV)


def opencv_w2c_to_opengl_c2w(w2c) -> np.ndarray:
    """Inverse of :func:`opengl_c2w_to_opencv_w2c`."""
    return rigid_inverse(np.asarray(w2c, np.float64)) @ OPENGL_TO_OPENCV


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV world->camera [4, 4] at ``eye`` looking at ``target``, image up nearest ``up``."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
        right = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    return w2c


def make_camera(w2c, *, width: int, height: int, fov_deg: float | None = None,
                focal: float | None = None) -> Camera:
    """A camera with a centred principal point and a focal from ``focal`` or horizontal FOV."""
    if focal is None:
        fov = 60.0 if fov_deg is None else fov_deg
        focal = 0.5 * width / np.tan(np.radians(fov) / 2)
    return Camera(world_to_camera=np.asarray(w2c, np.float32), fx=float(focal), fy=float(focal),
                  cx=width / 2.0, cy=height / 2.0, width=width, height=height)


def orbit(n: int, *, radius: float, elevation_deg: float = 20.0, target=(0.0, 0.0, 0.0),
          width: int = 128, height: int = 128, fov_deg: float | None = None,
          focal: float | None = None, start_deg: float = 0.0) -> Camera:
    """``n`` cameras on a horizontal circle around ``target`` (a turntable), batched."""
    target = np.asarray(target, np.float64)
    el = np.radians(elevation_deg)
    cams = []
    for i in range(n):
        az = np.radians(start_deg) + 2 * np.pi * i / n
        eye = target + radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cams.append(make_camera(look_at(eye, target), width=width, height=height,
                                fov_deg=fov_deg, focal=focal))
    return stack(cams)


def hemisphere(n: int, *, radius: float, min_elevation_deg: float = 5.0,
               max_elevation_deg: float = 60.0, target=(0.0, 0.0, 0.0), width: int = 128,
               height: int = 128, fov_deg: float | None = None, focal: float | None = None) -> Camera:
    """``n`` cameras spread evenly (Fibonacci spiral) over a band of the upper hemisphere."""
    target = np.asarray(target, np.float64)
    golden = np.pi * (3.0 - np.sqrt(5.0))
    z_lo, z_hi = np.sin(np.radians(min_elevation_deg)), np.sin(np.radians(max_elevation_deg))
    cams = []
    for i in range(n):
        z = z_lo + (z_hi - z_lo) * (i + 0.5) / n
        r = np.sqrt(1.0 - z * z)
        az = golden * i
        eye = target + radius * np.array([r * np.cos(az), r * np.sin(az), z])
        cams.append(make_camera(look_at(eye, target), width=width, height=height,
                                fov_deg=fov_deg, focal=focal))
    return stack(cams)
