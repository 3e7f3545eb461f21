"""Ablation benchmark: ProEdit vs its controls as paired statistics over seeds.

    python benchmarks/ablation.py [--smoke] [--out DIR] [--scenes face] [--seeds 20]
                                  [--variants 3,1,3:0] [--prompts P1,P2]

Runs :func:`experiments.ablation.run_ablation` at its defaults (simulated editor; see that
module for the methods, the editor variants and the mode-aware scores) into
``DIR/ablation_run`` (ablation.json with every run, ablation.md, views/, report.html) and writes ``DIR/ablation.json`` with the settings, the
summary (mean and Student-t 95% CI over seeds per scene, instruction, method and metric), the
paired differences proedit - other, the wall time, the CPU time of the process (steadier on a
shared machine) and the peak memory.
"""

from __future__ import annotations

import time

from common import parse_args, peak_rss_mb, write_json


def extra(p):
    from experiments.ablation import PROMPTS, SCENES, VARIANTS

    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--prompts", default=",".join(PROMPTS), help="comma-separated instructions")
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--variants", default=",".join(VARIANTS),
                   help="editor variants K or K:GAIN; the first is the mechanism test")


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    from experiments.ablation import run_ablation, smoke_overrides, tables

    split = lambda text: tuple(t.strip() for t in text.split(",") if t.strip())  # noqa: E731
    kw = dict(scenes=split(args.scenes), prompts=split(args.prompts) or None,
              seeds=args.seeds, variants=split(args.variants))
    if args.smoke:
        kw.update(smoke_overrides())
    t0, c0 = time.perf_counter(), time.process_time()
    result = run_ablation(args.out / "ablation_run", report=not args.smoke, log=print, **kw)
    print(tables(result["summary"], result["differences"]))
    write_json(args.out, "ablation", {
        "settings": result["settings"], "summary": result["summary"],
        "differences": result["differences"], "runs": len(result["runs"]),
        "wall_time_s": time.perf_counter() - t0, "cpu_time_s": time.process_time() - c0,
        "peak_rss_mb": peak_rss_mb(),
        "note": "CPU timings on a shared machine are noisy; runs go sequentially in one "
                "process, so later runs reuse compiled steps"})


if __name__ == "__main__":
    main()
