"""``make-scene``: write a built-in scene as a nerfstudio dataset.

    python -m experiments make-scene NAME --out DIR [--size N --views N --test-views N
                                                     --points N --supersample S --preview]

NAME is one of :func:`jaxedit.scenes.list_scenes` (face, tabletop, fence, ball).
``--seed`` (shared flag) picks the scene variant and the point-cloud draws; the
same flags give byte-identical files. ``--preview`` also writes ``preview.png``,
a contact sheet of up to 16 views, next to the dataset.
"""

from __future__ import annotations

import time

HELP = "write a built-in scene (face, tabletop, fence, ball) as a nerfstudio dataset"


def add_arguments(p) -> None:
    p.add_argument("name", metavar="NAME", help="built-in scene name")
    p.add_argument("--size", type=int, default=128, help="image width and height in pixels")
    p.add_argument("--views", type=int, default=64, help="number of training views")
    p.add_argument("--test-views", type=int, default=8, help="number of held-out views")
    p.add_argument("--points", type=int, default=4000, help="points in the initial cloud")
    p.add_argument("--supersample", type=int, default=2,
                   help="rays per pixel along each axis (anti-aliasing)")
    p.add_argument("--preview", action="store_true", help="also write DIR/preview.png")


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
    """Counts in range, and the memory they imply within the machine's, before any work."""
    from experiments.cli import check_minimums, require_memory

    check_minimums(args, {"size": 8, "views": 1, "test_views": 0, "points": 1, "supersample": 1})
    frames = args.views + args.test_views
    # Kept: every frame as float32 RGB (and once more while written). Per frame traced:
    # (size * supersample)^2 rays with about 40 float64 values each (origins, directions,
    # hits, shading). Points: a few float64 copies of [points, 3] positions and colours.
    rays = (args.size * args.supersample) ** 2
    needed = 2 * frames * args.size ** 2 * 3 * 4 + rays * 40 * 8 + args.points * 6 * 8 * 4
    require_memory("--size/--views/--points", needed,
                   f"{frames} views of {args.size}x{args.size} px and {args.points} points")


def run(args) -> dict:
    from jaxedit import DataError, scenes
    from jaxedit.io.nerfstudio import load_nerfstudio

    if args.out is None:
        raise DataError("--out", "make-scene needs an output folder (--out DIR)")
    if args.name not in scenes.list_scenes():
        raise DataError("NAME", f"unknown scene {args.name!r}; built-in scenes: "
                        f"{', '.join(scenes.list_scenes())}")
    check_sizes(args)
    start = time.perf_counter()
    path = scenes.make_scene(args.name, args.out, size=args.size, views=args.views,
                             test_views=args.test_views, seed=args.seed, num_points=args.points,
                             supersample=args.supersample)
    seconds = time.perf_counter() - start
    if args.preview:
        from jaxedit.io.images import write_image

        data = load_nerfstudio(path)
        write_image(args.out / "preview.png", contact_sheet(data.images[:16]))
    return {"scene": args.name, "dataset": str(path.parent), "views": args.views,
            "test_views": args.test_views, "size": args.size, "points": args.points,
            "seed": args.seed, "seconds": round(seconds, 2)}
