"""``export``: write a scene in the format a viewer or another tool reads.

    python -m experiments export SCENE --out FILE               # any format to any format
    python -m experiments export RUN_DIR --select 2 --out FILE.spz
    python -m experiments export RUN_DIR --out FILE.sog         # the run's selected.ply

SCENE is a splat file of any format :func:`jaxedit.io.load_scene` reads (INRIA or compressed
.ply, .spz, .sog, meta.json, .splat); RUN_DIR an edit run, whose subtask ``--select`` picks (an
index or a ratio, as ``edit --select``; the run is only read) or, without it, its
``selected.ply``. The format is FILE's extension (``.compressed.ply``, ``.spz``, ``.sog``,
``meta.json``, ``.splat``, ``.ply``) unless ``--format`` says. ``--up AXIS`` turns the scene's up
axis to -y, the up of the 3DGS .ply convention that splat viewers show upright (its view-dependent
colour turned with it). Here ``--out`` is that file, not
a run directory (``--output`` is the same flag, kept for older command lines): no run record
or lock is written beside it, and it is written atomically.

``edit ... --export spz,sog`` writes the run's selected snapshot the same way
(:func:`export_selected`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "write a scene or an edit run's snapshot as .ply, .compressed.ply, .spz, .sog or .splat"


def add_arguments(p) -> None:
    from jaxedit.io import FORMATS
    from jaxedit.io.similarity import AXES

    p.add_argument("source", type=Path, help="a splat file, or an edit run directory")
    # the shared --out (added before this) names the file written; --output is its old name
    out = next(a for a in p.arguments if a.dest == "out")
    out.help = "the file to write; its extension picks the format"
    p.add_argument("--output", dest="out", type=Path, default=None, help=argparse.SUPPRESS)
    p.add_argument("--select", default=None,
                   help="with RUN_DIR: the subtask (index or ratio) to export")
    p.add_argument("--format", default=None, choices=FORMATS,
                   help="the format, whatever --out's extension")
    p.add_argument("--up", default=None, choices=AXES,
                   help="the scene's up axis, turned to -y so that splat viewers (SuperSplat, "
                        "the INRIA viewer) show it upright; +z for the built-in scenes and "
                        "nerfstudio datasets; a minus sign needs the = form, --up=-z "
                        "(default: the file keeps the scene's axes)")


#: experiments/rundirs.py: ``--out`` names a file here (checked as one), not a run directory.
OUT_IS_FILE = True


def out_use(args) -> str:
    """No lock or config.json beside the file (experiments/cli.py): the file is the output."""
    return "signal"


def source_scene(source: Path, select: str | None) -> Path:
    """The splat file that ``source`` and ``--select`` name."""
    from jaxedit import DataError
    from jaxedit.pipelines.snapshots import find_snapshot

    if source.is_dir():
        if select is not None:
            return find_snapshot(source, select)[1]
        if not (source / "selected.ply").is_file():
            raise DataError(source, "a folder without selected.ply: give --select K (a subtask "
                                    "index or ratio), or a scene file")
        return source / "selected.ply"
    if select is not None:
        raise DataError("--select", "only applies when the source is an edit run directory")
    return source


def run(args) -> dict:
    from jaxedit.io import load_scene, save_scene, transform_gaussians, upright
    from jaxedit.io.formats import format_from_name

    from jaxedit import DataError

    if args.out is None:
        raise DataError("--out", "give the file to write (its extension picks the format)")
    scene_file = source_scene(args.source, args.select)
    fmt = args.format or format_from_name(args.out)  # a bad extension: before any reading
    gaussians = load_scene(scene_file)
    if args.up is not None:
        gaussians = transform_gaussians(gaussians, upright(args.up))
    path = save_scene(args.out, gaussians, format=fmt)
    return {"source": str(scene_file), "output": str(path), "format": fmt, "up": args.up,
            "gaussians": int(gaussians.alive.sum()), "bytes": path.stat().st_size}


def export_formats(values) -> tuple[str, ...]:
    """``edit --export``'s formats (a comma list of :data:`jaxedit.io.FORMATS`), each once,
    in the order given; DataError naming ``export`` for an unknown or empty one."""
    from jaxedit import DataError
    from jaxedit.io import FORMATS

    formats = tuple(dict.fromkeys(v.strip().lower() for v in values))
    bad = [v for v in formats if v not in FORMATS]
    if bad:
        raise DataError("export", f"unknown format {bad[0]!r} (expected a comma list of "
                                  f"{', '.join(FORMATS)})")
    return formats


def export_selected(run_dir: Path, formats, select, log=print) -> list[str]:
    """Write an edit run's chosen snapshot as ``run_dir/selected<suffix>`` in each format.

    The snapshot is subtask ``select`` (index or ratio) or, when None, the last finished
    one; it becomes ``selected.ply`` / ``selected.json`` first (as ``edit --select``).
    Logs one line per file; returns the paths written.
    """
    from jaxedit.io import load_scene, save_scene
    from jaxedit.io.formats import SUFFIXES
    from jaxedit.pipelines import select_snapshot

    if not formats:
        return []
    chosen = select_snapshot(run_dir, -1 if select is None else select)
    gaussians = load_scene(chosen)
    written = []
    for fmt in formats:
        path = chosen if fmt == "ply" else save_scene(run_dir / f"selected{SUFFIXES[fmt]}",
                                                      gaussians, format=fmt)
        log(f"exported the selected snapshot as {fmt}: {path} ({path.stat().st_size} bytes)")
        written.append(str(path))
    return written
