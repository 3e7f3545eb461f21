"""Local edits (issue 35): relevance lifting, regions and masks, frozen Gaussians."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxedit import camera as cam_lib
from jaxedit.gaussians import Gaussians
from jaxedit.raster import accumulate_weights, accumulate_weights_reference, render

W, H, N = 40, 36, 48


def make_scene(seed, n=N):
    rng = np.random.default_rng(seed)
    return Gaussians(means=jnp.asarray(rng.normal(0.0, 0.6, (n, 3)), jnp.float32),
                     log_scales=jnp.asarray(np.log(rng.uniform(0.03, 0.25, (n, 3))), jnp.float32),
                     quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
                     opacity_logits=jnp.asarray(rng.normal(0.0, 1.5, n), jnp.float32),
                     sh=jnp.asarray(rng.normal(0.0, 1.0, (n, 1, 3)), jnp.float32),
                     alive=jnp.asarray(rng.uniform(size=n) > 0.1))


def make_cameras():
    eyes = ((0.3, -3.0, 0.8), (2.5, -1.5, 0.2))
    return cam_lib.stack([cam_lib.make_camera(cam_lib.look_at(e, (0.0, 0.0, 0.0)), width=W,
                                              height=H, focal=float(W)) for e in eyes])


def test_per_gaussian_weights_match_the_dense_oracle():
    g = make_scene(0)
    cams = make_cameras()
    mask = jax.random.uniform(jax.random.key(1), (2, H, W, 1))
    values = jnp.concatenate([mask, jnp.ones_like(mask)], -1)  # [B, H, W, 2]
    tiles = np.asarray(accumulate_weights(g, cams, values))
    dense = np.asarray(accumulate_weights_reference(g, cams, values))
    assert tiles.shape == (N, 2)
    assert dense[:, 1].max() > 1.0  # drawn Gaussians
    np.testing.assert_allclose(tiles, dense, rtol=1e-4, atol=1e-5)
    assert np.all(tiles[~np.asarray(g.alive)] == 0)
    # The weights of one view sum, over Gaussians, to the frame's alpha: sum_i w_i = 1 - T.
    one = accumulate_weights(g, cams[0], jnp.ones((H, W, 1)))
    alpha = render(g, cams[0]).alpha
    np.testing.assert_allclose(float(one.sum()), float(alpha.sum()), rtol=1e-4)
