"""Reading a run directory for the report (a one-line DataError when malformed); layout::

    config.json      {"command", "argv", "flags", "jaxedit_version"}   (optional)
    schedule.json    {"prompt", "editor", "mode", "threshold", "difficulty_curve": [[r, d], ...],
                      "subtasks": [{"index", "name", "ratio", "difficulty", "steps", "seconds",
                                    "converged", "snapshot": "subtasks/02_r0.500/scene.ply"}]}
    metrics.json     {name: number, ...}
    original/renders/*.png, original/depth/*.png (optional)
    subtasks/NN_rX.XXX/{renders/*.png, depth/*.png, turntable.webp, metrics.json}
    train_log.jsonl  {"step", "loss", "psnr", "num_gaussians", ...} per line (a reconstruction)
"""

from __future__ import annotations

import json
from pathlib import Path

from ...errors import DataError


def read_json(path: Path, *, required: bool = True):
    """Parsed JSON, None when absent and not required; DataError when malformed."""
    path = Path(path)
    if not path.exists():
        if required:
            raise DataError(path, "missing")
        return None
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise DataError(path, f"cannot read ({e.strerror or e})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(path, f"malformed JSON ({e})") from None


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _check_schedule(path: Path, schedule) -> dict:
    """Validate the fields the report uses; one-line DataError otherwise."""
    if not isinstance(schedule, dict):
        raise DataError(path, "must be a JSON object")
    subtasks = schedule.get("subtasks", [])
    if not isinstance(subtasks, list):
        raise DataError(path, "'subtasks' must be a list")
    for i, s in enumerate(subtasks):
        if not isinstance(s, dict):
            raise DataError(path, f"subtasks[{i}] must be an object")
        if not _is_number(s.get("ratio")):
            raise DataError(path, f"subtasks[{i}].ratio must be a number, got {s.get('ratio')!r}")
        for key in ("difficulty", "seconds", "steps"):
            if s.get(key) is not None and not _is_number(s[key]):
                raise DataError(path, f"subtasks[{i}].{key} must be a number or null")
        if s.get("snapshot") is not None and not isinstance(s["snapshot"], str):
            raise DataError(path, f"subtasks[{i}].snapshot must be a path string")
    curve = schedule.get("difficulty_curve") or []
    if not isinstance(curve, list) or not all(
            isinstance(p, (list, tuple)) and len(p) == 2 and all(_is_number(v) or v is None for v in p)
            for p in curve):
        raise DataError(path, "'difficulty_curve' must be a list of [r, d] pairs")
    if schedule.get("threshold") is not None and not _is_number(schedule["threshold"]):
        raise DataError(path, "'threshold' must be a number or null")
    return schedule


def _snapshot_dir(run_dir: Path, subtask: dict, position: int) -> Path | None:
    """The folder of a subtask's snapshot: from its 'snapshot' path, else by index."""
    snap = subtask.get("snapshot")
    if snap:
        p = Path(snap)
        p = p if p.is_absolute() else run_dir / p
        return p.parent if p.suffix else p
    index = subtask.get("index", position)
    found = sorted((run_dir / "subtasks").glob(f"{int(index):02d}_*"))
    return found[0] if found else None


def _pngs(folder: Path | None) -> list[Path]:
    if folder is None or not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))


def read_train_log(path: Path) -> list[dict]:
    """Records of a JSON-lines training log (one object per line); DataError when malformed."""
    records = []
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise DataError(path, f"cannot read ({e.strerror or e})") from None
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as e:
            if i == len(lines) - 1:  # a run killed mid-write leaves a partial last line
                break
            raise DataError(path, f"line {i + 1}: malformed JSON ({e})") from None
        if isinstance(rec, dict):
            records.append(rec)
    return records
