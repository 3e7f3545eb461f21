"""The pre-registered mechanism study's figures and verdicts from its run folder.

    python scripts/mechanism_study.py RUN_DIR [--out FILE]

Reads ``RUN_DIR/runs.jsonl`` (the ablation's records, each with its per-edit log),
``RUN_DIR/settings.json`` (the training views) and the scene's reconstruction metrics
(``RUN_DIR/SCENE/reconstruct/metrics.json``, for the testability check), and writes the
summary of :func:`jaxedit_lab.ablation.mechanism.study` (default
``RUN_DIR/mechanism.json``): per run its early split, edit consistency, keep rate and
scores; per instruction and control the paired contrasts (t interval, Wilcoxon, Holm over the
primary family), Spearman's rho with its bootstrap interval, and P1-P4's verdicts. Prints one
line per verdict. A study still running gives the figures of the seeds done so far.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jaxedit.errors import DataError  # noqa: E402
from jaxedit.io.files import atomic_write_text  # noqa: E402
from jaxedit_lab.ablation.mechanism import study  # noqa: E402


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DataError(path, f"cannot be read as JSON ({e.__class__.__name__})") from None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    try:
        settings = _read_json(args.run_dir / "settings.json")
        jsonl = args.run_dir / "runs.jsonl"
        try:
            lines = jsonl.read_text().splitlines()
        except OSError:
            raise DataError(jsonl, "not found: not an ablation run folder") from None
        records = [json.loads(line) for line in lines if line.strip()]
        scenes = settings["scenes"]
        if len(scenes) != 1:
            raise DataError(args.run_dir, f"holds {len(scenes)} scenes; the study has one")
        metrics = args.run_dir / scenes[0] / "reconstruct" / "metrics.json"
        recon_psnr = _read_json(metrics).get("test_psnr") if metrics.exists() else None
        payload = {"run_dir": str(args.run_dir), "settings": settings,
                   "recon_test_psnr": recon_psnr,
                   **study(records, views=settings["views"], recon_psnr=recon_psnr)}
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = args.out or args.run_dir / "mechanism.json"
    atomic_write_text(out, json.dumps(payload, indent=1) + "\n")
    for prompt, res in payload["instructions"].items():
        print(f"{prompt}: {len(res['seeds'])} seeds")
        for control, c in res["controls"].items():
            for p, (verdict, why) in c["verdicts"].items():
                print(f"  {p} vs {control}: {verdict} ({why})")
        print(f"  P4 vs uniform: {res['P4'][0]} ({res['P4'][1]})")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
