"""JAX SSIM / photometric loss against scikit-image, and the reporting metrics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import skimage.data
from hypothesis import example, given, settings
from hypothesis import strategies as st
from skimage.metrics import structural_similarity

from jaxedit import losses, metrics
from jaxedit.errors import DataError

SHAPE = (24, 21, 3)  # fixed, so one compilation serves every example
ssim_jit = jax.jit(losses.ssim)
loss_jit = jax.jit(losses.photometric_loss)
ASTRO = skimage.data.astronaut().astype(np.float32) / 255.0


def skimage_ssim(a, b):
    """The reference, called exactly as the brief specifies."""
    return structural_similarity(np.asarray(a, np.float64), np.asarray(b, np.float64),
                                 gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=-1)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), noise=st.floats(0.0, 0.6), gain=st.floats(0.2, 1.0),
       offset=st.floats(0.0, 0.8))
def test_ssim_matches_skimage_random(seed, noise, gain, offset):
    rng = np.random.default_rng(seed)
    a = (offset + gain * rng.uniform(size=SHAPE) * (1 - offset)).astype(np.float32)
    b = np.clip(a + noise * rng.normal(size=SHAPE), 0.0, 1.0).astype(np.float32)
    assert abs(float(ssim_jit(a, b)) - skimage_ssim(a, b)) < 1e-4


@settings(max_examples=20, deadline=None)
@given(row=st.integers(0, 480), col=st.integers(0, 480), dy=st.integers(-3, 3),
       dx=st.integers(-3, 3), contrast=st.floats(0.3, 1.5), bright=st.floats(-0.3, 0.3))
@example(row=416, col=346, dy=1, dx=0, contrast=0.537109375, bright=0.0625)
def test_ssim_matches_skimage_structured(row, col, dy, dx, contrast, bright):
    # Crops of a natural picture against shifted, contrast- and brightness-changed crops. The
    # example: a black corner against a grey one, where float32's E[x^2] - E[x]^2 loses most
    # (1.03e-4 from scikit-image's float64).
    a = ASTRO[row + 3:row + 3 + SHAPE[0], col + 3:col + 3 + SHAPE[1]]
    b = ASTRO[row + 3 + dy:row + 3 + dy + SHAPE[0], col + 3 + dx:col + 3 + dx + SHAPE[1]]
    b = np.clip((b - 0.5) * contrast + 0.5 + bright, 0.0, 1.0).astype(np.float32)
    assert abs(float(ssim_jit(a, b)) - skimage_ssim(a, b)) < 2e-4


def test_ssim_edge_cases():
    flat0 = np.zeros(SHAPE, np.float32)
    flat1 = np.full(SHAPE, 0.7, np.float32)
    half = np.zeros(SHAPE, np.float32)
    half[:, :10] = 1.0
    for a, b in [(flat0, flat1), (flat1, flat1), (half, flat1), (half, 1 - half)]:
        assert abs(float(ssim_jit(a, b)) - skimage_ssim(a, b)) < 1e-4
    assert float(ssim_jit(half, half)) == pytest.approx(1.0, abs=1e-5)


def test_ssim_other_window_and_range():
    rng = np.random.default_rng(3)
    a = rng.uniform(size=(20, 20, 2)).astype(np.float32) * 255
    b = np.clip(a + rng.normal(scale=30, size=a.shape), 0, 255).astype(np.float32)
    # scikit-image derives the window from sigma (truncate 3.5): sigma 1.0 -> radius 4,
    # i.e. a 9-tap window.
    ours = float(losses.ssim(a, b, window=9, sigma=1.0, data_range=255.0))
    ref = structural_similarity(a.astype(np.float64), b.astype(np.float64), gaussian_weights=True,
                                sigma=1.0, use_sample_covariance=False, data_range=255.0,
                                channel_axis=-1)
    assert abs(ours - ref) < 1e-4
    other = float(losses.ssim(a, b, window=7, sigma=1.0, data_range=255.0))
    assert abs(other - ours) > 1e-5  # the window really matters
    with pytest.raises(ValueError):
        losses.ssim(a, b, window=8)
    with pytest.raises(ValueError):
        losses.ssim(a[:5, :5], b[:5, :5])


def test_photometric_loss_value_and_batching():
    rng = np.random.default_rng(1)
    r = rng.uniform(size=(3,) + SHAPE).astype(np.float32)
    t = np.clip(r + rng.normal(scale=0.1, size=r.shape), 0, 1).astype(np.float32)
    want = np.mean([0.8 * np.abs(r[i] - t[i]).mean() + 0.2 * (1 - skimage_ssim(r[i], t[i]))
                    for i in range(3)])
    assert float(loss_jit(r, t)) == pytest.approx(want, abs=1e-5)
    per = jax.vmap(losses.ssim)(r, t)
    assert per.shape == (3,)
    np.testing.assert_allclose(per, losses.ssim(r, t), atol=1e-6)
    np.testing.assert_allclose(per, [skimage_ssim(r[i], t[i]) for i in range(3)], atol=1e-4)
    assert float(losses.dssim(r[0], t[0])) == pytest.approx(1 - float(per[0]), abs=1e-6)
    assert float(losses.photometric_loss(r, t, lambda_dssim=0.0)) == pytest.approx(
        float(losses.l1(r, t)), abs=1e-6)


def test_photometric_loss_within_a_weight():
    rng = np.random.default_rng(3)
    r = rng.uniform(size=SHAPE).astype(np.float32)
    t = np.clip(r + rng.normal(scale=0.1, size=SHAPE), 0, 1).astype(np.float32)
    ones = np.ones(SHAPE[:2], np.float32)
    assert float(losses.photometric_loss(r, t, weight=ones)) == pytest.approx(
        float(losses.photometric_loss(r, t)), abs=1e-6)
    # Half the view: its L1 is that half's, whatever the other half holds.
    half = ones.copy()
    half[:, SHAPE[1] // 2:] = 0.0
    t2 = t.copy()
    t2[:, SHAPE[1] // 2:] = 1.0 - t2[:, SHAPE[1] // 2:]
    got = float(losses.photometric_loss(r, t2, lambda_dssim=0.0, weight=half))
    assert got == pytest.approx(float(np.abs(r - t)[:, : SHAPE[1] // 2].mean()), abs=1e-6)
    assert float(losses.photometric_loss(r, t, weight=0 * ones)) == 0.0


def test_loss_gradient_is_finite_and_correct():
    rng = np.random.default_rng(2)
    t = jnp.asarray(rng.uniform(size=SHAPE).astype(np.float32))
    r = jnp.asarray(np.clip(np.asarray(t) + rng.normal(scale=0.2, size=SHAPE), 0, 1).astype(np.float32))
    flat = jnp.full(SHAPE, 0.5)  # zero variance: the worst case for the ratio
    grad_fn = jax.jit(jax.grad(lambda x, y: losses.ssim(x, y)))
    g = grad_fn(r, t)
    assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.abs(g).max()) > 0
    assert bool(jnp.all(jnp.isfinite(grad_fn(flat, flat))))
    assert bool(jnp.all(jnp.isfinite(jax.grad(loss_jit)(r, t))))
    # Directional finite difference (central, float32: loose but meaningful tolerance).
    d = jnp.asarray(rng.normal(size=SHAPE).astype(np.float32))
    eps = 1e-2
    fd = (float(ssim_jit(r + eps * d, t)) - float(ssim_jit(r - eps * d, t))) / (2 * eps)
    assert float(jnp.sum(g * d)) == pytest.approx(fd, rel=2e-2, abs=2e-4)


def test_metrics_psnr_and_ssim():
    a = np.full((8, 9, 3), 0.25)
    b = a + 0.1
    assert metrics.psnr(a, b) == pytest.approx(20.0, abs=1e-9)
    assert metrics.psnr(a, a) == np.inf
    batch = metrics.psnr(np.stack([a, a]), np.stack([b, a]))
    assert batch.shape == (2,) and batch[0] == pytest.approx(20.0) and batch[1] == np.inf
    x = ASTRO[:32, :32]
    y = np.clip(x + 0.05, 0, 1)
    assert metrics.ssim_skimage(x, y) == pytest.approx(skimage_ssim(x, y), abs=1e-12)
    scores = metrics.image_metrics(np.stack([x, x]), np.stack([y, x]))
    assert scores["psnr"] == pytest.approx((metrics.psnr(x, y) + 100.0) / 2)
    assert scores["ssim"] == pytest.approx((skimage_ssim(x, y) + 1.0) / 2)
    with pytest.raises(DataError, match="shape"):
        metrics.psnr(a, a[:4])
    with pytest.raises(DataError, match="NaN"):
        metrics.ssim_skimage(a * np.nan, a)
