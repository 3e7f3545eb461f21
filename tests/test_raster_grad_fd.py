"""Gradients of the tile splatter against central finite differences, in float64.

Both compositing backends: the XLA path and the Pallas kernel (in the interpreter),
whose backward recovers each pair's transmittance by division, back to front.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxedit import camera as cam_lib
from jaxedit.gaussians import Gaussians
from jaxedit.raster import render_reference
from jaxedit.raster.render import render_tiles

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")
S = 16  # image 16 x 13: two 8x8 tiles per row, partial tiles at the bottom
N = 5


def _scene(seed):
    rng = np.random.default_rng(seed)
    # Opacities <= 0.8 and few Gaussians: T never reaches 1e-4 and alpha never 0.99,
    # so the loss is smooth away from the 1/255 footprint edges.
    return Gaussians(
        means=jnp.asarray(rng.normal(0.0, 0.3, (N, 3)), jnp.float64),
        log_scales=jnp.asarray(np.log(rng.uniform(0.08, 0.3, (N, 3))), jnp.float64),
        quats=jnp.asarray(rng.normal(size=(N, 4)), jnp.float64),
        opacity_logits=jnp.asarray(rng.uniform(-1.0, 1.3, N), jnp.float64),
        sh=jnp.asarray(rng.normal(0.0, 0.4, (N, 4, 3)), jnp.float64),
        alive=jnp.ones(N, bool),
    )


def _camera():
    return cam_lib.make_camera(cam_lib.look_at((0.4, -2.5, 0.6), (0, 0, 0)), width=S,
                               height=S - 3, focal=float(S))


def _loss(renderer):
    def loss(g, cam, w_rgb, w_a):
        out = renderer(g, cam, background=jnp.asarray([0.3, 0.1, 0.2], g.means.dtype))
        return (jnp.sum(out.rgb * w_rgb) + jnp.sum(out.alpha * w_a)
                + 0.1 * jnp.sum(out.depth * out.alpha * w_a))
    return loss


BACKENDS = ("xla", "pallas")


def _tiles_fn(backend):
    def tiles(g, cam, **kw):
        return render_tiles(g, cam, capacity=256, backend=backend, **kw)

    return tiles


# Jitted, so that float64 compiles one program a backend instead of the splatter op by op
# (the overflow check alone, run eagerly, compiled some 400 primitives: 18 s of the file).
RENDER_TILES = {b: jax.jit(_tiles_fn(b)) for b in BACKENDS}
LOSS_TILES = {b: jax.jit(_loss(_tiles_fn(b))) for b in BACKENDS}
GRAD_TILES = {b: jax.jit(jax.grad(_loss(_tiles_fn(b)), allow_int=True)) for b in BACKENDS}
grad_ref = jax.jit(jax.grad(_loss(render_reference), allow_int=True))


def _weights(seed):
    rng = np.random.default_rng(100 + seed)
    return (jnp.asarray(rng.normal(size=(S - 3, S, 3))), jnp.asarray(rng.normal(size=(S - 3, S))))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_gradients_match_central_differences_float64(seed, backend):
    loss_tiles, grad_tiles = LOSS_TILES[backend], GRAD_TILES[backend]
    with jax.enable_x64(True):
        g, cam, (w_rgb, w_a) = _scene(seed), _camera(), _weights(seed)
        assert not bool(RENDER_TILES[backend](g, cam).overflow)
        grads = grad_tiles(g, cam, w_rgb, w_a)
        rng = np.random.default_rng(200 + seed)
        eps = 1e-6
        for name in PARAMS:
            x = getattr(g, name)
            direction = jnp.asarray(rng.normal(size=x.shape))
            plus = loss_tiles(dataclasses.replace(g, **{name: x + eps * direction}), cam, w_rgb, w_a)
            minus = loss_tiles(dataclasses.replace(g, **{name: x - eps * direction}), cam, w_rgb, w_a)
            fd = float(plus - minus) / (2 * eps)
            analytic = float(jnp.sum(getattr(grads, name) * direction))
            assert analytic == pytest.approx(fd, rel=1e-5, abs=1e-7), name
        # In float64 the splatter's gradients equal the oracle's to rounding.
        ref = grad_ref(g, cam, w_rgb, w_a)
        for name in PARAMS:
            np.testing.assert_allclose(np.asarray(getattr(grads, name)),
                                       np.asarray(getattr(ref, name)), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_extreme_gaussians_match_oracle_gradients_float64(backend):
    grad_tiles = GRAD_TILES[backend]
    with jax.enable_x64(True):
        g = _scene(3)
        log_scales = np.asarray(g.log_scales).copy()
        log_scales[0] = 40.0  # huge (clipped to exp(20))
        log_scales[1] = -40.0  # tiny: the 0.3 px blur only
        log_scales[2] = [5.0, -25.0, 0.0]  # needle
        quats = np.asarray(g.quats).copy()
        quats[0] = 0.0  # zero quaternion
        quats[2] *= 1e-4
        quats[3] *= 1e4
        g = dataclasses.replace(g, log_scales=jnp.asarray(log_scales), quats=jnp.asarray(quats))
        cam, (w_rgb, w_a) = _camera(), _weights(3)
        ga, gb = grad_tiles(g, cam, w_rgb, w_a), grad_ref(g, cam, w_rgb, w_a)
        for name in PARAMS:
            a, b = np.asarray(getattr(ga, name)), np.asarray(getattr(gb, name))
            assert np.all(np.isfinite(a)), name
            np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9 * (1 + np.max(np.abs(b))))
