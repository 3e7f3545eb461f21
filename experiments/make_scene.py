"""``make-scene``: write a built-in scene as a nerfstudio dataset.

    python -m experiments make-scene NAME --out DIR [--size N --views N --test-views N
                                                     --points N --supersample S --preview]
    python -m experiments make-scene person --out DIR [--downscale F --views N --test-views N]

NAME is one of :func:`jaxedit.scenes.list_scenes`: the procedural scenes (face,
tabletop, fence, ball) are rendered on the spot (defaults: 128 px, 64 + 8 views,
4000 points, 2x2 supersampling); ``person`` (Blender Cycles renders of a photo-textured
man, 256 px, 72 + 8 views, RGBA) is copied from the package, ``--downscale F``
dividing its size, ``--views`` / ``--test-views`` keeping that many views evenly spread
along its camera arc. ``--seed`` (shared flag) picks the scene variant and the
point-cloud draws of procedural scenes; the same flags give byte-identical files.
``--preview`` also writes ``preview.png``, a contact sheet of up to 16 views, next to
the dataset.
"""

from __future__ import annotations

import dataclasses
import json
import time

from jaxedit.errors import check_ranges, ranged

HELP = "write a built-in scene (face, tabletop, fence, ball, person) as a nerfstudio dataset"

# Flags that only the procedural scenes take, by make_scene keyword.
_PROCEDURAL_ONLY = {"size": "--size", "num_points": "--points", "supersample": "--supersample"}


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """How a built-in scene is written (None: the scene's own default, see the module
    docstring).

    Attributes:
      size: image width and height in pixels (procedural scenes; None: 128).
      views: number of training views (None: 64; person: all 72).
      test_views: number of held-out views (None: 8).
      points: points in the initial cloud (procedural scenes; None: 4000).
      supersample: rays per pixel along each axis (procedural scenes; None: 2).
      downscale: image downscale factor of a rendered scene (person: 256 px / F).
      preview: also write DIR/preview.png.
    """

    size: int | None = ranged(None, low=8)
    views: int | None = ranged(None, low=1)
    test_views: int | None = ranged(None, low=0)
    points: int | None = ranged(None, low=1)
    supersample: int | None = ranged(None, low=1)
    downscale: int = ranged(1, low=1)
    preview: bool = False

    def __post_init__(self):
        check_ranges(self)


def _config_flags():
    from experiments.flags import Flag, FlagSet

    return FlagSet(SceneConfig, tuple(Flag(f.name) for f in dataclasses.fields(SceneConfig))).complete()


#: The command's flags, generated from :class:`SceneConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    p.add_argument("name", metavar="NAME", help="built-in scene name")
    FLAGS[0].add_to(p)


def run_config(args) -> SceneConfig:
    """The :class:`SceneConfig` of ``args`` (range errors name the flag)."""
    return FLAGS[0].build(args)


def contact_sheet(images, columns: int = 8):
    """float [N, H, W, 3] -> one float [rows*H, columns*W, 3] image (white padding)."""
    import numpy as np

    n, h, w = images.shape[:3]
    columns = min(columns, n)
    rows = -(-n // columns)
    sheet = np.ones((rows * h, columns * w, 3), np.float32)
    for i in range(n):
        r, c = divmod(i, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = images[i]
    return sheet


def check_sizes(args) -> None:
    """Counts in range (:class:`SceneConfig`), and the memory they imply within the
    machine's, before any work."""
    from jaxedit.scenes.dataset import PROCEDURAL_DEFAULTS

    from jaxedit.memory import require_memory

    run_config(args)
    if args.name in _rendered_scenes():
        return  # copied from the package: a few MB whatever the flags
    d = PROCEDURAL_DEFAULTS
    size = args.size or d["size"]
    supersample = args.supersample or d["supersample"]
    points = args.points or d["num_points"]
    frames = ((d["views"] if args.views is None else args.views)
              + (d["test_views"] if args.test_views is None else args.test_views))
    # Kept: every frame as float32 RGB (and once more while written). Per frame traced:
    # (size * supersample)^2 rays with about 40 float64 values each (origins, directions,
    # hits, shading). Points: a few float64 copies of [points, 3] positions and colours.
    rays = (size * supersample) ** 2
    needed = 2 * frames * size ** 2 * 3 * 4 + rays * 40 * 8 + points * 6 * 8 * 4
    require_memory("--size/--views/--points", needed,
                   f"{frames} views of {size}x{size} px and {points} points")


def _rendered_scenes():
    from jaxedit import scenes

    return scenes.DATASETS


def run(args) -> dict:
    from jaxedit import DataError, scenes
    from jaxedit.io.nerfstudio import load_nerfstudio

    if args.out is None:
        raise DataError("--out", "make-scene needs an output folder (--out DIR)")
    if args.name not in scenes.list_scenes():
        raise DataError("NAME", f"unknown scene {args.name!r}; built-in scenes: "
                        f"{', '.join(scenes.list_scenes())}")
    kwargs = {"size": args.size, "num_points": args.points, "supersample": args.supersample}
    if args.name in scenes.DATASETS:
        # Name the flag, not make_scene's keyword, when one does not apply.
        for key, value in kwargs.items():
            if value is not None:
                raise DataError(_PROCEDURAL_ONLY[key], f"{args.name} is a rendered dataset of "
                                f"256 px views; use --downscale, --views, --test-views")
        kwargs = {"downscale": args.downscale}
    elif args.downscale != 1:
        raise DataError("--downscale", f"applies to rendered scenes "
                        f"({', '.join(scenes.DATASETS)}); {args.name} takes --size")
    check_sizes(args)
    start = time.perf_counter()
    path = scenes.make_scene(args.name, args.out, views=args.views, test_views=args.test_views,
                             seed=args.seed, **kwargs)
    seconds = time.perf_counter() - start
    if args.preview:
        from jaxedit.io.images import write_image

        data = load_nerfstudio(path)
        write_image(args.out / "preview.png", contact_sheet(data.images[:16]))
    info = json.loads((path.parent / scenes.SCENE_INFO).read_text(encoding="utf-8"))
    return {"scene": args.name, "dataset": str(path.parent), "views": info["views"],
            "test_views": info["test_views"], "size": info["size"],
            "downscale": args.downscale, "seed": args.seed, "seconds": round(seconds, 2)}
