"""The run directory of ``train-editor``: the small InstructPix2Pix, from the built-in scenes
to a diffusers folder that :mod:`jaxedit.editors` loads like any other.

The training pipeline of the bundled editor, beside the other pipelines: :mod:`.edit_data`
(its dataset, from the built-in scenes), :mod:`.tiny_ip2p` (its networks' configs and
training steps), :mod:`.export` (the diffusers folder), :mod:`.quality` (its evaluation on
held-out cameras); this module writes the run directory:

    OUT/dataset.npz              the edit pairs (uint8), built once, reused on --resume
    OUT/checkpoints/vae.npz      the autoencoder's training state (every CHECKPOINT_EVERY steps)
    OUT/checkpoints/decoder.npz  with --init and --decoder-steps: the decoder's fine-tuning
    OUT/checkpoints/unet.npz     the UNet's and text encoder's state, EMA included
    OUT/training.json            the config, the losses, the seconds of each stage
    OUT/model/                   the diffusers folder (EMA weights), with instructions.json
                                 and a model card

Stages run in order and each resumes from its checkpoint: the dataset, the tokenizer (a
pure function of the instructions), the VAE (with ``--init``: kept, or its decoder
fine-tuned), the latents (a pure function of the VAE's encoder), the UNet (with ``--init``
and ``--steps 0``: kept). The same config and seed give the same weights on the same
machine.

A resume reads the run's files through one checked reader each (:func:`read_dataset`,
:func:`read_stage_checkpoint`) and refuses, before anything is written, a folder with nothing
to resume, a name taken by the wrong kind of thing (:data:`RUN_LAYOUT`), and a dataset or
checkpoint that is damaged or was made with other settings: a refused resume leaves the run
directory byte-identical.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Callable

import equinox as eqx
import jax
import numpy as np

from jaxedit.errors import DataError
from jaxedit.io.checkpoint import read_pytree, restore, save_pytree
from jaxedit.io.files import atomic_path, atomic_write_text, read_npz
from jaxedit.models import CLIPTokenizer
from jaxedit.models.load import DDPMSchedule
from jaxedit_lab.train_editor import edit_data, tiny_ip2p
from jaxedit_lab.train_editor.export import write_pipeline, write_tokenizer

#: Steps between checkpoints of either stage.
CHECKPOINT_EVERY = 250


def _config_record(cfg: tiny_ip2p.EditorTrainConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


#: The settings the autoencoder's stage depends on: a run that changes only the UNet's
#: settings resumes the finished autoencoder instead of training it again.
VAE_SETTINGS = ("size", "procedural_views", "off_orbit_views", "off_orbit_edits",
                "off_orbit_geometry_only", "scenes", "vae_steps", "vae_batch", "vae_crop",
                "vae_lr", "seed")


#: The settings the decoder's fine-tuning depends on (the dataset's, the autoencoder's
#: batches and rate, its length, the autoencoder it starts from, the seed).
DECODER_SETTINGS = ("size", "procedural_views", "off_orbit_views", "off_orbit_edits",
                    "off_orbit_geometry_only", "scenes", "vae_batch", "vae_crop", "vae_lr",
                    "decoder_steps", "init", "seed")

#: Each stage's checkpoint kind, and the settings it depends on (None: the whole config).
STAGE_SETTINGS = {"editor-vae": VAE_SETTINGS, "editor-decoder": DECODER_SETTINGS,
                  "editor-unet": None}


#: Settings added to the config after runs were checkpointed, with the value such a run had.
ADDED_SETTINGS = {"outcome_from_noise": False, "balance_outcomes": False, "decoder_steps": 0,
                  "off_orbit_views": 0, "off_orbit_edits": True,
                  "off_orbit_geometry_only": False}


def _stage_record(cfg, kind: str) -> dict:
    record, names = _config_record(cfg), STAGE_SETTINGS[kind]
    return record if names is None else {k: record[k] for k in names}


def _stage_steps(cfg, kind: str) -> int:
    return {"editor-vae": cfg.vae_steps, "editor-decoder": cfg.decoder_steps,
            "editor-unet": cfg.steps}[kind]


#: What a run directory holds, by kind ("dir" / "file"): each is checked before any work, so
#: a name taken by the wrong kind of thing is one line, not a traceback at the end of a run.
RUN_LAYOUT = {"dataset.npz": "file", "training.json": "file", "checkpoints": "dir",
              "checkpoints/vae.npz": "file", "checkpoints/decoder.npz": "file",
              "checkpoints/unet.npz": "file", "model": "dir",
              "model/tokenizer": "dir"}


def check_run_folder(out: Path) -> None:
    """Refuse, before any work, a run directory where a name the run writes (:data:`RUN_LAYOUT`)
    is taken by the wrong kind of thing (a file where a folder goes, or the reverse)."""
    for name, kind in RUN_LAYOUT.items():
        p = out / name
        if p.exists() and p.is_dir() != (kind == "dir"):
            what = "a folder" if kind == "dir" else "a file"
            raise DataError(p, f"must be {what} of the training run; move it or choose "
                               f"another --out")


def _dataset_record(cfg) -> dict:
    return {"size": cfg.size, "procedural_views": cfg.procedural_views,
            "off_orbit_views": cfg.off_orbit_views, "off_orbit_edits": cfg.off_orbit_edits,
            "off_orbit_geometry_only": cfg.off_orbit_geometry_only, "scenes": list(cfg.scenes)}


#: The dataset record's keys, and the value a record written before a key existed reads as.
DATASET_RECORD = ("size", "procedural_views", "off_orbit_views", "off_orbit_edits",
                  "off_orbit_geometry_only", "scenes")
DATASET_RECORD_ADDED = {k: v for k, v in ADDED_SETTINGS.items() if k in DATASET_RECORD}


#: dataset.npz's arrays: (dtype kind, number of dimensions); images are [N, size, size, 3].
DATASET_ARRAYS = {"inputs": ("u", 4), "scene": ("i", 1), "held_out": ("b", 1),
                  "targets": ("u", 4), "target_view": ("i", 1), "target_instruction": ("i", 1),
                  "target_outcome": ("i", 1)}


def _checked_dataset_record(record, extra_counts: tuple[str, ...] = ()):
    """A dataset record with the settings added since read as such a run had them
    (:data:`DATASET_RECORD_ADDED`); None unless it is a dict of exactly :data:`DATASET_RECORD`
    and ``extra_counts`` (integers a record of another file adds), each of the type a run
    writes."""
    if not isinstance(record, dict):
        return None
    record = {**DATASET_RECORD_ADDED, **record}
    counts = ("size", "procedural_views", "off_orbit_views", *extra_counts)
    ok = (set(record) == set(DATASET_RECORD) | set(counts)
          and all(isinstance(record[k], int) and not isinstance(record[k], bool) for k in counts)
          and isinstance(record["off_orbit_edits"], bool)
          and isinstance(record["off_orbit_geometry_only"], bool)
          and isinstance(record["scenes"], list)
          and all(isinstance(x, str) for x in record["scenes"]))
    return record if ok else None


def read_dataset(path: Path) -> tuple[dict, edit_data.EditDataset]:
    """(the settings it was built with, the dataset) of a ``dataset.npz``: the one reader of
    the file, which checks its record, every array's dtype and rank, that the images are
    square RGB of the recorded size, and that every index points inside its table.

    Raises:
      DataError naming ``path``.
    """
    arrays = read_npz(path)
    try:
        record = json.loads(str(arrays.pop("meta")))
    except (KeyError, json.JSONDecodeError):
        raise DataError(path, "not a train-editor dataset (no readable settings record); "
                              "delete it to rebuild it") from None
    checked = _checked_dataset_record(record)
    if checked is None:
        raise DataError(path, f"its settings record is not {{{', '.join(DATASET_RECORD)}}}: "
                              f"{json.dumps(record)[:120]}; delete it to rebuild it")
    record = checked
    if set(arrays) != set(DATASET_ARRAYS):
        raise DataError(path, f"holds arrays {sorted(arrays)}, expected "
                              f"{sorted(DATASET_ARRAYS)}; delete it to rebuild it")
    for name, (kind, ndim) in DATASET_ARRAYS.items():
        a = arrays[name]
        if a.dtype.kind != kind or a.ndim != ndim:
            raise DataError(path, f"array {name} is {a.dtype} with {a.ndim} dimensions, "
                                  f"expected kind {kind!r} with {ndim}; delete it to rebuild it")
    size, n, m = record["size"], len(arrays["inputs"]), len(arrays["targets"])
    problem = None
    for name in ("inputs", "targets"):
        if arrays[name].shape[1:] != (size, size, 3):
            problem = f"{name} are {list(arrays[name].shape[1:])}, expected [{size}, {size}, 3]"
    if len(arrays["scene"]) != n or len(arrays["held_out"]) != n:
        problem = "scene / held_out do not have one entry per input view"
    elif any(len(arrays[k]) != m for k in ("target_view", "target_instruction",
                                           "target_outcome")):
        problem = "target_view / target_instruction / target_outcome do not match targets"
    elif m and not (0 <= arrays["target_view"].min() and arrays["target_view"].max() < n):
        problem = "target_view points outside the input views"
    elif m and not (0 <= arrays["target_instruction"].min()
                    and arrays["target_instruction"].max() < len(edit_data.INSTRUCTIONS)):
        problem = "target_instruction points outside the instructions"
    elif n and not (0 <= arrays["scene"].min() and arrays["scene"].max() < len(record["scenes"])):
        problem = "scene points outside the scenes"
    if problem:
        raise DataError(path, f"{problem}; delete it to rebuild it")
    return record, edit_data.EditDataset(tuple(record["scenes"]), edit_data.INSTRUCTIONS,
                                         **arrays)


def stored_dataset(cfg, out: Path, *, resume: bool = False) -> edit_data.EditDataset | None:
    """OUT/dataset.npz when it holds this config's dataset; None when it must be built.

    On ``resume`` an existing dataset that is damaged or was built with other settings is
    refused (the run's checkpoints were trained on it; it is left as it is), not rebuilt.
    """
    path = out / "dataset.npz"
    if not path.exists():
        return None
    try:
        stored, data = read_dataset(path)
    except DataError:
        if resume:
            raise
        return None
    if stored == _dataset_record(cfg):
        return data
    if resume:
        raise DataError(path, f"was built with other settings ({json.dumps(stored)[:160]}); "
                              f"use its flags or another --out")
    return None


def build_dataset(cfg, out: Path, progress=None) -> edit_data.EditDataset:
    """This config's dataset, built from its record and written with it to OUT/dataset.npz
    (atomically)."""
    record = _dataset_record(cfg)
    data = rebuild_dataset(record, progress)
    with atomic_path(out / "dataset.npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.asarray(json.dumps(record)), **data.arrays())
    return data


def trained_on(folder: str | Path) -> dict:
    """The dataset settings an exported editor folder was trained with: the ``"dataset"``
    record of its ``instructions.json`` (:data:`DATASET_RECORD` and ``holdout_every``), a
    setting added since the folder was written read as such a run had it.

    Raises:
      DataError naming the file when the folder lists no such record (it was not written by
      ``train-editor``, so no dataset can be rebuilt for it) or a damaged one.
    """
    path = Path(folder) / "instructions.json"
    try:
        record = json.loads(path.read_text())["dataset"]
    except (OSError, ValueError, KeyError, TypeError):
        raise DataError(path, "lists no training dataset (a folder written by "
                              "`python -m experiments train-editor` does)") from None
    checked = _checked_dataset_record(record, ("holdout_every",))
    if checked is None:
        raise DataError(path, f"its training dataset record is not {{"
                              f"{', '.join(DATASET_RECORD)}, holdout_every}}: "
                              f"{json.dumps(record)[:120]}")
    return checked


def rebuild_dataset(settings: dict, progress=None) -> edit_data.EditDataset:
    """The dataset a dataset record describes: a run's (:func:`_dataset_record`), or the one a
    folder was trained on (:func:`trained_on`)."""
    return edit_data.build_dataset(settings["size"], settings["procedural_views"],
                                   tuple(settings["scenes"]), progress,
                                   settings["off_orbit_views"], settings["off_orbit_edits"],
                                   settings["off_orbit_geometry_only"])


def tokenizer_folder(out: Path) -> Path:
    return out / "model" / "tokenizer"


#: The record each stage's checkpoint carries beside its state (all required, no others).
CHECKPOINT_META = {"config": dict, "step": int, "losses": list}


def read_stage_checkpoint(path: Path, kind: str, cfg) -> tuple[dict, int, list[float]]:
    """(arrays, step, losses) of a stage's checkpoint: the one reader of ``vae.npz`` /
    ``decoder.npz`` / ``unet.npz``, which checks its record's keys and types, that it was
    written by a run with this config's settings of the stage, and that its step and losses
    agree with each other, with the stored state's step and with the stage's length.

    Raises:
      DataError naming ``path``.
    """
    arrays, meta = read_pytree(path, kind=kind)
    older = isinstance(meta, dict) and set(meta) == {"config", "step"}
    if older:
        meta = dict(meta, losses=[])  # a checkpoint of an older run has no losses
    if not isinstance(meta, dict) or set(meta) != set(CHECKPOINT_META):
        keys = sorted(meta) if isinstance(meta, dict) else type(meta).__name__
        raise DataError(path, f"checkpoint record has keys {keys}, expected "
                              f"{sorted(CHECKPOINT_META)}; delete it to start the stage over")
    for key, kind_ in CHECKPOINT_META.items():
        if not isinstance(meta[key], kind_) or isinstance(meta[key], bool):
            raise DataError(path, f"checkpoint record's {key} is a {type(meta[key]).__name__}, "
                                  f"expected a {kind_.__name__}")
    # A setting added since the checkpoint was written reads as its default then.
    stored = {**ADDED_SETTINGS, **meta["config"]}
    if STAGE_SETTINGS[kind] is not None:
        stored = {k: stored.get(k) for k in STAGE_SETTINGS[kind]}
    if stored != _stage_record(cfg, kind):
        raise DataError(path, "was written by a run with other settings; use its own flags "
                              "or another --out")
    step, losses = meta["step"], meta["losses"]
    total = _stage_steps(cfg, kind)
    state_step = arrays.get(".step")
    if (not 0 <= step <= total or (len(losses) != step and not older)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       and math.isfinite(v) for v in losses)
            or state_step is None or state_step.shape != () or int(state_step) != step):
        raise DataError(path, f"checkpoint record is inconsistent (step {step} of {total}, "
                              f"{len(losses)} losses, state at step "
                              f"{None if state_step is None else state_step.tolist()}); "
                              f"delete it to start the stage over")
    return arrays, step, [float(v) for v in losses]


def _restored(stored: tuple, template, path: Path) -> tuple[object, list[float]]:
    """(the stage's state, its losses so far) from :func:`read_stage_checkpoint`'s answer."""
    arrays, _, losses = stored
    return restore(template, arrays, path), losses


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
    check_run_folder(out)
    stages = {"editor-vae": ckpt / "vae.npz", "editor-decoder": ckpt / "decoder.npz",
              "editor-unet": ckpt / "unet.npz"}
    if not resume and ckpt.exists() and any(ckpt.iterdir()):
        raise DataError(ckpt, "holds a previous run's checkpoints; pass --resume to continue "
                              "it or choose another --out")
    if resume and not any(p.exists() for p in stages.values()) and not (
            out / "dataset.npz").exists():
        raise DataError(out, "nothing to resume (no checkpoints/vae.npz, decoder.npz, "
                             "unet.npz or dataset.npz); run without --resume to start a new "
                             "run")
    stage = stage or (lambda name, total, done: None)
    seconds: dict[str, float] = {}
    key = jax.random.key(cfg.seed)
    k_vae, k_unet, k_scale, k_degrade, k_nets = jax.random.split(key, 5)

    # Every record a resume reads is read and checked before anything is written: a refused
    # resume leaves the run directory as it was. (The states are restored into their
    # templates later, as each stage starts: building a template costs a minute.)
    stored = {kind: read_stage_checkpoint(path, kind, cfg) for kind, path in stages.items()
              if resume and path.exists()}

    # The tokenizer, and --init's networks checked against this config before any work.
    vocab, merges = run_tokenizer(cfg, out, resume)
    start = initial_networks(cfg, vocab) if cfg.init else None

    data = stored_dataset(cfg, out, resume=resume)  # checked before the stage is announced
    t0 = time.perf_counter()
    on_scene = stage("dataset", len(cfg.scenes), 0)
    built: list[str] = []

    def scene_done(name: str) -> None:
        built.append(name)
        if on_scene is not None:
            on_scene(len(built), float("nan"))

    if data is None:
        data = build_dataset(cfg, out, scene_done)
    ckpt.mkdir(parents=True, exist_ok=True)
    seconds["dataset"] = time.perf_counter() - t0
    train_views = np.flatnonzero(~data.held_out)
    log(f"dataset: {len(data.inputs)} views ({int(data.held_out.sum())} held out), "
        f"{len(data.targets)} edited views, {len(data.instructions)} instructions")

    # The tokenizer (above), written where the model folder keeps it.
    write_tokenizer(tokenizer_folder(out), vocab, merges, bos=tiny_ip2p.BOS, eos=tiny_ip2p.EOS,
                    max_length=tiny_ip2p.MAX_LENGTH)
    tokenizer = CLIPTokenizer.from_folder(tokenizer_folder(out))
    tokens = tokenizer([i.prompt for i in data.instructions] + [""])

    # The autoencoder, on the training views' inputs and targets (or --init's, kept or its
    # decoder fine-tuned on them).
    t0 = time.perf_counter()
    train_rows = data.split(held_out=False)
    vae_static = eqx.filter(tiny_ip2p.AutoencoderKL.from_config(
        tiny_ip2p.vae_config(cfg), key=jax.random.key(0)), eqx.is_array, inverse=True)
    vae_losses: list[float] = []
    from_init = start is not None
    autoencoder = "decoder fine-tuned" if cfg.decoder_steps else "kept" if from_init else "trained"
    if from_init:
        log(f"autoencoder, UNet and text encoder start from {cfg.init}")
    if autoencoder != "kept":
        kind = "editor-decoder" if from_init else "editor-vae"
        vae_images = np.concatenate([data.inputs[train_views], data.targets[train_rows]])
        state = (tiny_ip2p.init_decoder(cfg, start["vae"], k_vae) if from_init
                 else tiny_ip2p.init_vae(cfg, k_vae))
        if kind in stored:
            state, vae_losses = _restored(stored[kind], state, stages[kind])
        step = tiny_ip2p.make_vae_step(cfg, vae_static, jax.numpy.asarray(vae_images),
                                       decoder_only=from_init)
        total = _stage_steps(cfg, kind)
        state, vae_losses = tiny_ip2p.run_steps(
            step, state, total, every=CHECKPOINT_EVERY, losses=vae_losses,
            on_progress=stage("decoder" if from_init else "vae", total, int(state.step)),
            checkpoint=_checkpointer(stages[kind], kind, cfg))
        vae = eqx.combine(state.vae, vae_static)
    else:
        vae = eqx.combine(start["vae"], vae_static)
    seconds["vae"] = time.perf_counter() - t0

    # The UNet and the text encoder: trained on the latents (every image encoded once, the
    # scaling factor from the training targets), or --init's kept with its scaling factor.
    unet, text = tiny_ip2p.build_networks(cfg, len(vocab), tokenizer.bos_id, tokenizer.eos_id,
                                          k_nets)
    statics = (eqx.filter(unet, eqx.is_array, inverse=True),
               eqx.filter(text, eqx.is_array, inverse=True))
    unet_losses: list[float] = []
    if cfg.steps:
        t0 = time.perf_counter()
        d = tiny_ip2p.unet_data(data, vae, tokens, k_degrade)
        scaling = tiny_ip2p.latent_scaling(np.asarray(d.target_mean)[train_rows],
                                           np.asarray(d.target_std)[train_rows], k_scale)
        seconds["latents"] = time.perf_counter() - t0
        log(f"latent scaling factor {scaling:.4f}")
        t0 = time.perf_counter()
        if from_init:
            unet, text = (eqx.combine(start[name], static)
                          for name, static in zip(("unet", "text"), statics))
        ustate = tiny_ip2p.init_unet(cfg, unet, text, k_unet)
        if "editor-unet" in stored:
            ustate, unet_losses = _restored(stored["editor-unet"], ustate, stages["editor-unet"])
        schedule = DDPMSchedule.from_config(tiny_ip2p.SCHEDULER_CONFIG)
        ustep = tiny_ip2p.make_unet_step(cfg, statics, d, scaling, schedule)
        ustate, unet_losses = tiny_ip2p.run_steps(
            ustep, ustate, cfg.steps, every=CHECKPOINT_EVERY, losses=unet_losses,
            on_progress=stage("unet", cfg.steps, int(ustate.step)),
            checkpoint=_checkpointer(stages["editor-unet"], "editor-unet", cfg))
        seconds["unet"] = time.perf_counter() - t0
        exported = ustate.ema
    else:
        scaling = start["scaling"]
        log(f"UNet and text encoder kept; latent scaling factor {scaling:.4f} (--init's)")
        exported = tiny_ip2p.Networks(start["unet"], start["text"])

    summary = {
        "config": _config_record(cfg), "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "devices": [str(dv) for dv in jax.devices()],
        "dataset": {"views": int(len(data.inputs)), "held_out_views": int(data.held_out.sum()),
                    "edited_views": int(len(data.targets)),
                    "scenes": list(data.scenes)},
        "scaling_factor": scaling, "autoencoder": autoencoder,
        "unet": "trained" if cfg.steps else "kept",
        "vae_loss_last100": _mean_tail(vae_losses), "unet_loss_last100": _mean_tail(unet_losses),
        "vae_losses_every50": vae_losses[::50], "unet_losses_every50": unet_losses[::50],
    }
    write_pipeline(
        out / "model", unet=eqx.combine(exported.unet, statics[0]),
        unet_config=tiny_ip2p.unet_config(cfg), vae=vae,
        vae_config=tiny_ip2p.vae_config(cfg, scaling),
        text_encoder=eqx.combine(exported.text, statics[1]),
        text_config=tiny_ip2p.text_config(cfg, len(vocab), tokenizer.bos_id, tokenizer.eos_id),
        vocab=vocab, merges=merges, bos=tiny_ip2p.BOS, eos=tiny_ip2p.EOS,
        max_length=tiny_ip2p.MAX_LENGTH, scheduler_config=tiny_ip2p.SCHEDULER_CONFIG,
        instructions=[i.describe() for i in data.instructions],
        dataset={**_dataset_record(cfg), "holdout_every": edit_data.HOLDOUT_EVERY})
    atomic_write_text(out / "training.json", json.dumps(summary, indent=2) + "\n")
    return summary


def run_tokenizer(cfg, out: Path, resume: bool) -> tuple[dict[str, int], list]:
    """(vocab, merges) of the run: ``--init``'s own tokenizer (its text encoder was trained
    on its ids), on ``resume`` the one the run wrote (``tokenizers``' BPE trainer breaks ties
    differently in each process, so learning it again could give the checkpoint's text
    encoder other ids), else one learnt on the instructions."""
    from jaxedit_lab.train_editor.export import read_tokenizer

    for folder, use in ((Path(cfg.init) / "tokenizer", bool(cfg.init)),
                        (tokenizer_folder(out), resume)):
        if use and (folder / "vocab.json").is_file() and (folder / "merges.txt").is_file():
            return read_tokenizer(folder)
    return tiny_ip2p.train_tokenizer([i.prompt for i in edit_data.INSTRUCTIONS])


def initial_networks(cfg, vocab: dict) -> dict:
    """The arrays of ``cfg.init``'s autoencoder, UNet and text encoder ({"vae", "unet",
    "text"}), checked to be this config's architecture (every array's path and shape), and
    its latent scaling factor ("scaling").

    Raises:
      DataError naming ``--init``.
    """
    from jaxedit.models import load_ip2p

    models = load_ip2p(Path(cfg.init))
    key = jax.random.key(0)
    fresh = {"vae": tiny_ip2p.AutoencoderKL.from_config(tiny_ip2p.vae_config(cfg), key=key),
             **dict(zip(("unet", "text"), tiny_ip2p.build_networks(
                 cfg, len(vocab), vocab[tiny_ip2p.BOS], vocab[tiny_ip2p.EOS], key)))}
    loaded = {"vae": models.vae, "unet": models.unet, "text": models.text_encoder}
    out = {}
    for name, module in loaded.items():
        want = eqx.filter(fresh[name], eqx.is_array)
        got = eqx.filter(module, eqx.is_array)
        shapes = lambda t: [(jax.tree_util.keystr(p), x.shape)  # noqa: E731
                            for p, x in jax.tree_util.tree_leaves_with_path(t)]
        if shapes(want) != shapes(got):
            raise DataError("--init", f"{cfg.init}: its {name} is not this config's "
                                      f"architecture (--size, --text-width, --text-layers)")
        out[name] = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(want),
                                                 jax.tree_util.tree_leaves(got))
    out["scaling"] = float(models.vae.scaling_factor)
    return out


def _mean_tail(losses: list[float], n: int = 100) -> float | None:
    tail = losses[-n:]
    return float(np.mean(tail)) if tail else None
