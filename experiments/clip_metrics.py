"""clip-metrics: IN2N's CLIP metrics of a finished edit run, from its saved test-view renders.

    python -m experiments clip-metrics --run RUN_DIR --clip-weights DIR \\
        --caption-orig "a photo of a man" --caption-edit "a photo of a bronze statue of a man"

Compares ``RUN_DIR/original/renders/*.png`` (the input scene) with the renders of a
snapshot (default: the last one under ``RUN_DIR/subtasks/``; ``--select NODE``: a node of
the run's tree as ``edit --select-only --select`` names it, e.g. 2, 0.5, b1:-1; or
``--snapshot DIR``), view by view in file-name order (the test cameras' order, which the direction consistency
treats as the path). Writes ``clip_metrics.json`` into the snapshot folder and prints it.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from jaxedit.errors import DataError

HELP = "CLIP text-image direction similarity and direction consistency of an edit run"


@dataclasses.dataclass(frozen=True)
class ClipMetricsConfig:
    """Which run and snapshot are measured, and with which CLIP.

    Attributes:
      run: edit run directory.
      snapshot: snapshot folder with renders/ (None: the run's last subtask).
      select: a node of the run's tree instead: a subtask index or ratio of the main
        branch, or BRANCH:INDEX (negative from the end), as ``edit --select`` takes it.
      clip_weights: transformers CLIP folder (or a cached Hub id), e.g.
        openai/clip-vit-large-patch14.
      caption_orig: caption of the original scene.
      caption_edit: caption of the edited scene.
      clip_device: torch device (None: cuda:0 or cpu).
    """

    run: Path | None = None
    snapshot: Path | None = None
    select: str | None = None
    clip_weights: str | None = None
    caption_orig: str | None = None
    caption_edit: str | None = None
    clip_device: str | None = None


def _config_flags():
    from experiments.flags import Flag, FlagSet

    return FlagSet(ClipMetricsConfig, (
        Flag("run", required=True), Flag("snapshot"), Flag("select", metavar="NODE"),
        Flag("clip_weights"),
        Flag("caption_orig", required=True), Flag("caption_edit", required=True),
        Flag("clip_device"))).complete()


#: The command's flags, generated from :class:`ClipMetricsConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    FLAGS[0].add_to(p)


def run_config(args) -> ClipMetricsConfig:
    """The :class:`ClipMetricsConfig` of ``args``."""
    return FLAGS[0].build(args)


def _renders(folder: Path) -> list[Path]:
    files = sorted((folder / "renders").glob("*.png"))
    if not files:
        raise DataError(folder / "renders", "no rendered views (*.png) here")
    return files


def node_folder(run_dir: Path, which: str) -> Path:
    """The snapshot folder of node ``which`` of a run (``--select``'s syntax)."""
    from jaxedit.pipelines.snapshots import branch_folder, find_snapshot

    branch, which = (str(which).rpartition(":")[::2] if ":" in str(which)
                     else ("main", str(which)))
    try:
        folder = branch_folder(run_dir, branch)
    except DataError as e:
        raise DataError("--select", e.problem) from None
    if not (folder / "schedule.json").is_file():
        raise DataError("--select", f"the run has no branch {branch!r}")
    return find_snapshot(folder, which)[1].parent


def clip_metrics_of_run(run_dir: Path, *, snapshot: Path | None = None, clip_weights=None,
                        caption_orig: str, caption_edit: str, device=None) -> dict:
    """IN2N's CLIP metrics of ``snapshot`` (default: the last subtask) against ``original/``.

    Also writes them to ``SNAPSHOT/clip_metrics.json``.
    """
    import numpy as np

    from jaxedit.clip_metrics import DEFAULT_CLIP, load_clip_metrics
    from jaxedit.io import read_image
    from jaxedit.io.files import atomic_write_text

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError(run_dir, "edit run directory not found")
    if snapshot is None:
        subtasks = sorted(p for p in (run_dir / "subtasks").glob("*") if (p / "renders").is_dir())
        if not subtasks:
            raise DataError(run_dir / "subtasks", "no snapshot with renders/; pass --snapshot")
        snapshot = subtasks[-1]
    edits = _renders(Path(snapshot))  # first: it may be the path the user gave
    originals = _renders(run_dir / "original")
    if [p.name for p in originals] != [p.name for p in edits]:
        raise DataError(snapshot, "its renders/ do not match original/renders/ view for view")
    try:
        metrics_fn = load_clip_metrics(clip_weights or DEFAULT_CLIP, device=device)
    except ImportError as e:
        raise DataError("--clip-weights", str(e)) from None
    orig = np.stack([read_image(p) for p in originals])
    edit = np.stack([read_image(p) for p in edits])
    result = metrics_fn(orig, edit, caption_orig, caption_edit)
    result["snapshot"] = str(snapshot)
    atomic_write_text(Path(snapshot) / "clip_metrics.json", json.dumps(result, indent=2) + "\n")
    return result


def run(args):
    config = run_config(args)
    snapshot = config.snapshot
    if config.select is not None:
        if snapshot is not None:
            raise DataError("--select", "either --select or --snapshot")
        if not Path(config.run).is_dir():
            raise DataError(config.run, "edit run directory not found")
        snapshot = node_folder(Path(config.run), config.select)
    result = clip_metrics_of_run(config.run, snapshot=snapshot,
                                 clip_weights=config.clip_weights,
                                 caption_orig=config.caption_orig,
                                 caption_edit=config.caption_edit, device=config.clip_device)
    return {k: result[k] for k in ("direction_similarity", "direction_consistency",
                                   "clip_score_edit", "views", "snapshot")}
