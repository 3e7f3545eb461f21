"""Training the small InstructPix2Pix that ships with jaxedit, with jaxedit's own modules.

Three networks in Stable Diffusion's architecture, small enough for a 2-core CPU
(:mod:`jaxedit.models`, the same modules the JAX editor runs):

- an AutoencoderKL with 3 levels (4x downsampling, 4 latent channels), trained first on the
  dataset's images (L1 + a small KL term) on random crops, its ``scaling_factor`` set to
  1 / std of the latents as Stable Diffusion's;
- a CLIP-style text encoder (transformers' CLIPTextModel architecture) over a byte-level BPE
  tokenizer trained on the instructions with ``tokenizers`` (CLIP's vocabulary layout:
  the 256 byte symbols, with and without ``</w>``, then the merges);
- the 8-channel conditional UNet, trained jointly with the text encoder on IP2P's objective:
  eps-prediction of the edited view's noised latent, conditioned on the instruction and on
  the input view's latent (posterior mode, unscaled), with IP2P's conditioning dropout (text
  alone, image alone, both, 5 % each) so dual classifier-free guidance works. The empty
  prompt means "keep the view": an example whose text alone is dropped takes the input as
  its target (``empty_is_identity``), so the branch E("") + image that identity, ProEdit's
  e(0) and the image guidance read is the input, not a mixture of every instruction's edits.

Training examples (all drawn inside the compiled step from the step's key): an instruction
uniformly (plus the identity class: the empty prompt and the input itself as target), a
training view it applies to, and for a divergent instruction one of its outcomes uniformly
(``outcome_from_noise``: uniformly too, but read from the example's diffusion noise).
The input view is, half of the time, degraded as a reconstruction's render is (a Gaussian
blur of random width and pixel noise), so the editor also sees renders like those IDU gives
it; the targets stay clean. An exponential moving average of the UNet and text encoder is
what is exported.

Everything is a pure function of the config and the seed; :func:`train_vae` and
:func:`train_unet` advance a state pytree one jit-compiled step at a time and hand it to a
``checkpoint`` callback, so a run can be stopped and resumed (the edge writes the files:
:mod:`jaxedit_lab.train_editor`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxedit.errors import DataError
from jaxedit.models import AutoencoderKL, CLIPTextEncoder, UNet2DCondition
from jaxedit.models.load import DDPMSchedule
from jaxedit_lab.train_editor import edit_data
from jaxedit_lab.train_editor.edit_data import EditDataset

Array = jax.Array

#: CLIP's special tokens (the tokenizer folder names them the same way).
BOS, EOS = "<|startoftext|>", "<|endoftext|>"
MAX_LENGTH = 77


@dataclasses.dataclass(frozen=True)
class EditorTrainConfig:
    """Every setting of a training run (recorded in training.json and the model card).

    Attributes:
      size: image size of the edit dataset and the model (px, a multiple of 4).
      procedural_views: spiral cameras per procedural scene (every 10th held out).
      off_orbit_views: more training cameras per procedural scene, nearer than its orbit and
        up to above it (:func:`edit_data.off_orbit_views`): the object larger in the frame
        and seen from higher than the orbit shows it, as a capture's close-ups and top views
        do.
      off_orbit_edits: whether those cameras also get the instructions' edit targets; off
        (``--off-orbit-identity-only``), they give identity examples only (the empty prompt
        keeps a view seen from there): what they teach is to keep such views, and the
        edits' bands are learnt from the orbit's views alone.
      off_orbit_geometry_only: those cameras get the geometry instruction's edit targets only
        (``--off-orbit-geometry-only``): the image-space edits are learnt from the orbit and
        kept off it as with ``--off-orbit-identity-only``, while a changed shape seen close
        and from above, which the orbit never shows, is learnt from the nearer views.
      scenes: the built-in scenes the dataset is made of.
      vae_steps: training steps of the autoencoder.
      vae_batch: crops per autoencoder step.
      vae_crop: side of the autoencoder's random crops (px).
      vae_lr: the autoencoder's peak learning rate (Adam, cosine decay).
      decoder_steps: with ``init``, steps that fine-tune the kept autoencoder's decoder on
        the training views (``vae_batch`` crops of ``vae_crop`` px, ``vae_lr``). The encoder
        is frozen, so the latents the UNet was trained on, and the UNet, stay valid
        (Stable Diffusion's fine-tuned decoders were made the same way); it sharpens the
        round trip, while what it does to the edits, decoded from the UNet's latents, is
        the quality benchmark's to say (docs/editor.md, v17). 0: the decoder is kept.
      steps: training steps of the UNet and the text encoder; 0 (with ``init`` only): both
        are kept as they are, with ``init``'s latent scaling factor.
      batch: examples per UNet step.
      lr: the UNet's peak learning rate (AdamW, warmup then cosine decay).
      ema: decay of the exponential moving average that is exported.
      identity_share: share of identity examples (empty prompt, the input as target).
      drop: probability of each of IP2P's conditioning dropouts (text, image, both).
      empty_is_identity: an example whose instruction is dropped (IP2P's text dropout, the
        image kept) takes the input as its target, so E("") with the image means "keep the
        view", as the identity examples and ProEdit's e(0) read it. False (the first bundled
        editor's recipe): it keeps its edit, and E("") + image learns a mixture of the input
        (about 2/3) and every instruction's edits (1/3), which the identity edit and the
        image guidance then draw from.
      outcome_from_noise: a divergent instruction's outcome is read from the example's
        diffusion noise (:func:`outcome_of_noise`, each outcome equally likely) instead of
        drawn apart from it. Drawn apart, a noised latent at high noise says nothing of the
        outcome, so the UNet's best guess there is the average of the outcomes, which the
        text guidance then amplifies; read from the noise, the outcome is visible in x_t at
        every noise level, so the UNet could predict one outcome. Tried for v5
        (docs/editor.md): 2000 steps from v4 did not learn it, and the models already pick
        one outcome per seed; off by default.
      balance_outcomes: instructions are drawn in proportion to their outcomes' number, so
        each outcome of a divergent instruction is as frequent as a one-outcome instruction
        (with 2 x 3 outcomes and 4 single ones: each divergent instruction 3/10 of the
        non-identity examples instead of 1/6, each of its outcomes 1/10 instead of 1/18).
        Off: each instruction equally often, a band outcome a third as often as an
        instruction.
      init: a diffusers folder of this architecture (a previous run's ``model/``) whose
        networks start the run: its autoencoder is kept as it is (no VAE stage), its UNet and
        text encoder start the UNet stage (the optimiser and the EMA start afresh). Empty:
        every network starts from random weights.
      degrade: share of inputs degraded as a reconstruction's renders are (blur, noise).
      width: the UNet's channels at each of its three resolutions.
      text_width: width of the text encoder (and the UNet's cross-attention).
      text_layers: transformer layers of the text encoder.
      seed: every random draw of the run derives from it.
    """

    size: int = 64
    procedural_views: int = 100
    off_orbit_views: int = 0
    off_orbit_edits: bool = True
    off_orbit_geometry_only: bool = False
    scenes: tuple[str, ...] = edit_data.SCENES
    vae_steps: int = 2500
    vae_batch: int = 16
    vae_crop: int = 32
    vae_lr: float = 1e-3
    decoder_steps: int = 0
    steps: int = 2000
    batch: int = 32
    lr: float = 5e-4
    ema: float = 0.999
    identity_share: float = 0.1
    drop: float = 0.05
    empty_is_identity: bool = True
    outcome_from_noise: bool = False
    balance_outcomes: bool = False
    degrade: float = 0.5
    #: Channels of the UNet's three levels (not a flag: the shipped architecture).
    width: tuple[int, int, int] = (32, 64, 96)
    text_width: int = 64
    text_layers: int = 2
    init: str = ""
    seed: int = 0

    @staticmethod
    def smoke() -> "EditorTrainConfig":
        """A run of a minute on the CPU (CI): a few steps of each stage on a small dataset."""
        return EditorTrainConfig(size=32, procedural_views=10, vae_steps=3, vae_batch=4,
                                 vae_crop=16, steps=3, batch=4, width=(16, 32, 32),
                                 text_width=32, text_layers=1)

    def check(self) -> "EditorTrainConfig":
        """This config, or a DataError naming the flag of the first setting that is out of
        range, inconsistent, or whose working set exceeds the free memory (checked here,
        before any work: :func:`train_memory`, :func:`jaxedit.memory.require_memory`)."""
        for name in ("size", "procedural_views", "off_orbit_views", "vae_steps", "vae_batch",
                     "vae_crop", "decoder_steps", "steps", "batch", "text_width",
                     "text_layers"):
            value, most = getattr(self, name), MAXIMA[name]
            # The orbit alone, the decoder kept and (from --init) the UNet kept are allowed.
            least = 0 if name in ("off_orbit_views", "decoder_steps", "steps") else 1
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise DataError(_flag(name), f"must be a whole number, got {value!r}")
            if not least <= value <= most:
                raise DataError(_flag(name), f"must be in {least} .. {most}, got {value}")
        if not self.init and (self.decoder_steps or not self.steps):
            flag = "--decoder-steps" if self.decoder_steps else "--steps"
            raise DataError(flag, "fine-tuning the decoder alone or keeping the UNet needs a "
                                  "trained editor to start from: give --init FOLDER (without "
                                  "it every network is trained: --vae-steps, --steps >= 1)")
        if not self.off_orbit_edits and not self.off_orbit_views:
            raise DataError("--off-orbit-identity-only", "needs nearer cameras to give identity "
                            "examples: give --off-orbit-views N with N > 0")
        if self.off_orbit_geometry_only and not (self.off_orbit_views and self.off_orbit_edits):
            raise DataError("--off-orbit-geometry-only", "needs nearer cameras with edit "
                            "targets: give --off-orbit-views N with N > 0, without "
                            "--off-orbit-identity-only")
        if self.size % 16 or self.vae_crop % 4 or self.vae_crop > self.size:
            # The UNet halves the latent (size / 4) twice: size must be a multiple of 16.
            raise DataError("--size", f"size must be a multiple of 16 and the crop a multiple "
                            f"of 4 with crop <= size, got {self.size} and {self.vae_crop}")
        if self.text_width % 2:  # the text encoder's two attention heads split it
            raise DataError("--text-width", f"must be even, got {self.text_width}")
        from jaxedit.scenes import list_scenes

        unknown = [s for s in self.scenes if s not in list_scenes()]
        if unknown or not self.scenes:
            what = f"unknown scene {unknown[0]!r}" if unknown else "no scene given"
            raise DataError("--scenes", f"{what}; built-in scenes: {', '.join(list_scenes())}")
        if "person" in self.scenes and 256 % self.size:  # person's renders are 256 px
            raise DataError("--size", f"256 / size must be an integer with the person scene, "
                            f"got {self.size}")
        for name in ("ema", "identity_share", "drop", "degrade"):
            if not 0 <= float(getattr(self, name)) < 1:
                raise DataError(_flag(name), f"must be in [0, 1), got {getattr(self, name)}")
        for name in ("lr", "vae_lr"):
            if not 0 < float(getattr(self, name)) <= 1:
                raise DataError(_flag(name), f"must be in (0, 1], got {getattr(self, name)}")
        if self.init:
            from pathlib import Path

            folder = Path(self.init)
            missing = [c for c in ("unet", "vae", "text_encoder", "tokenizer")
                       if not (folder / c / "config.json").is_file() and c != "tokenizer"
                       or c == "tokenizer" and not (folder / c / "vocab.json").is_file()]
            if missing:
                raise DataError("--init", f"{self.init!r} is not a diffusers folder of a "
                                f"trained editor (no {missing[0]}/ in it)")
        if not -2**63 <= int(self.seed) < 2**63:  # jax.random.key takes a 64-bit integer
            raise DataError("--seed", f"must fit in 64 bits (|seed| < 2^63), got {self.seed}")
        from jaxedit.memory import require_memory

        require_memory("--size/--procedural-views/--batch/--vae-batch", train_memory(self),
                       f"training at {self.size} px on {self.procedural_views} views per scene")
        return self


#: The largest value of each count of :class:`EditorTrainConfig` (a hundred times or more the
#: shipped run's, which takes an hour on a 2-core CPU): beyond it a typo, not a plan, which
#: would otherwise run for days or fail deep inside the work.
MAXIMA = {"size": 1024, "procedural_views": 10_000, "off_orbit_views": 10_000,
          "vae_steps": 250_000, "vae_batch": 4096, "decoder_steps": 250_000,
          "vae_crop": 1024, "steps": 200_000, "batch": 4096, "text_width": 4096,
          "text_layers": 48}


def _flag(field: str) -> str:
    return f"--{field.replace('_', '-')}"


#: Edited views per input view at most (every outcome of every instruction: 1+1+3+3+1+1).
TARGETS_PER_VIEW = 10


def train_memory(cfg: EditorTrainConfig) -> float:
    """Bytes a training run holds at least: the dataset (uint8 inputs and targets, held three
    times: as built, as the VAE's training set and on the device) plus one scene's float32
    renders while it is built, plus one step's activations of the VAE and of the UNet
    (a few dozen feature maps of the first level kept for the backward pass). A low estimate:
    it refuses only what surely cannot fit."""
    views = (cfg.procedural_views + cfg.off_orbit_views) * len(cfg.scenes)
    pixels = float(cfg.size) ** 2
    dataset = 3 * views * (1 + TARGETS_PER_VIEW) * pixels * 3
    render = (max(cfg.procedural_views, cfg.off_orbit_views) * (1 + TARGETS_PER_VIEW)
              * pixels * 4 * 4)
    kept = 32  # feature maps of the first level a step keeps for its gradient
    vae_step = cfg.vae_batch * float(cfg.vae_crop) ** 2 * 16 * 4 * kept
    unet_step = 3 * cfg.batch * pixels / 16 * cfg.width[0] * 4 * kept
    return dataset + render + max(vae_step, unet_step)


# ----------------------------------------------------------------------------- architectures

SCHEDULER_CONFIG = {
    "_class_name": "DDIMScheduler", "_diffusers_version": "0.27.0",
    "beta_start": 0.00085, "beta_end": 0.012, "beta_schedule": "scaled_linear",
    "num_train_timesteps": 1000, "clip_sample": False, "set_alpha_to_one": False,
    "steps_offset": 1, "prediction_type": "epsilon", "trained_betas": None,
}


def vae_config(cfg: EditorTrainConfig, scaling_factor: float = 1.0) -> dict:
    """diffusers AutoencoderKL config: 3 levels (4x), 4 latent channels, no mid attention."""
    return {"_class_name": "AutoencoderKL", "_diffusers_version": "0.27.0",
            "in_channels": 3, "out_channels": 3, "latent_channels": 4,
            "down_block_types": ["DownEncoderBlock2D"] * 3,
            "up_block_types": ["UpDecoderBlock2D"] * 3,
            "block_out_channels": [16, 32, 64], "layers_per_block": 1, "act_fn": "silu",
            "norm_num_groups": 8, "sample_size": cfg.size, "scaling_factor": scaling_factor,
            "mid_block_add_attention": False}


def unet_config(cfg: EditorTrainConfig) -> dict:
    """diffusers UNet2DConditionModel config: 8 input channels (latent + image latent)."""
    return {"_class_name": "UNet2DConditionModel", "_diffusers_version": "0.27.0",
            "in_channels": 8, "out_channels": 4, "sample_size": cfg.size // 4,
            "block_out_channels": list(cfg.width),
            "down_block_types": ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"],
            "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"],
            "layers_per_block": 1, "cross_attention_dim": cfg.text_width,
            "attention_head_dim": 4, "norm_num_groups": 16 if min(cfg.width) >= 16 else 8,
            "act_fn": "silu", "flip_sin_to_cos": True, "freq_shift": 0,
            "center_input_sample": False, "downsample_padding": 1, "mid_block_scale_factor": 1,
            "norm_eps": 1e-5, "use_linear_projection": False}


def text_config(cfg: EditorTrainConfig, vocab_size: int, bos_id: int, eos_id: int) -> dict:
    """transformers CLIPTextConfig."""
    return {"architectures": ["CLIPTextModel"], "model_type": "clip_text_model",
            "hidden_size": cfg.text_width, "intermediate_size": 2 * cfg.text_width,
            "num_hidden_layers": cfg.text_layers, "num_attention_heads": 2,
            "max_position_embeddings": MAX_LENGTH, "vocab_size": vocab_size,
            "hidden_act": "quick_gelu", "layer_norm_eps": 1e-5, "projection_dim": cfg.text_width,
            "bos_token_id": bos_id, "eos_token_id": eos_id, "pad_token_id": eos_id,
            "attention_dropout": 0.0, "dropout": 0.0, "initializer_factor": 1.0,
            "initializer_range": 0.02, "torch_dtype": "float32"}


# ----------------------------------------------------------------------------- tokenizer

def byte_symbols() -> list[str]:
    """The 256 printable symbols byte-level BPE writes bytes as, in CLIP's (GPT-2's) order."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + \
        list(range(ord("®"), ord("ÿ") + 1))
    cs, n = bs[:], 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    order = sorted(range(256), key=lambda i: bs[i])
    return [chr(cs[i]) for i in order]


def train_tokenizer(texts: list[str], vocab_size: int = 1024) -> tuple[dict[str, int], list[tuple[str, str]]]:
    """A CLIP-layout BPE vocabulary learnt on ``texts`` with ``tokenizers``: (vocab, merges).

    The vocabulary holds every byte symbol, alone and as a word end (``</w>``), then one
    token per merge in order, then the two special tokens, as CLIP's does; so both the
    ``tokenizers`` reader (:class:`jaxedit.models.CLIPTokenizer`) and transformers'
    CLIPTokenizer read the folder the same way.
    """
    from tokenizers import Regex, Tokenizer, normalizers, pre_tokenizers, trainers
    from tokenizers.models import BPE

    from jaxedit.models.clip_text import _CLIP_SPLIT

    tok = Tokenizer(BPE(end_of_word_suffix="</w>"))
    tok.normalizer = normalizers.Sequence(
        [normalizers.NFC(), normalizers.Replace(Regex(r"\s+"), " "), normalizers.Lowercase()])
    tok.pre_tokenizer = pre_tokenizers.Sequence([
        pre_tokenizers.Split(Regex(_CLIP_SPLIT), behavior="removed", invert=True),
        pre_tokenizers.ByteLevel(add_prefix_space=False)])
    trainer = trainers.BpeTrainer(vocab_size=vocab_size, show_progress=False,
                                  initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
                                  end_of_word_suffix="</w>", min_frequency=1)
    tok.train_from_iterator(texts, trainer)
    import json

    merges = [tuple(m.split(" ")) if isinstance(m, str) else tuple(m)
              for m in json.loads(tok.to_str())["model"]["merges"]]
    symbols = byte_symbols()
    vocab: dict[str, int] = {}
    for token in symbols + [s + "</w>" for s in symbols] + ["".join(m) for m in merges] + [BOS, EOS]:
        vocab.setdefault(token, len(vocab))
    return vocab, merges


# ----------------------------------------------------------------------------- image helpers

def blur(images: Array, sigma: Array) -> Array:
    """Per-image separable Gaussian blur: images [B, H, W, 3], sigma [B] (px, >= 0)."""
    r = 3
    x = jnp.arange(-r, r + 1, dtype=jnp.float32)
    k = jnp.exp(-0.5 * (x[None] / jnp.maximum(sigma[:, None], 1e-3)) ** 2)
    k = k / k.sum(1, keepdims=True)  # [B, 7]
    pad = jnp.pad(images, ((0, 0), (r, r), (r, r), (0, 0)), mode="edge")
    h, w = images.shape[1:3]
    rows = sum(k[:, i, None, None, None] * pad[:, i:i + h, :, :] for i in range(2 * r + 1))
    return sum(k[:, i, None, None, None] * rows[:, :, i:i + w, :] for i in range(2 * r + 1))


def degrade(images: Array, key: Array, share: float) -> Array:
    """A reconstruction's look on a share of ``images`` [B, H, W, 3] in [0, 1]: blur of
    sigma in [0.3, 1.2] px and Gaussian noise of std in [0, 0.03]."""
    b = images.shape[0]
    k_on, k_s, k_n, k_e = jax.random.split(key, 4)
    on = jax.random.uniform(k_on, (b,)) < share
    sigma = jax.random.uniform(k_s, (b,), minval=0.3, maxval=1.2)
    std = jax.random.uniform(k_n, (b,), maxval=0.03)
    bad = jnp.clip(blur(images, sigma) + std[:, None, None, None]
                   * jax.random.normal(k_e, images.shape), 0, 1)
    return jnp.where(on[:, None, None, None], bad, images)


def as_float(images_u8: Array) -> Array:
    return images_u8.astype(jnp.float32) / 255.0


# ----------------------------------------------------------------------------- the VAE stage

class VAEState(NamedTuple):
    """vae: the module's arrays; opt: Adam's state; step: int32 []; key: the run's key."""

    vae: Any
    opt: Any
    step: Array
    key: Array


def vae_optimizer(cfg: EditorTrainConfig, decoder_only: bool = False):
    total = cfg.decoder_steps if decoder_only else cfg.vae_steps
    return optax.adam(optax.cosine_decay_schedule(cfg.vae_lr, total, alpha=0.05))


def init_vae(cfg: EditorTrainConfig, key: Array) -> VAEState:
    k_init, k_run = jax.random.split(key)
    vae = AutoencoderKL.from_config(vae_config(cfg), key=k_init)
    params = eqx.filter(vae, eqx.is_array)
    return VAEState(params, vae_optimizer(cfg).init(params), jnp.zeros((), jnp.int32), k_run)


def init_decoder(cfg: EditorTrainConfig, params, key: Array) -> VAEState:
    """The decoder stage's state: a trained autoencoder's arrays ``params``, Adam afresh."""
    return VAEState(params, vae_optimizer(cfg, decoder_only=True).init(params),
                    jnp.zeros((), jnp.int32), key)


#: Weight of the KL term of the VAE loss (the latents stay near a unit Gaussian, as SD's).
KL_WEIGHT = 1e-6


def make_vae_step(cfg: EditorTrainConfig, static, images_u8: Array, decoder_only: bool = False):
    """A compiled step over ``images_u8`` uint8 [N, H, W, 3]: one batch of random crops.

    ``decoder_only``: the encoder's posterior is a constant of the loss, so the encoder's
    gradients are zero and Adam leaves its weights exactly as they are (the latent space
    the UNet was trained in stays the same); only the decoder learns."""
    opt = vae_optimizer(cfg, decoder_only)
    c = cfg.vae_crop
    frozen = jax.lax.stop_gradient if decoder_only else (lambda x: x)

    def loss_fn(params, x, key):
        vae = eqx.combine(params, static)
        mean, logvar = frozen(vae.encode(x * 2 - 1))
        z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape)
        recon = (vae.decode(z) + 1) / 2
        kl = 0.5 * jnp.mean(jnp.sum(mean ** 2 + jnp.exp(logvar) - 1 - logvar, axis=-1))
        return jnp.mean(jnp.abs(recon - x)) + KL_WEIGHT * kl

    @jax.jit
    def step(state: VAEState):
        k = jax.random.fold_in(state.key, state.step)
        k_i, k_y, k_x, k_f, k_z = jax.random.split(k, 5)
        idx = jax.random.randint(k_i, (cfg.vae_batch,), 0, images_u8.shape[0])
        y0 = jax.random.randint(k_y, (cfg.vae_batch,), 0, images_u8.shape[1] - c + 1)
        x0 = jax.random.randint(k_x, (cfg.vae_batch,), 0, images_u8.shape[2] - c + 1)
        crop = jax.vmap(lambda i, y, x: jax.lax.dynamic_slice(images_u8[i], (y, x, 0), (c, c, 3)))
        x = as_float(crop(idx, y0, x0))
        flip = jax.random.bernoulli(k_f, 0.5, (cfg.vae_batch,))
        x = jnp.where(flip[:, None, None, None], x[:, :, ::-1], x)
        loss, grads = jax.value_and_grad(loss_fn)(state.vae, x, k_z)
        updates, opt_state = opt.update(grads, state.opt, state.vae)
        return VAEState(optax.apply_updates(state.vae, updates), opt_state, state.step + 1,
                        state.key), loss

    return step


def encode_all(vae, images_u8: np.ndarray, chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) float32 [N, h, w, 4] each: the posterior of every image, in chunks."""
    enc = jax.jit(lambda x: vae.encode(as_float(x) * 2 - 1))
    means, stds = [], []
    for lo in range(0, len(images_u8), chunk):
        m, lv = enc(jnp.asarray(images_u8[lo:lo + chunk]))
        means.append(np.asarray(m))
        stds.append(np.asarray(jnp.exp(0.5 * jnp.clip(lv, -30, 20))))
    return np.concatenate(means), np.concatenate(stds)


# ----------------------------------------------------------------------------- the UNet stage

class Networks(NamedTuple):
    """The trained pair: the UNet and the text encoder (arrays only)."""

    unet: Any
    text: Any


class UNetState(NamedTuple):
    """params / ema: :class:`Networks` of arrays; opt: AdamW's state; step: int32 []; key."""

    params: Networks
    ema: Networks
    opt: Any
    step: Array
    key: Array


def unet_optimizer(cfg: EditorTrainConfig):
    warmup = min(200, max(cfg.steps // 10, 1))
    schedule = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, warmup, max(cfg.steps, warmup + 1),
                                                  end_value=cfg.lr * 0.05)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=1e-4))


def build_networks(cfg: EditorTrainConfig, vocab_size: int, bos_id: int, eos_id: int, key):
    """Freshly initialised (UNet, text encoder) modules."""
    k_u, k_t = jax.random.split(key)
    return (UNet2DCondition.from_config(unet_config(cfg), key=k_u),
            CLIPTextEncoder.from_config(text_config(cfg, vocab_size, bos_id, eos_id), key=k_t))


def init_unet(cfg: EditorTrainConfig, unet, text, key: Array) -> UNetState:
    params = Networks(eqx.filter(unet, eqx.is_array), eqx.filter(text, eqx.is_array))
    return UNetState(params, params, unet_optimizer(cfg).init(params), jnp.zeros((), jnp.int32),
                     key)


class UNetData(NamedTuple):
    """The UNet stage's device arrays.

    target_mean, target_std: float32 [M, h, w, 4], the targets' posteriors; input_mean:
    float32 [V, 2, h, w, 4], each view's posterior mode, clean (0) and degraded (1);
    input_std: [V, h, w, 4] the clean inputs' posterior std (identity targets);
    rows: int32 [I, R] the training target rows of each instruction (padded), counts: int32
    [I] how many are real; active: int32
    [A] the instructions with training rows (an instruction of no scene of the run has none);
    views: int32 [Vt] the training views (identity examples); tokens: int32 [I + 1, L],
    the instructions' token ids then the empty prompt's; target_view: int32 [M];
    siblings: int32 [M, K] each row's outcomes (the rows of its view and instruction in
    outcome order, then the row itself repeated); outcomes: int32 [M] how many it has.
    """

    target_mean: Array
    target_std: Array
    input_mean: Array
    input_std: Array
    rows: Array
    counts: Array
    active: Array
    views: Array
    tokens: Array
    target_view: Array
    siblings: Array
    outcomes: Array


def outcome_siblings(view: np.ndarray, instruction: np.ndarray, outcome: np.ndarray,
                     most: int) -> tuple[np.ndarray, np.ndarray]:
    """(siblings int32 [M, most], outcomes int32 [M]) of target rows given by their view,
    instruction and outcome index (int [M] each): :class:`UNetData`'s fields."""
    siblings = np.repeat(np.arange(len(view), dtype=np.int32)[:, None], most, 1)
    outcomes = np.ones(len(view), np.int32)
    order = np.lexsort((outcome, instruction, view))
    key = np.stack([view[order], instruction[order]], 1)
    starts = np.flatnonzero(np.r_[True, (key[1:] != key[:-1]).any(1)])
    for group in np.split(order, starts[1:]):
        siblings[group, : len(group)] = group
        outcomes[group] = len(group)
    return siblings, outcomes


def outcome_direction(h: int, w: int, c: int) -> np.ndarray:
    """float [h, w, c]: the unit direction :func:`outcome_of_noise` projects on, the latent
    checkerboard (+-1 by pixel parity, every channel, normalised). The checkerboard because
    a rendered view's latent has little energy at that frequency, so the projection stays
    legible in a noised latent down to low noise levels."""
    sign = np.where((np.arange(h)[:, None] + np.arange(w)[None, :]) % 2, -1.0, 1.0)
    return np.repeat(sign[..., None], c, -1) / np.sqrt(h * w * c)


def outcome_of_noise(noise: Array, outcomes: Array) -> Array:
    """int32 [B]: which of ``outcomes`` (int [B]) equally likely outcomes standard normal
    ``noise`` [B, h, w, c] stands for: the quantile bin of its projection on
    :func:`outcome_direction`."""
    projection = jnp.einsum("bhwc,hwc->b", noise, outcome_direction(*noise.shape[1:]))
    bin_ = jnp.floor(jax.scipy.stats.norm.cdf(projection) * outcomes).astype(jnp.int32)
    return jnp.clip(bin_, 0, outcomes - 1)


def unet_data(data: EditDataset, vae, tokens: np.ndarray, key: Array, degrade_share: float = 1.0,
              chunk: int = 64) -> UNetData:
    """Encode every image once (the VAE is frozen from here on)."""
    t_mean, t_std = encode_all(vae, data.targets, chunk)
    clean_mean, clean_std = encode_all(vae, data.inputs, chunk)
    degraded = np.asarray(jax.jit(degrade, static_argnums=2)(
        as_float(jnp.asarray(data.inputs)), key, degrade_share))
    bad_mean, _ = encode_all(vae, np.round(degraded * 255).astype(np.uint8), chunk)
    train_rows = data.split(held_out=False)
    per = [train_rows[data.target_instruction[train_rows] == i]
           for i in range(len(data.instructions))]
    width = max(len(r) for r in per)
    rows = np.stack([np.pad(r, (0, width - len(r))) for r in per])  # padding never drawn
    siblings, outcomes = outcome_siblings(data.target_view, data.target_instruction,
                                          data.target_outcome,
                                          max(len(i.outcomes) for i in data.instructions))
    return UNetData(jnp.asarray(t_mean), jnp.asarray(t_std),
                    jnp.asarray(np.stack([clean_mean, bad_mean], 1)), jnp.asarray(clean_std),
                    jnp.asarray(rows, jnp.int32), jnp.asarray([len(r) for r in per], jnp.int32),
                    jnp.asarray([i for i, r in enumerate(per) if len(r)], jnp.int32),
                    jnp.asarray(np.flatnonzero(~data.held_out), jnp.int32),
                    jnp.asarray(tokens, jnp.int32), jnp.asarray(data.target_view, jnp.int32),
                    jnp.asarray(siblings), jnp.asarray(outcomes))


def draw_batch(d: UNetData, key: Array, cfg: EditorTrainConfig, scaling: float,
               noise: Array | None = None):
    """One batch: (clean latents z0 [B, h, w, 4] scaled, image latents [B, h, w, 4],
    token ids [B, L]), conditioning dropout applied. ``noise`` [B, h, w, 4]: the diffusion
    noise the examples will be noised with (needed with ``cfg.outcome_from_noise``)."""
    b, n_ins = cfg.batch, d.rows.shape[0]
    ks = jax.random.split(key, 8)
    identity = jax.random.uniform(ks[0], (b,)) < cfg.identity_share
    if cfg.balance_outcomes:  # weight each active instruction by its outcomes
        weights = d.outcomes[d.rows[d.active, 0]].astype(jnp.float32)
        ins = d.active[jax.random.categorical(ks[1], jnp.log(weights), shape=(b,))]
    else:
        ins = d.active[jax.random.randint(ks[1], (b,), 0, d.active.shape[0])]
    row = d.rows[ins, jax.random.randint(ks[2], (b,), 0, 1 << 30) % d.counts[ins]]
    if cfg.outcome_from_noise:  # the drawn row's sibling of the noise's outcome
        row = d.siblings[row, outcome_of_noise(noise, d.outcomes[row])]
    view_id = d.views[jax.random.randint(ks[3], (b,), 0, d.views.shape[0])]
    view = jnp.where(identity, view_id, d.target_view[row])
    eps_vae = jax.random.normal(ks[4], d.target_mean.shape[1:])
    target = jnp.where(identity[:, None, None, None],
                       d.input_mean[view, 0] + d.input_std[view] * eps_vae,
                       d.target_mean[row] + d.target_std[row] * eps_vae)
    bad = jax.random.uniform(ks[5], (b,)) < cfg.degrade
    cond = jnp.where(bad[:, None, None, None], d.input_mean[view, 1], d.input_mean[view, 0])
    tokens = d.tokens[jnp.where(identity, n_ins, ins)]
    # IP2P's dropout: text alone, image alone, both, each with probability ``drop``.
    u = jax.random.uniform(ks[6], (b,))
    no_text = u < 2 * cfg.drop
    no_image = (u >= cfg.drop) & (u < 3 * cfg.drop)
    tokens = jnp.where(no_text[:, None], d.tokens[n_ins][None], tokens)
    cond = jnp.where(no_image[:, None, None, None], 0.0, cond)
    if cfg.empty_is_identity:  # no instruction but the image: keep the view
        keep = no_text & ~no_image
        target = jnp.where(keep[:, None, None, None],
                           d.input_mean[view, 0] + d.input_std[view] * eps_vae, target)
    return target * scaling, cond, tokens


def make_unet_step(cfg: EditorTrainConfig, statics, d: UNetData, scaling: float,
                   schedule: DDPMSchedule):
    """A compiled training step of the UNet and the text encoder (IP2P's loss)."""
    opt = unet_optimizer(cfg)
    unet_static, text_static = statics
    alphas = jnp.asarray(schedule.alphas_cumprod, jnp.float32)

    def loss_fn(params: Networks, z0, cond, tokens, t, noise):
        unet = eqx.combine(params.unet, unet_static)
        text = eqx.combine(params.text, text_static)
        a = alphas[t][:, None, None, None]
        zt = jnp.sqrt(a) * z0 + jnp.sqrt(1 - a) * noise
        eps = unet(jnp.concatenate([zt, cond], -1), t, text(tokens))
        return jnp.mean((eps - noise) ** 2)

    @jax.jit
    def step(state: UNetState):
        k_batch, k_loss = jax.random.split(jax.random.fold_in(state.key, state.step))
        k_t, k_n = jax.random.split(k_loss)
        t = jax.random.randint(k_t, (cfg.batch,), 0, alphas.shape[0])
        noise = jax.random.normal(k_n, (cfg.batch, *d.target_mean.shape[1:]))
        z0, cond, tokens = draw_batch(d, k_batch, cfg, scaling, noise)
        loss, grads = jax.value_and_grad(loss_fn)(state.params, z0, cond, tokens, t, noise)
        updates, opt_state = opt.update(grads, state.opt, state.params)
        params = optax.apply_updates(state.params, updates)
        # The EMA warms up (decay min(ema, (1 + n) / (10 + n))) so early weights fade fast.
        n = state.step.astype(jnp.float32)
        decay = jnp.minimum(cfg.ema, (1 + n) / (10 + n))
        ema = jax.tree_util.tree_map(lambda e, p: decay * e + (1 - decay) * p, state.ema, params)
        return UNetState(params, ema, opt_state, state.step + 1, state.key), loss

    return step


def latent_scaling(mean: np.ndarray, std: np.ndarray, key: Array) -> float:
    """Stable Diffusion's scaling factor: 1 / std of posterior samples of the latents."""
    z = mean + std * np.asarray(jax.random.normal(key, mean.shape))
    return float(1.0 / np.std(z))


def run_steps(step: Callable, state, total: int, *, every: int, losses=(), on_progress=None,
              checkpoint=None):
    """Advance ``state`` with ``step`` until its ``step`` counter reaches ``total``.

    ``losses``: the losses of the steps already done (a resumed stage's); ``on_progress(done,
    loss)`` after each step (loss a float, fetched every 10 steps); ``checkpoint(state,
    losses)`` every ``every`` steps and at the end. Returns (state, every step's loss).
    """
    losses = list(losses)
    pending = []
    while int(state.step) < total:
        state, loss = step(state)
        pending.append(loss)
        done = int(state.step)
        if len(pending) >= 10 or done == total:
            losses += [float(v) for v in jax.device_get(pending)]
            pending = []
            if not all(math.isfinite(v) for v in losses[-10:]):
                raise DataError("training", f"the loss is not finite at step {done}")
        if on_progress is not None:
            on_progress(done, losses[-1] if losses else float("nan"))
        if checkpoint is not None and (done % every == 0 or done == total):
            checkpoint(state, losses)
    return state, losses
