"""The built-in scenes (procedural ``seed -> Scene``, or rendered datasets shipped under
``scenes/data/NAME``) and their camera rigs; +z up, units of about a metre."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera, look_at, make_camera, stack
from ..errors import DataError
from . import raycast as rc
from .textures import Texture, mean_color

# Crops (rows, cols) of the 512 x 512 astronaut picture: her face, her hair.
_FACE_CROP = (15, 200, 150, 300)
_HAIR_CROP = (28, 62, 190, 280)


def face(seed: int = 0) -> rc.Scene:
    """A head wearing the astronaut's face, neck and shoulders (IN2N "face" analogue)."""
    del seed  # the benchmark scene never changes
    face_tex = Texture("astronaut", crop=_FACE_CROP, wrap="clamp")
    hair = Texture("astronaut", crop=_HAIR_CROP, repeat=(6.0, 3.0), wrap="mirror")
    skin = tuple(mean_color(Texture("astronaut", crop=(120, 160, 195, 255))))
    suit = Texture("astronaut", crop=(280, 340, 60, 120), repeat=(3.0, 1.0), wrap="mirror")
    shapes = (
        rc.ellipsoid("head", (0.0, 0.0, 0.3), (0.72, 0.62, 0.85), color=skin,
                     decal=rc.Decal(face_tex, center=(0.5, 0.47), radii=(0.56, 0.5), feather=0.25,
                                    taper=0.55)),
        # set back and up: where it pokes out of the head it is the hair
        rc.ellipsoid("hair", (-0.08, 0.0, 0.34), (0.71, 0.7, 0.86), texture=hair),
        rc.ellipsoid("neck", (-0.05, 0.0, -0.55), (0.3, 0.3, 0.45), color=skin),
        rc.ellipsoid("shoulders", (-0.1, 0.0, -1.1), (0.6, 1.2, 0.42), texture=suit),
    )
    lights = (rc.Light((1.0, 0.6, 1.2), 0.55), rc.Light((0.6, -1.0, 0.3), 0.25, shadows=False))
    rig = rc.Rig(radius=3.6, target=(0.0, 0.0, 0.0), fov_deg=40.0, elevation_deg=(-10.0, 35.0),
                 azimuth_deg=(-100.0, 100.0))
    return rc.Scene("face", shapes, lights, rig, ambient=0.42,
                    description="head wearing the astronaut's face (IN2N 'face' analogue)")


def tabletop(seed: int = 0) -> rc.Scene:
    """Textured objects on a stone table top; seeds other than 0 jitter position and yaw."""
    rng = np.random.default_rng(seed)
    jit = (lambda scale: rng.uniform(-scale, scale, size=2)) if seed else (lambda scale: np.zeros(2))
    yaw = (lambda: float(rng.uniform(-30, 30))) if seed else (lambda: 0.0)

    def at(x, y, z, scale=0.12):
        dx, dy = jit(scale)
        return (x + dx, y + dy, z)

    stone = Texture("gravel", tint=(0.95, 0.85, 0.7), tile=1.0, wrap="mirror")
    shapes = (
        rc.box("table", (0.0, 0.0, -0.05), (1.5, 1.1, 0.05), texture=stone),
        rc.sphere("cat_ball", at(-0.55, 0.45, 0.35), 0.35,
                  texture=Texture("chelsea", repeat=(2.0, 1.0), wrap="mirror")),
        rc.box("coffee_box", at(0.45, 0.45, 0.25), (0.25, 0.25, 0.25), euler=(0, 0, 20 + yaw()),
               texture=Texture("coffee", crop=(0, 400, 100, 500))),
        rc.box("rocket_box", at(0.5, -0.45, 0.4), (0.18, 0.12, 0.4), euler=(0, 0, -15 + yaw()),
               texture=Texture("rocket", crop=(0, 427, 150, 500))),
        rc.ellipsoid("egg", at(-0.45, -0.4, 0.3), (0.22, 0.22, 0.3), euler=(0, 0, yaw()),
                     texture=Texture("retina", crop=(300, 1100, 300, 1100), repeat=(2.0, 1.0),
                                     wrap="mirror")),
        rc.sphere("red_ball", at(0.05, 0.0, 0.14, 0.05), 0.14, color=(0.85, 0.15, 0.1)),
    )
    lights = (rc.Light((0.5, 0.35, 1.0), 0.6), rc.Light((-0.6, -0.3, 0.5), 0.2, shadows=False))
    rig = rc.Rig(radius=4.2, target=(0.0, 0.0, 0.2), fov_deg=45.0, elevation_deg=(15.0, 65.0))
    return rc.Scene("tabletop", shapes, lights, rig, ambient=0.35,
                    description="textured objects on a stone table (indoor analogue)")


