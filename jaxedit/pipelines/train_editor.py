"""The run directory of ``train-editor``: the small InstructPix2Pix, from the built-in scenes
to a diffusers folder (:mod:`jaxedit.editors.tiny_ip2p` holds the training itself).

    OUT/dataset.npz              the edit pairs (uint8), built once, reused on --resume
    OUT/checkpoints/vae.npz      the autoencoder's training state (every CHECKPOINT_EVERY steps)
    OUT/checkpoints/unet.npz     the UNet's and text encoder's state, EMA included
    OUT/training.json            the config, the losses, the seconds of each stage
    OUT/model/                   the diffusers folder (EMA weights), with instructions.json
                                 and a model card

Stages run in order and each resumes from its checkpoint: the dataset, the tokenizer (a
pure function of the instructions), the VAE, the latents (a pure function of the VAE), the
UNet. The same config and seed give the same weights on the same machine.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Callable

import equinox as eqx
import jax
import numpy as np

from ..editors import edit_data, tiny_ip2p
from ..editors.export import write_pipeline, write_tokenizer
from ..errors import DataError
from ..io.checkpoint import read_pytree, restore, save_pytree
from ..io.files import atomic_path, atomic_write_text, read_npz
from ..models import CLIPTokenizer
from ..models.load import DDPMSchedule

#: Steps between checkpoints of either stage.
CHECKPOINT_EVERY = 250


def _config_record(cfg: tiny_ip2p.EditorTrainConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


#: The settings the autoencoder's stage depends on: a run that changes only the UNet's
#: settings resumes the finished autoencoder instead of training it again.
VAE_SETTINGS = ("size", "procedural_views", "scenes", "vae_steps", "vae_batch", "vae_crop",
                "vae_lr", "seed")


def _stage_record(cfg, kind: str) -> dict:
    record = _config_record(cfg)
    return {k: record[k] for k in VAE_SETTINGS} if kind == "editor-vae" else record


def load_or_build_dataset(cfg, out: Path, progress=None) -> edit_data.EditDataset:
    """OUT/dataset.npz when it holds this config's dataset, else built and written."""
    path = out / "dataset.npz"
    record = {"size": cfg.size, "procedural_views": cfg.procedural_views,
              "scenes": list(cfg.scenes)}
    if path.exists():
        arrays = read_npz(path)
        meta = json.loads(str(arrays.pop("meta", "{}")))
        if meta == record:
            return edit_data.EditDataset(tuple(cfg.scenes), edit_data.INSTRUCTIONS, **arrays)
    data = edit_data.build_dataset(cfg.size, cfg.procedural_views, tuple(cfg.scenes), progress)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.asarray(json.dumps(record)), **data.arrays())
    return data


def tokenizer_folder(out: Path) -> Path:
    return out / "model" / "tokenizer"


def _resume_state(path: Path, template, kind: str, cfg) -> tuple[object, list[float]]:
    """(the stage's state, its losses so far) from its checkpoint; refuses other settings."""
    arrays, meta = read_pytree(path, kind=kind)
    stored = meta.get("config")
    if stored is not None and kind == "editor-vae":
        stored = {k: stored.get(k) for k in VAE_SETTINGS}
    if stored != _stage_record(cfg, kind):
        raise DataError(path, "was written by a run with other settings; use its own flags "
                              "or another --out")
    losses = meta.get("losses", [])  # a checkpoint of an older run has none
    return restore(template, arrays, path), [float(v) for v in losses]


def _checkpointer(path: Path, kind: str, cfg):
    def save(state, losses: list[float]):
        save_pytree(path, state, kind=kind, meta={"config": _stage_record(cfg, kind),
                                                  "step": int(state.step), "losses": losses})
    return save


