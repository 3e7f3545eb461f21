"""Ablation benchmark: ProEdit vs its controls as paired statistics over seeds.

    python benchmarks/ablation.py [--smoke] [--out DIR] [--scenes face] [--seeds 20]
                                  [--variants 3,1,3:0] [--prompts P1,P2]

Runs :func:`jaxedit_lab.ablation.run_ablation` at its defaults (simulated editor; see
that module for the methods, the editor variants and the mode-aware scores) into
``DIR/ablation_run`` (ablation.json with every run, ablation.md, views/, report.html) and
writes ``DIR/ablation.json`` with the settings, the
summary (mean and Student-t 95% CI over seeds per scene, instruction, method and metric), the
paired differences proedit - other, the wall time, the CPU time of the process (steadier on a
shared machine) and the peak memory.
"""

from __future__ import annotations

import time

from common import parse_args, peak_rss_mb, write_json


def extra(p):
    from jaxedit_lab.ablation import AblationConfig

    defaults = AblationConfig()
    p.add_argument("--scenes", default=",".join(defaults.scenes))
    p.add_argument("--prompts", default=",".join(defaults.prompts),
                   help="comma-separated instructions")
    p.add_argument("--seeds", type=int, default=defaults.seeds)
    p.add_argument("--variants", default=",".join(defaults.variants),
                   help="editor variants K or K:GAIN; the first is the mechanism test")


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import dataclasses

    from jaxedit_lab.ablation import AblationConfig, run_ablation, tables

    split = lambda text: tuple(t.strip() for t in text.split(",") if t.strip())  # noqa: E731
    config = AblationConfig.smoke() if args.smoke else dataclasses.replace(
        AblationConfig(), scenes=split(args.scenes), prompts=split(args.prompts),
        seeds=args.seeds, variants=split(args.variants))
    t0, c0 = time.perf_counter(), time.process_time()
    result = run_ablation(args.out / "ablation_run", config, report=not args.smoke, log=print)
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
