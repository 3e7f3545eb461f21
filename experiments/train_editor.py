"""``python -m experiments train-editor --out DIR``: train the small InstructPix2Pix.

The edge of :mod:`jaxedit_lab.train_editor` (whose docstring lists what DIR receives):
the edit dataset from the built-in scenes, the autoencoder, the tokenizer, the UNet and the
text encoder, then ``DIR/model``, a diffusers folder that ``--editor ip2p --ip2p-weights
DIR/model`` and diffusers' ``StableDiffusionInstructPix2PixPipeline`` load. The flags are
generated from :class:`jaxedit_lab.train_editor.tiny_ip2p.EditorTrainConfig`;
``--smoke`` is :meth:`~jaxedit_lab.train_editor.tiny_ip2p.EditorTrainConfig.smoke`
(CI: a couple of minutes);
``--seed`` seeds every draw. The weights bundled with jaxedit (v15) were made by
``bash scripts/train_bundled_editor.sh``: v1 from scratch, then cycles of ``--init`` the
previous model, each a study of ``docs/editor.md``.
"""

from __future__ import annotations

HELP = ("train the small InstructPix2Pix on edits of the built-in scenes (VAE, text encoder, "
        "UNet) and write it as a diffusers folder")


def _config_flags():
    from jaxedit_lab.train_editor.tiny_ip2p import EditorTrainConfig

    from .flags import Flag, FlagSet

    names = ("size", "procedural_views", "off_orbit_views", "scenes", "vae_steps", "vae_batch",
             "vae_crop", "vae_lr", "decoder_steps", "steps", "batch", "lr", "ema",
             "identity_share", "drop", "degrade", "text_width", "text_layers", "init")
    return FlagSet(EditorTrainConfig, tuple(Flag(name) for name in names)
                   + (Flag("empty_is_identity", off="--empty-prompt-edits"),
                      Flag("off_orbit_edits", off="--off-orbit-identity-only"),
                      Flag("off_orbit_geometry_only"),
                      Flag("outcome_from_noise"), Flag("balance_outcomes")),
                   derived=("seed",)).complete()  # the shared --seed


#: The command's flags, generated from
#: :class:`jaxedit_lab.train_editor.tiny_ip2p.EditorTrainConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    FLAGS[0].add_to(p)
    p.add_argument("--smoke", action="store_true",
                   help="tiny sizes (CI): a couple of minutes; sets every setting itself")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its checkpoints")


def run_config(args):
    """The :class:`EditorTrainConfig` of ``args`` (DataErrors name its fields)."""
    import dataclasses

    from jaxedit import DataError
    from jaxedit_lab.train_editor.tiny_ip2p import EditorTrainConfig

    if not args.smoke:
        config = FLAGS[0].build(args)
    else:
        given = FLAGS[0].values(args)
        if given:  # a value given beside --smoke would be silently dropped
            flags = [FLAGS[0].flag_of()[field] for field in given]
            raise DataError(flags[0], f"--smoke sets {', '.join(flags)} itself; give either "
                                      f"--smoke or {', '.join(flags)}")
        config = EditorTrainConfig.smoke()
    return dataclasses.replace(config, seed=int(args.seed)).check()


def run(args) -> dict:
    import math

    from jaxedit import DataError
    from jaxedit_lab.train_editor import train_editor

    from experiments.progress import Progress, configure

    if args.out is None:
        raise DataError("--out", "required (the training run directory)")
    config = run_config(args)
    configure(quiet=args.quiet)
    bars: list = []

    def stage(name: str, total: int, done: int):
        for bar in bars:
            bar.close()
        bars[:] = [Progress(total, f"train-editor {name}", initial=min(done, total))]

        def on_progress(done: int, loss: float) -> None:
            postfix = {"loss": round(loss, 4)} if math.isfinite(loss) else {}
            bars[0].update(done - bars[0].n, **postfix)
        return on_progress

    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    try:
        summary = train_editor(config, args.out, resume=args.resume, stage=stage, log=log)
    finally:
        for bar in bars:
            bar.close()
    return {"model": str(args.out / "model"), "seconds": summary["seconds"],
            "vae_loss": summary["vae_loss_last100"], "unet_loss": summary["unet_loss_last100"]}
