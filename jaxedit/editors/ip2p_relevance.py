"""Relevance of an instruction for the JAX InstructPix2Pix ("Watch Your Steps", ICCV 2023).

Per view: the difference between the UNet's noise prediction with the instruction's
embedding e and with the null embedding E(""), the image conditioning kept in both,
averaged over ``draws`` noise draws and timesteps, then normalised, smoothed and
thresholded (:func:`jaxedit.editors.base.relevance_mask`). One batched UNet call on
2 x B x draws samples. Kept apart from :mod:`jaxedit.editors.jax_ip2p` (it only reads its
pure pieces); :func:`jaxedit.editors.base.relevance` dispatches to it.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from . import jax_ip2p as jx
from .masks import relevance_mask
from .diffusion import timestep_bounds

#: Noise draws (each with its own timestep) averaged per view.
DRAWS = 4


def noise_difference(nets, images, originals, embedding, null, keys, t_bounds, schedule,
                     cfg, model_hw: tuple[int, int], draws: int = DRAWS) -> jax.Array:
    """Mean |eps(x_t, c, e) - eps(x_t, c, E(""))| per latent pixel, float32 [B, h, w].

    Args:
      nets: :class:`jaxedit.editors.jax_ip2p.Networks`.
      images, originals: float [B, H, W, 3] in [0, 1] (render, original photo).
      embedding: float [77, D], the instruction's; null: [77, D], E("").
      keys: B typed keys; each draws ``draws`` timesteps in ``t_bounds`` (int32 [2])
        and noises.
      schedule, cfg: the editor's :class:`DiffusionSchedule` and :class:`EditConfig`.
      model_hw: the networks' (h, w), multiples of the VAE's factor f.
    Returns:
      float32 [B, h/f, w/f], averaged over channels and draws.
    """
    b = images.shape[0]
    f = jx.latent_factor(nets.vae)
    lat_hw = (model_hw[0] // f, model_hw[1] // f)
    sub = jax.vmap(lambda k: jax.random.split(k, draws))(keys).reshape(-1)  # [B * draws]
    t, vae_noise, sde_noise = jx.draw_noise(sub, t_bounds, lat_hw)
    rep = lambda x: jnp.repeat(x, draws, 0)  # noqa: E731 - [B, ...] -> [B * draws, ...]
    latents, cond = jx.encode_latents(
        nets.vae, rep(jx.resize_images(images.astype(jnp.float32), model_hw)),
        rep(jx.resize_images(originals.astype(jnp.float32), model_hw)), vae_noise, cfg)
    a = schedule.alphas_cumprod[t][:, None, None, None]
    x = a ** 0.5 * latents + (1 - a) ** 0.5 * sde_noise
    n = b * draws
    context = jnp.concatenate([jnp.broadcast_to(embedding, (n, *null.shape)),
                               jnp.broadcast_to(null, (n, *null.shape))]).astype(cfg.dtype)
    sample = jnp.concatenate([jnp.concatenate([x, x]), jnp.concatenate([cond, cond])], -1)
    eps = nets.unet(sample.astype(cfg.dtype), jnp.concatenate([t, t]), context)
    eps = eps.astype(jnp.float32)
    diff = jnp.mean(jnp.abs(eps[:n] - eps[n:]), -1)  # [B * draws, h, w]
    return jnp.mean(diff.reshape(b, draws, *diff.shape[1:]), 1)


noise_difference_jit = eqx.filter_jit(noise_difference)


def relevance(editor, image, original, embedding, key: jax.Array, *,
              timestep_range: tuple[float, float] = (0.02, 0.98),
              guidance: tuple[float, float] = (7.5, 1.5), draws: int = DRAWS,
              sigma: float = 1.5, threshold: float = 0.3) -> jax.Array:
    """The Editor protocol's ``relevance`` for a :class:`JaxIP2PEditor`: float32 [H, W].

    ``image``, ``original``: [H, W, 3] in [0, 1]; ``embedding``: [77, D] (e.g. e(r));
    ``key``: one typed key (timesteps and noises). The latent map is resized to the view
    and put through :func:`jaxedit.editors.base.relevance_mask`.
    """
    image = jnp.asarray(image, jnp.float32)
    original = jnp.asarray(original, jnp.float32)
    if image.ndim != 3 or image.shape != original.shape:
        raise DataError("image", f"need [H, W, 3] image and original of one shape, got "
                        f"{tuple(image.shape)} and {tuple(original.shape)}")
    emb = editor._embedding(embedding)
    if emb.ndim != 2:
        raise DataError("embedding", f"need one [77, D] embedding, got {tuple(emb.shape)}")
    key = key if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else \
        jax.random.wrap_key_data(jnp.asarray(key, jnp.uint32))
    height, width = image.shape[:2]
    t_bounds = jnp.asarray(np.asarray(timestep_bounds(timestep_range,
                                                      editor.num_train_timesteps), np.int32))
    diff = noise_difference_jit(editor.nets, image[None], original[None], jnp.asarray(emb),
                                jnp.asarray(editor.encode("")), key.reshape(1), t_bounds,
                                editor.schedule, editor.config(guidance),
                                editor.model_hw(height, width), draws)
    diff = jax.image.resize(diff[..., None], (1, height, width, 1), "linear")[0, ..., 0]
    return relevance_mask(diff, sigma=sigma, threshold=threshold)