def fence(seed: int = 0) -> rc.Scene:
    """Thin, high-frequency structure: a picket fence before a brick wall, on grass."""
    del seed
    grass = Texture("grass", tint=(0.45, 0.8, 0.35), tile=0.8, wrap="mirror")
    brick = Texture("brick", tint=(0.95, 0.55, 0.42), tile=0.9, wrap="mirror")
    wood = (0.92, 0.9, 0.85)
    shapes = [
        rc.plane("lawn", (0.0, 0.0, 0.0), (1.8, 1.8), texture=grass),
        rc.box("wall", (-0.5, 0.0, 0.5), (0.12, 1.4, 0.5), texture=brick),
        rc.box("rail_low", (0.35, 0.0, 0.25), (0.02, 1.25, 0.03), color=wood),
        rc.box("rail_high", (0.35, 0.0, 0.65), (0.02, 1.25, 0.03), color=wood),
    ]
    for k, y in enumerate(np.linspace(-1.17, 1.17, 14)):
        shapes.append(rc.box(f"picket_{k}", (0.39, float(y), 0.42), (0.02, 0.02, 0.42), color=wood))
    lights = (rc.Light((0.8, 0.5, 1.0), 0.6), rc.Light((-0.5, -0.6, 0.6), 0.2, shadows=False))
    rig = rc.Rig(radius=4.3, target=(0.0, 0.0, 0.35), fov_deg=45.0, elevation_deg=(10.0, 60.0))
    return rc.Scene("fence", tuple(shapes), lights, rig, ambient=0.35,
                    description="picket fence before a brick wall on grass (thin structures)")


def ball(seed: int = 0) -> rc.Scene:
    """One textured sphere: the smallest scene, for fast tests."""
    del seed
    shapes = (rc.sphere("ball", (0.0, 0.0, 0.0), 0.8,
                        texture=Texture("chelsea", repeat=(2.0, 1.0), wrap="mirror")),)
    lights = (rc.Light((0.6, 0.4, 1.0), 0.6),)
    rig = rc.Rig(radius=3.5, fov_deg=40.0, elevation_deg=(-30.0, 60.0))
    return rc.Scene("ball", shapes, lights, rig, description="one textured sphere (for tests)")


SCENES = {"face": face, "tabletop": tabletop, "fence": fence, "ball": ball}

#: Rendered scenes shipped as datasets: name -> description.
DATASETS = {
    "person": "head and shoulders of a photo-textured man (Reallusion model, CC BY 3.0), "
              "80 Blender Cycles views at 256 px on a frontal arc, RGBA",
}


def list_scenes() -> list[str]:
    """Names of the built-in scenes: the procedural ones, then the rendered datasets."""
    return [*SCENES, *DATASETS]


def _unknown(name: str) -> DataError:
    return DataError("scene", f"unknown scene {name!r}; built-in scenes: "
                              f"{', '.join(list_scenes())}")


def get_scene(name: str, seed: int = 0) -> rc.Scene:
    """The procedural scene ``name`` for ``seed``; other names raise DataError."""
    if name in DATASETS:
        raise DataError("scene", f"{name!r} is a rendered dataset, not a procedural scene; "
                                 f"write it with make_scene or read dataset_path({name!r})")
    if name not in SCENES:
        raise _unknown(name)
    return SCENES[name](int(seed))


def dataset_path(name: str) -> Path:
    """The folder of the rendered scene ``name`` inside the installed package."""
    if name not in DATASETS:
        raise _unknown(name)
    path = Path(__file__).parent / "data" / name
    if not (path / "transforms.json").is_file():
        raise DataError(path, "the rendered scene's files are missing from this installation "
                              "(package data of jaxedit.scenes)")
    return path


def rig_cameras(rig: rc.Rig, n: int, *, width: int = 128, height: int | None = None) -> Camera:
    """``n`` cameras [n] on an equal-area golden-ratio spiral over the rig's band, so any
    prefix of views covers it evenly."""
    if n < 1:
        raise DataError("views", f"need at least one camera, got {n}")
    height = width if height is None else height
    target = np.asarray(rig.target, np.float64)
    lo, hi = np.sin(np.radians(rig.elevation_deg[0])), np.sin(np.radians(rig.elevation_deg[1]))
    a0, a1 = np.radians(rig.azimuth_deg[0]), np.radians(rig.azimuth_deg[1])
    phi = (np.sqrt(5.0) - 1) / 2
    cams = []
    for i in range(n):
        z = lo + (hi - lo) * (i + 0.5) / n
        az = a0 + (a1 - a0) * ((0.5 + i * phi) % 1.0)
        r = np.sqrt(max(1.0 - z * z, 0.0))
        eye = target + rig.radius * np.array([r * np.cos(az), r * np.sin(az), z])
        cams.append(make_camera(look_at(eye, target), width=width, height=height,
                                fov_deg=rig.fov_deg))
    return stack(cams)


def split_views(views: int, test_views: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (train, test) into ``views + test_views`` cameras, test views spread evenly."""
    total = views + test_views
    if views < 1 or test_views < 0:
        raise DataError("views", f"need views >= 1 and test views >= 0, got {views}, {test_views}")
    test = np.array(sorted({int((k + 0.5) * total / test_views) for k in range(test_views)}),
                    np.int64) if test_views else np.zeros(0, np.int64)
    train = np.setdiff1d(np.arange(total), test)
    return train, test


def scene_cameras(scene: rc.Scene, *, views: int = 64, test_views: int = 8,
                  size: int = 128) -> tuple[Camera, np.ndarray, np.ndarray]:
    """(cameras [views + test_views], train indices [views], test indices [test_views])."""
    train, test = split_views(views, test_views)
    return rig_cameras(scene.rig, views + test_views, width=size), train, test
