"""Snapshot folders (what a person looks at for one scene state) and the user's choice
of one as ``RUN/selected.ply``."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Callable

import numpy as np

from .. import viz
from ..edit.outputs import scene_metrics
from ..errors import DataError
from ..io import save_ply, write_image
from ..io.files import atomic_path, atomic_write_text


def _write_png(path: Path, image) -> None:
    # C order: OpenImageIO refuses arrays with strided channels (np.clip keeps the layout).
    write_image(path, np.ascontiguousarray(np.clip(np.asarray(image, np.float32), 0.0, 1.0)))


def write_snapshot(directory, gaussians, cameras, *, background=(1.0, 1.0, 1.0),
                   prefix: str = "view", sh_degree: int | None = None, ply: bool = True,
                   depth: bool = True, depth_percentiles=(2.0, 98.0),
                   turntable_frames: int = 0, turntable_size: int | None = None,
                   render_fn: Callable | None = None) -> dict:
    """Write atomically ``scene.ply``, ``renders/{prefix}_000.png`` per camera, ``depth/``
    (one shared near/far) and ``turntable.webp`` (``turntable_frames`` > 0) of one state.

    Args:
      directory: output folder (created).
      gaussians: the scene.
      cameras: batched :class:`jaxedit.Camera` [N], e.g. the test views.
      background: float [3] render background.
    Returns:
      {"ply": str|None, "renders": [str], "depth": [str], "depth_range": [near, far],
       "turntable": [str]} with paths relative to ``directory``.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    record: dict = {"ply": None, "renders": [], "depth": [], "depth_range": None, "turntable": []}
    if ply:
        save_ply(directory / "scene.ply", gaussians)
        record["ply"] = "scene.ply"
    rgb, alpha, dep = viz.render_views(gaussians, cameras, background=background,
                                       sh_degree=sh_degree, render_fn=render_fn)
    for i, image in enumerate(rgb):
        rel = f"renders/{prefix}_{i:03d}.png"
        _write_png(directory / rel, image)
        record["renders"].append(rel)
    if depth:
        near, far = viz.depth_range(dep, alpha, percentiles=depth_percentiles)
        record["depth_range"] = [near, far]
        for i in range(len(dep)):
            rel = f"depth/{prefix}_{i:03d}.png"
            _write_png(directory / rel, viz.colorize_depth(dep[i], alpha[i], near=near,
                                                           far=far, background=background))
            record["depth"].append(rel)
    if turntable_frames > 0:
        frames = viz.turntable(gaussians, n_frames=turntable_frames, cameras=cameras,
                               size=turntable_size, background=background,
                               sh_degree=sh_degree, render_fn=render_fn)
        written = viz.write_turntable(directory / "turntable.webp", frames)
        record["turntable"] = [p.name for p in written]
    return record


def write_scene_snapshot(ctx, directory: Path, gaussians, *, ratio: float,
                         reference: tuple | None = None) -> dict:
    """:func:`write_snapshot` plus metrics.json (``reference`` as in
    :func:`jaxedit.edit.outputs.scene_metrics`)."""
    directory = Path(directory)
    write_snapshot(directory, gaussians, ctx.data.test_cameras,
                       background=tuple(ctx.config.background),
                       turntable_frames=ctx.config.turntable_frames,
                       render_fn=lambda g, cam, **kw: ctx.renderer(g, cam))
    metrics = scene_metrics(ctx, gaussians, ratio, reference=reference)
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


#: A steered run's branches' folders (RUN/branches/NAME, :mod:`jaxedit.pipelines.steer_run`).
BRANCHES = "branches"


def branch_folder(run_dir, name: str) -> Path:
    """The folder of branch ``name`` of a run ("main": the run directory itself); a name
    that is not a branch name (:func:`jaxedit.edit.steer.check_name`) is a DataError."""
    from ..edit.steer import check_name

    return Path(run_dir) if name == "main" else Path(run_dir) / BRANCHES / check_name(name)


def select_snapshot(run_dir: str | os.PathLike, which) -> Path:
    """Make (and return) ``run_dir/selected.ply`` the snapshot ``which`` (as in
    :func:`find_snapshot`, or ``"BRANCH:INDEX"``), with ``selected.json``."""
    run_dir = Path(run_dir)
    branch = "main"
    if isinstance(which, str) and ":" in which:
        branch, _, which = which.rpartition(":")
        if not (branch_folder(run_dir, branch) / "schedule.json").is_file():
            raise DataError("select", f"the run has no branch {branch!r}")
    chosen, src = find_snapshot(branch_folder(run_dir, branch), which)
    chosen = dict(chosen, snapshot=str(src.relative_to(run_dir)), branch=branch)
    dst = run_dir / "selected.ply"
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
    atomic_write_text(run_dir / "selected.json",
                      json.dumps({"index": chosen["index"], "name": chosen["name"],
                                  "ratio": chosen["ratio"], "snapshot": chosen["snapshot"],
                                  **({} if branch == "main" else {"branch": branch})},
                                 indent=2) + "\n")
    return dst


def find_snapshot(run_dir: str | os.PathLike, which) -> tuple[dict, Path]:
    """(schedule.json's entry, scene.ply path) of subtask ``which``: an int index (negative
    from the end) or a float ratio (the last nearest); strings are parsed."""
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
        top = max(1.0, max(s["ratio"] for s in subtasks))  # past 1 in an extended branch
        if not 0.0 <= r <= top:
            raise DataError("select", f"ratio must be in [0, {top:g}], got {r}")
        best = min(abs(s["ratio"] - r) for s in subtasks)
        chosen = [s for s in subtasks if abs(s["ratio"] - r) == best][-1]
    src = run_dir / chosen["snapshot"]
    if not src.is_file():
        raise DataError(src, f"snapshot of subtask {chosen['index']} is missing (listed in {path})")
    return chosen, src
