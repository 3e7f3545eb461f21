"""``report``: (re)write the self-contained report.html of a run directory.

    python -m experiments report RUN_DIR [--output FILE] [--thumb-px 192]

Works on edit run directories (``schedule.json``), ablation run directories
(``ablation.json``) and any run directory with ``metrics.json`` + ``renders/``.
Edit/ablation commands write their report themselves; this re-creates it, e.g.
after a run was interrupted or to change the image sizes.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from jaxedit.errors import DataError, check_ranges, ranged

HELP = "write RUN_DIR/report.html (self-contained) from a run directory's JSON and images"


@dataclasses.dataclass(frozen=True)
class ReportConfig:
    """Where the page goes and how large its images are.

    Attributes:
      output: where to write the page (None: RUN_DIR/report.html).
      thumb_px: longest side of each gallery view.
      max_views: test views per gallery row.
      max_mb: page budget in MB: images shrink until it fits.
    """

    output: Path | None = None
    thumb_px: int = ranged(192, low=16, high=2048)
    max_views: int = ranged(8, low=1)
    max_mb: float = ranged(10.0, low=0, open=True)

    def __post_init__(self):
        check_ranges(self)


def _config_flags():
    from experiments.flags import Flag, FlagSet

    return FlagSet(ReportConfig, tuple(Flag(f.name) for f in dataclasses.fields(ReportConfig))).complete()


#: The command's flags, generated from :class:`ReportConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    p.add_argument("run_dir", type=Path, help="run directory to report on")
    FLAGS[0].add_to(p)


def run_config(args) -> ReportConfig:
    """The :class:`ReportConfig` of ``args`` (range errors name the flag)."""
    return FLAGS[0].build(args)


def run(args) -> dict:
    from jaxedit.pipelines.report import write_report
    from jaxedit_lab.ablation.report import write_ablation_report

    config = run_config(args)
    kinds = ("schedule.json", "ablation.json", "metrics.json")
    if args.run_dir.is_dir() and not any((args.run_dir / k).is_file() for k in kinds):
        raise DataError(args.run_dir, "not a run directory (no schedule.json, ablation.json or "
                                      "metrics.json)")
    write = write_ablation_report if (args.run_dir / "ablation.json").exists() else write_report
    path = write(args.run_dir, out=config.output, thumb_px=config.thumb_px,
                 max_views=config.max_views, max_bytes=int(config.max_mb * 1e6))
    return {"report": str(path), "bytes": path.stat().st_size}
