"""Ablation benchmark: ProEdit vs ND vs IN2N on the face scene, against the simulated ground truth.

    python benchmarks/ablation.py [--smoke] [--out DIR]

Runs :func:`experiments.ablation.run_ablation` into ``DIR/ablation_run`` (the
per-mode edit run directories, ablation.md and report.html) and writes
``DIR/ablation.json`` with, per mode: psnr_vs_target, ssim_vs_target (held-out
views vs the editor's noise-free target), multiview_consistency (reprojection
PSNR between neighbouring held-out views), edit_fit_psnr, num_gaussians,
subtasks, total_steps, wall_time_s; plus the unedited input as a floor.
"""

from __future__ import annotations

import time

from common import parse_args, peak_rss_mb, write_json


def extra(p):
    p.add_argument("--prompt", default="turn him into a bronze statue")
    p.add_argument("--max-steps", type=int, default=250)
    p.add_argument("--size", type=int, default=64)


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    from experiments.ablation import run_ablation, smoke_overrides, table

    kw = dict(size=args.size, max_steps=args.max_steps)
    if args.smoke:
        kw.update(smoke_overrides())
    t0 = time.perf_counter()
    results = run_ablation(args.out / "ablation_run", prompt=args.prompt, log=print, **kw)
    print(table(results))
    payload = {"settings": {"prompt": args.prompt, "smoke": args.smoke, **{k: v for k, v in kw.items()}},
               "results": results, "wall_time_s": time.perf_counter() - t0,
               "peak_rss_mb": peak_rss_mb(),
               "note": "CPU timings on a shared machine are noisy; modes run sequentially in one "
                       "process, so later modes reuse compiled steps"}
    write_json(args.out, "ablation", payload)


if __name__ == "__main__":
    main()