def train_editor(cfg: tiny_ip2p.EditorTrainConfig, out: str | Path, *, resume: bool = False,
                 stage: Callable[[str, int, int], Callable[[int, float], None]] | None = None,
                 log: Callable[[str], None] = lambda s: None) -> dict:
    """Train the small IP2P into ``out`` (see the module docstring); returns the summary.

    ``stage(name, total, done)`` is called at each stage's start (``done``: the units a
    resumed stage had already done) and returns the stage's
    ``on_progress(done, loss)`` (a progress bar at the edge); ``log`` takes one-line notes.
    Without ``resume`` a folder that already holds checkpoints is refused.
    """
    cfg = cfg.check()
    out = Path(out)
    ckpt = out / "checkpoints"
    if not resume and ckpt.exists() and any(ckpt.iterdir()):
        raise DataError(ckpt, "holds a previous run's checkpoints; pass --resume to continue "
                              "it or choose another --out")
    ckpt.mkdir(parents=True, exist_ok=True)
    stage = stage or (lambda name, total, done: None)
    seconds: dict[str, float] = {}
    key = jax.random.key(cfg.seed)
    k_vae, k_unet, k_scale, k_degrade, k_nets = jax.random.split(key, 5)

    t0 = time.perf_counter()
    on_scene = stage("dataset", len(cfg.scenes), 0)
    built: list[str] = []

    def scene_done(name: str) -> None:
        built.append(name)
        if on_scene is not None:
            on_scene(len(built), float("nan"))

    data = load_or_build_dataset(cfg, out, scene_done)
    seconds["dataset"] = time.perf_counter() - t0
    train_views = np.flatnonzero(~data.held_out)
    log(f"dataset: {len(data.inputs)} views ({int(data.held_out.sum())} held out), "
        f"{len(data.targets)} edited views, {len(data.instructions)} instructions")

    # The tokenizer: learnt on the instructions, written where the model folder keeps it.
    vocab, merges = tiny_ip2p.train_tokenizer([i.prompt for i in data.instructions])
    write_tokenizer(tokenizer_folder(out), vocab, merges, bos=tiny_ip2p.BOS, eos=tiny_ip2p.EOS,
                    max_length=tiny_ip2p.MAX_LENGTH)
    tokenizer = CLIPTokenizer.from_folder(tokenizer_folder(out))
    tokens = tokenizer([i.prompt for i in data.instructions] + [""])

    # The autoencoder, on the training views' inputs and targets.
    t0 = time.perf_counter()
    train_rows = data.split(held_out=False)
    vae_images = np.concatenate([data.inputs[train_views], data.targets[train_rows]])
    state = tiny_ip2p.init_vae(cfg, k_vae)
    vae_static = eqx.filter(tiny_ip2p.AutoencoderKL.from_config(
        tiny_ip2p.vae_config(cfg), key=jax.random.key(0)), eqx.is_array, inverse=True)
    vae_losses: list[float] = []
    if resume and (ckpt / "vae.npz").exists():
        state, vae_losses = _resume_state(ckpt / "vae.npz", state, "editor-vae", cfg)
    step = tiny_ip2p.make_vae_step(cfg, vae_static, jax.numpy.asarray(vae_images))
    state, vae_losses = tiny_ip2p.run_steps(
        step, state, cfg.vae_steps, every=CHECKPOINT_EVERY, losses=vae_losses,
        on_progress=stage("vae", cfg.vae_steps, int(state.step)),
        checkpoint=_checkpointer(ckpt / "vae.npz", "editor-vae", cfg))
    vae = eqx.combine(state.vae, vae_static)
    seconds["vae"] = time.perf_counter() - t0

    # The latents: every image encoded once; the scaling factor from the training targets.
    t0 = time.perf_counter()
    d = tiny_ip2p.unet_data(data, vae, tokens, k_degrade)
    scaling = tiny_ip2p.latent_scaling(np.asarray(d.target_mean)[train_rows],
                                       np.asarray(d.target_std)[train_rows], k_scale)
    seconds["latents"] = time.perf_counter() - t0
    log(f"latent scaling factor {scaling:.4f}")

    # The UNet and the text encoder.
    t0 = time.perf_counter()
    unet, text = tiny_ip2p.build_networks(cfg, len(vocab), tokenizer.bos_id, tokenizer.eos_id,
                                          k_nets)
    statics = (eqx.filter(unet, eqx.is_array, inverse=True),
               eqx.filter(text, eqx.is_array, inverse=True))
    ustate = tiny_ip2p.init_unet(cfg, unet, text, k_unet)
    unet_losses: list[float] = []
    if resume and (ckpt / "unet.npz").exists():
        ustate, unet_losses = _resume_state(ckpt / "unet.npz", ustate, "editor-unet", cfg)
    schedule = DDPMSchedule.from_config(tiny_ip2p.SCHEDULER_CONFIG)
    ustep = tiny_ip2p.make_unet_step(cfg, statics, d, scaling, schedule)
    ustate, unet_losses = tiny_ip2p.run_steps(
        ustep, ustate, cfg.steps, every=CHECKPOINT_EVERY, losses=unet_losses,
        on_progress=stage("unet", cfg.steps, int(ustate.step)),
        checkpoint=_checkpointer(ckpt / "unet.npz", "editor-unet", cfg))
    seconds["unet"] = time.perf_counter() - t0

    summary = {
        "config": _config_record(cfg), "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "devices": [str(dv) for dv in jax.devices()],
        "dataset": {"views": int(len(data.inputs)), "held_out_views": int(data.held_out.sum()),
                    "edited_views": int(len(data.targets)),
                    "scenes": list(data.scenes)},
        "scaling_factor": scaling,
        "vae_loss_last100": _mean_tail(vae_losses), "unet_loss_last100": _mean_tail(unet_losses),
        "vae_losses_every50": vae_losses[::50], "unet_losses_every50": unet_losses[::50],
    }
    write_pipeline(
        out / "model", unet=eqx.combine(ustate.ema.unet, statics[0]),
        unet_config=tiny_ip2p.unet_config(cfg), vae=vae,
        vae_config=tiny_ip2p.vae_config(cfg, scaling),
        text_encoder=eqx.combine(ustate.ema.text, statics[1]),
        text_config=tiny_ip2p.text_config(cfg, len(vocab), tokenizer.bos_id, tokenizer.eos_id),
        vocab=vocab, merges=merges, bos=tiny_ip2p.BOS, eos=tiny_ip2p.EOS,
        max_length=tiny_ip2p.MAX_LENGTH, scheduler_config=tiny_ip2p.SCHEDULER_CONFIG,
        instructions=[i.describe() for i in data.instructions],
        dataset={"size": cfg.size, "procedural_views": cfg.procedural_views,
                 "scenes": list(cfg.scenes), "holdout_every": edit_data.HOLDOUT_EVERY})
    atomic_write_text(out / "training.json", json.dumps(summary, indent=2) + "\n")
    return summary


def _mean_tail(losses: list[float], n: int = 100) -> float | None:
    tail = losses[-n:]
    return float(np.mean(tail)) if tail else None
