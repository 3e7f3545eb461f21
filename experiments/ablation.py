"""``python -m experiments ablation``: ProEdit vs its controls as paired statistics over seeds.

The edge of :mod:`jaxedit_lab.ablation` (whose docstring has the methods, the
editor variants, the scores and what RUN_DIR receives): the flags are generated from
:class:`jaxedit_lab.ablation.AblationConfig` (experiments/flags.py); ``--smoke``
is :meth:`AblationConfig.smoke`, and ``--seed`` seeds the scenes and reconstructions.
"""

from __future__ import annotations

import dataclasses

HELP = ("ablation: proedit vs nd, nd at equal steps and calls (nd_equal, nd_replay), nd-k, "
        "uniform and in2n over seeds, with reference levels and paired 95-percent confidence "
        "intervals (simulated editor or the bundled ip2p); resumes from RUN_DIR/runs.jsonl")


def _config_flags():
    from jaxedit_lab.ablation import AblationConfig

    from .flags import Flag, FlagSet

    from jaxedit_lab.ablation import EDITORS

    names = ("scenes", "prompts", "seeds", "variants", "methods", "control_methods", "size",
             "views", "test_views", "recon_iters", "refine_every", "max_steps", "warmup",
             "patience", "edit_every", "lr_sh_dc", "ip2p_steps", "ip2p_weights", "points")
    return FlagSet(AblationConfig, tuple(Flag(name) for name in names) + (
        Flag("editor", choices=EDITORS), Flag("references", off="--no-references"))).complete()


@dataclasses.dataclass(frozen=True)
class AblationCommand:
    """What one ``ablation`` command runs of the study its settings describe.

    Attributes:
      smoke: tiny sizes (CI): seconds, not minutes; sets every setting itself.
      seed_range: run only seeds A .. B-1 of the study's --seeds, as A:B (a part of the
        study, in a folder of its own; the part holding seed 0 runs the reference levels);
        parts merge by concatenating their runs.jsonl.
    """

    smoke: bool = False
    seed_range: str | None = None


def _command_flags():
    from .flags import Flag, FlagSet

    return FlagSet(AblationCommand, (Flag("smoke"), Flag("seed_range", metavar="A:B"))).complete()


#: The command's flags: the study's settings, generated from
#: :class:`jaxedit_lab.ablation.AblationConfig`, and the command's own
#: (:class:`AblationCommand`).
FLAGS = (_config_flags(), _command_flags())


def add_arguments(p) -> None:
    FLAGS[0].add_to(p)
    FLAGS[1].add_to(p)


def seed_range(text: str | None, seeds: int) -> range | None:
    """``--seed-range A:B`` as ``range(A, B)`` within ``0 .. seeds``; None when not given."""
    from jaxedit import DataError

    if text is None:
        return None
    try:
        start, stop = (int(v) for v in text.split(":"))
    except ValueError:
        raise DataError("--seed-range", f"expected A:B (two whole numbers), got {text!r}"
                        ) from None
    if not 0 <= start < stop <= seeds:
        raise DataError("--seed-range", f"{text} is not a non-empty range within 0:{seeds} "
                                        f"(--seeds {seeds})")
    return range(start, stop)


def run_config(args):
    """The :class:`AblationConfig` of ``args`` (DataErrors name its fields)."""
    from jaxedit import DataError
    from jaxedit_lab.ablation import AblationConfig

    if not args.smoke:
        return FLAGS[0].build(args)
    given = FLAGS[0].values(args)
    if given:  # a value given beside --smoke would be silently dropped
        flags = [FLAGS[0].flag_of()[field] for field in given]
        raise DataError(flags[0], f"--smoke sets {', '.join(flags)} itself; give either "
                                  f"--smoke or {', '.join(flags)}")
    return AblationConfig.smoke()


def run(args) -> dict:
    from jaxedit import DataError
    from jaxedit_lab.ablation import ALL, run_ablation

    if args.out is None:
        raise DataError("--out", "required (the ablation run directory)")
    config = run_config(args)
    part = seed_range(args.seed_range, config.seeds)
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    result = run_ablation(args.out, config, recon_seed=args.seed, log=log, seeds=part)
    return {f"m{r['editor_modes']} {r['scene']} {r['method']} {r['metric']}":
            round(r["mean"], 4) for r in result["summary"]
            if r["prompt"] in (ALL, result["settings"]["prompts"][0])
            and r["metric"] in ("psnr_best", "mode_mixing")
            and (r["prompt"] == ALL or len(result["settings"]["prompts"]) == 1)}
