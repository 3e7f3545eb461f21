"""``report``: (re)write the self-contained report.html of a run directory.

    python -m experiments report RUN_DIR [--output FILE] [--thumb-px 192]

Works on edit run directories (``schedule.json``), ablation run directories
(``ablation.json``) and any run directory with ``metrics.json`` + ``renders/``.
Edit/ablation commands write their report themselves; this re-creates it, e.g.
after a run was interrupted or to change the image sizes.
"""

from __future__ import annotations

from pathlib import Path

HELP = "write RUN_DIR/report.html (self-contained) from a run directory's JSON and images"


def add_arguments(p) -> None:
    p.add_argument("run_dir", type=Path, help="run directory to report on")
    p.add_argument("--output", type=Path, default=None,
                   help="where to write the page (default RUN_DIR/report.html)")
    p.add_argument("--thumb-px", type=int, default=192, help="longest side of each gallery view")
    p.add_argument("--max-views", type=int, default=8, help="test views per gallery row")
    p.add_argument("--max-mb", type=float, default=10.0,
                   help="page budget in MB: images shrink until it fits")


def run(args) -> dict:
    from jaxedit import DataError
    from jaxedit.pipelines.report import write_report

    if not 16 <= args.thumb_px <= 2048:
        raise DataError("--thumb-px", f"must be in [16, 2048], got {args.thumb_px}")
    if args.max_views < 1:
        raise DataError("--max-views", f"must be >= 1, got {args.max_views}")
    if not args.max_mb > 0:
        raise DataError("--max-mb", f"must be > 0, got {args.max_mb}")
    path = write_report(args.run_dir, out=args.output, thumb_px=args.thumb_px,
                        max_views=args.max_views, max_bytes=int(args.max_mb * 1e6))
    return {"report": str(path), "bytes": path.stat().st_size}
