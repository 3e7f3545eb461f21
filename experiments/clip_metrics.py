"""clip-metrics: IN2N's CLIP metrics of a finished edit run, from its saved test-view renders.

    python -m experiments clip-metrics --run RUN_DIR --clip-weights DIR \\
        --caption-orig "a photo of a man" --caption-edit "a photo of a bronze statue of a man"

Compares ``RUN_DIR/original/renders/*.png`` (the input scene) with the renders of a
snapshot (default: the last one under ``RUN_DIR/subtasks/``, or ``--snapshot DIR``), view
by view in file-name order (the test cameras' order, which the direction consistency
treats as the path). Writes ``clip_metrics.json`` into the snapshot folder and prints it.
"""

from __future__ import annotations

import json
from pathlib import Path

from jaxedit.errors import DataError

HELP = "CLIP text-image direction similarity and direction consistency of an edit run"


def add_arguments(p) -> None:
    p.add_argument("--run", type=Path, required=True, help="edit run directory")
    p.add_argument("--snapshot", type=Path, default=None,
                   help="snapshot folder with renders/ (default: the run's last subtask)")
    p.add_argument("--clip-weights", default=None,
                   help="transformers CLIP folder (or a cached Hub id), e.g. "
                        "openai/clip-vit-large-patch14")
    p.add_argument("--caption-orig", required=True, help="caption of the original scene")
    p.add_argument("--caption-edit", required=True, help="caption of the edited scene")
    p.add_argument("--clip-device", default=None, help="torch device (default cuda:0 or cpu)")


def _renders(folder: Path) -> list[Path]:
    files = sorted((folder / "renders").glob("*.png"))
    if not files:
        raise DataError(folder / "renders", "no rendered views (*.png) here")
    return files


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
    result = clip_metrics_of_run(args.run, snapshot=args.snapshot, clip_weights=args.clip_weights,
                                 caption_orig=args.caption_orig, caption_edit=args.caption_edit,
                                 device=args.clip_device)
    return {k: result[k] for k in ("direction_similarity", "direction_consistency",
                                   "clip_score_edit", "views", "snapshot")}
