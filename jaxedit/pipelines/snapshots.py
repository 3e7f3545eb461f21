"""Snapshot folders of an edit run: one per scene state, and the user's selection.

``RUN/original`` and ``RUN/subtasks/NN_rX.XXX`` each hold scene.ply, renders/,
depth/, (turntable.webp) and metrics.json (:func:`write_scene_snapshot`);
:func:`select_snapshot` makes one of them ``RUN/selected.ply``, the user's choice
of the edit's aggressivity.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from ..edit.outputs import scene_metrics
from ..errors import DataError
from ..io.files import atomic_path, atomic_write_text


def write_scene_snapshot(ctx, directory: Path, gaussians, *, ratio: float) -> dict:
    """scene.ply, renders/, depth/, (turntable.webp) and metrics.json of one scene state."""
    from .. import viz

    directory = Path(directory)
    viz.write_snapshot(directory, gaussians, ctx.data.test_cameras,
                       background=tuple(ctx.config.background),
                       turntable_frames=ctx.config.turntable_frames,
                       render_fn=lambda g, cam, **kw: ctx.renderer(g, cam))
    metrics = scene_metrics(ctx, gaussians, ratio)
    atomic_write_text(directory / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return metrics


def snapshot_ratio(directory: Path) -> float:
    """The ratio of a snapshot folder (its metrics.json)."""
    path = Path(directory) / "metrics.json"
    if not Path(directory).is_dir():
        raise DataError(directory, "not a snapshot directory of an edit run (not a folder)")
    try:
        return float(json.loads(path.read_text())["ratio"])
    except FileNotFoundError:
        raise DataError(path, "not a snapshot directory of an edit run (no metrics.json)") from None
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(path, f"malformed snapshot metrics ({e})") from None


def select_snapshot(run_dir: str | os.PathLike, which) -> Path:
    """Make ``run_dir/selected.ply`` the snapshot of a subtask, chosen by ratio or index.

    ``which``: an int (subtask index, negative counts from the end) or a float
    ratio (the last subtask with the nearest ratio; a string is parsed: "2" is
    an index, "0.5" a ratio). Also writes ``selected.json``. Returns the path.
    """
    run_dir = Path(run_dir)
    path = run_dir / "schedule.json"
    try:
        subtasks = [s for s in json.loads(path.read_text())["subtasks"] if s.get("snapshot")]
    except FileNotFoundError:
        raise DataError(path, "no schedule.json: not an edit run directory") from None
    except (KeyError, ValueError) as e:
        raise DataError(path, f"malformed schedule ({e})") from None
    if not subtasks:
        raise DataError(path, "no finished subtask to select")
    if isinstance(which, str):
        try:
            which = int(which) if which.lstrip("-").isdigit() else float(which)
        except ValueError:
            raise DataError("select", f"expected a subtask index or a ratio, got {which!r}") from None
    if isinstance(which, (int, np.integer)) and not isinstance(which, bool):
        by_index = {s["index"]: s for s in subtasks}
        idx = int(which) if which >= 0 else subtasks[int(which)]["index"] if -len(subtasks) <= which else None
        if idx not in by_index:
            raise DataError("select", f"no finished subtask {which}; have "
                                        f"{sorted(by_index)}")
        chosen = by_index[idx]
    else:
        r = float(which)
        if not 0.0 <= r <= 1.0:
            raise DataError("select", f"ratio must be in [0, 1], got {r}")
        best = min(abs(s["ratio"] - r) for s in subtasks)
        chosen = [s for s in subtasks if abs(s["ratio"] - r) == best][-1]
    src = run_dir / chosen["snapshot"]
    if not src.is_file():
        raise DataError(src, f"snapshot of subtask {chosen['index']} is missing (listed in {path})")
    dst = run_dir / "selected.ply"
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
    atomic_write_text(run_dir / "selected.json",
                      json.dumps({"index": chosen["index"], "name": chosen["name"],
                                  "ratio": chosen["ratio"], "snapshot": chosen["snapshot"]},
                                 indent=2) + "\n")
    return dst
