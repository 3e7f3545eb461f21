"""The JAX InstructPix2Pix editor's own logic, on stand-in networks (tests/ip2p_standins.py).

Oracle: a per-view Python loop written from the torch editor's algorithm (its host list
schedule, its DDIM equations spelled out, its three-branch order), against which the
batched, fixed-length, jit-compiled core must agree, including T < steps where slots
repeat or reach 0. The whole-edit comparison with the torch editor on real (tiny)
diffusers networks is in tests/test_ip2p_equivalence.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ip2p_standins import sd_schedule, standin_editor

from jaxedit.editors import Editor
from jaxedit.editors import diffusion as dm
from jaxedit.editors import jax_ip2p as jx
from jaxedit.errors import DataError

PROMPT = "turn the bear into a panda"


@pytest.fixture(scope="module")
def editor():
    return standin_editor(size=32, steps=4)


def _image(seed, shape=(24, 20, 3)):
    return np.random.default_rng(seed).uniform(0, 1, shape).astype(np.float32)


@pytest.mark.parametrize("steps", [1, 2, 3, 7, 14, 20, 50])
def test_timestep_table_is_the_schedule(steps):
    """Every T in [1, 999] at once: the valid slots are the host list, in order."""
    t_start = np.arange(1, 1000)
    t, t_next, valid = (np.asarray(a) for a in dm.timestep_table(jnp.asarray(t_start), steps))
    for T, ts, nxt, ok in zip(t_start, t, t_next, valid):
        listed = dm.timestep_schedule(int(T), steps)
        assert ts[ok].tolist() == listed and nxt[ok].tolist() == listed[1:] + [0], T


def test_timestep_table_small_t_repeats_are_masked():
    # T = 3 over 4 slots: round(3, 2.25, 1.5, 0.75) = 3, 2, 2, 1 -> the repeated 2 is skipped.
    t, t_next, valid = (np.asarray(a)[0] for a in dm.timestep_table(jnp.asarray([3]), 4))
    assert t.tolist() == [3, 2, 2, 1] and valid.tolist() == [True, True, False, True]
    assert t_next[valid].tolist() == [2, 1, 0]


def _loop_reference(ed: jx.JaxIP2PEditor, images, originals, emb, t_start, vae_noise, sde_noise,
                    guidance):
    """The torch editor's algorithm view by view, with its host schedule and float64 alphas."""
    nets, sf = ed.nets, ed.scaling_factor
    a = np.asarray(sd_schedule().alphas_cumprod, np.float64)
    final = float(a[0])
    null = jnp.asarray(ed.encode(""))
    s_t, s_i = guidance
    outs = []
    for b in range(images.shape[0]):
        hw = (vae_noise.shape[1] * 8, vae_noise.shape[2] * 8)
        pair = jnp.concatenate([jx.resize_images(images[b:b + 1], hw),
                                jx.resize_images(originals[b:b + 1], hw)]) * 2 - 1
        mean, logvar = nets.vae.encode(pair)
        x = (mean[:1] + jnp.exp(0.5 * logvar[:1]) * vae_noise[b:b + 1]) * sf
        cond = mean[1:]
        T = int(t_start[b])
        x = a[T] ** 0.5 * x + (1 - a[T]) ** 0.5 * sde_noise[b:b + 1]
        ts = dm.timestep_schedule(T, ed.steps)
        for i, t in enumerate(ts):
            sample = jnp.concatenate([
                jnp.concatenate([x, cond], -1), jnp.concatenate([x, cond], -1),
                jnp.concatenate([x, jnp.zeros_like(cond)], -1)])
            context = jnp.stack([jnp.asarray(emb[b]), null, null])
            e_ti, e_i, e_u = nets.unet(sample, jnp.full((3,), t), context)
            eps = e_u + s_t * (e_ti - e_i) + s_i * (e_i - e_u)
            a_t, a_p = a[t], (a[ts[i + 1]] if i + 1 < len(ts) else final)
            x0 = (x - (1 - a_t) ** 0.5 * eps) / a_t ** 0.5
            x = a_p ** 0.5 * x0 + (1 - a_p) ** 0.5 * eps
        dec = jnp.clip((nets.vae.decode(x / sf) + 1) / 2, 0, 1)
        outs.append(jnp.clip(jx.resize_images(dec, images.shape[1:3]), 0, 1)[0])
    return np.stack([np.asarray(o) for o in outs])


@pytest.mark.parametrize("guidance", [(7.5, 1.5), (3.0, 0.5)])
def test_batched_core_matches_the_loop(editor, guidance):
    """Three views, three different T (one large, one with repeated slots, one with a
    single slot) in one compiled call agree with the per-view loop."""
    b = 3
    images = jnp.asarray(np.stack([_image(i) for i in range(b)]))
    originals = jnp.asarray(np.stack([_image(10 + i) for i in range(b)]))
    emb = np.stack([editor.encode(PROMPT), editor.encode("a"), editor.encode("")])
    t_start = jnp.asarray([640, 3, 1], jnp.int32)
    hw = editor.model_hw(24, 20)
    assert hw == (32, 24)
    k1, k2 = jax.random.split(jax.random.key(0))
    vae_noise = jax.random.normal(k1, (b, hw[0] // 8, hw[1] // 8, 4))
    sde_noise = jax.random.normal(k2, (b, hw[0] // 8, hw[1] // 8, 4))
    out = jx.edit_with_noise_jit(editor.nets, images, originals, jnp.asarray(emb),
                                 jnp.asarray(editor.encode("")), t_start, vae_noise, sde_noise,
                                 editor.schedule, editor.config(guidance))
    ref = _loop_reference(editor, images, originals, emb, t_start, vae_noise, sde_noise, guidance)
    assert out.shape == images.shape and out.dtype == jnp.float32
    # float32 reassociation only: batched and per-view convolutions sum in another order, by
    # as much as 2.03e-5 on an AMD EPYC (x86-64) CI machine through the whole DDIM loop.
    np.testing.assert_allclose(np.asarray(out), ref, rtol=0, atol=4e-5)
    # The views differ (the test is not passing on a constant output).
    assert np.abs(ref[0] - ref[1]).max() > 1e-2


def test_edit_draws_the_torch_editors_timestep(editor):
    """Same key -> same T as the torch editor's draw (key split into (k_t, k_n) alike)."""
    keys = jax.random.split(jax.random.key(5), 6)
    lo, hi = dm.timestep_bounds((0.3, 0.9))
    t, vae_noise, sde_noise = jx.draw_noise(keys, jnp.asarray([lo, hi]), (4, 3))
    expected = [dm.draw_timestep(jax.random.split(k)[0], (0.3, 0.9)) for k in keys]
    assert np.asarray(t).tolist() == expected
    assert vae_noise.shape == sde_noise.shape == (6, 4, 3, 4)
    assert not np.allclose(vae_noise, sde_noise)


def test_editor_protocol_and_batching(editor):
    assert isinstance(editor, Editor) and editor.name == "ip2p" and editor.dtype == "float32"
    e = editor.encode(PROMPT)
    assert isinstance(e, np.ndarray) and e.shape == (77, 16) and e.dtype == np.float32
    assert not np.allclose(e, editor.encode(""))
    imgs = np.stack([_image(20), _image(21)])
    keys = jax.random.split(jax.random.key(3), 2)
    both = editor.edit_many(imgs, imgs[::-1], e, keys, timestep_range=(0.4, 0.8))
    assert isinstance(both, jax.Array) and both.shape == imgs.shape
    assert float(both.min()) >= 0 and float(both.max()) <= 1
    # A view edited alone gives the bits it gets in a batch (per-view keys, independent math).
    alone = editor.edit(imgs[1], imgs[0], e, keys[1], timestep_range=(0.4, 0.8))
    np.testing.assert_allclose(np.asarray(alone), np.asarray(both[1]), rtol=0, atol=1e-6)
    again = editor.edit(imgs[1], imgs[0], e, jax.random.key_data(keys[1]),
                        timestep_range=(0.4, 0.8))  # raw uint32 keys are accepted
    np.testing.assert_array_equal(np.asarray(again), np.asarray(alone))
    other = editor.edit(imgs[1], imgs[0], e, jax.random.key(99), timestep_range=(0.4, 0.8))
    assert np.abs(np.asarray(other) - np.asarray(alone)).max() > 1e-4


def test_bad_inputs(editor):
    e = editor.encode(PROMPT)
    with pytest.raises(DataError, match="image"):
        editor.edit(np.zeros((8, 8, 4), np.float32), _image(0), e, jax.random.key(0))
    with pytest.raises(DataError, match="embedding"):
        editor.edit(_image(0), _image(0), e[:10], jax.random.key(0))
    with pytest.raises(DataError, match="timestep_range"):
        editor.edit(_image(0), _image(0), e, jax.random.key(0), timestep_range=(0.9, 0.1))
    with pytest.raises(DataError, match="original"):
        editor.edit(_image(0), _image(0, (16, 16, 3)), e, jax.random.key(0))
    with pytest.raises(DataError, match="size"):
        standin_editor(size=30)


def test_resize_matches_torch_interpolate():
    torch = pytest.importorskip("torch")
    x = _image(30, (50, 36, 3))
    for hw in [(32, 24), (64, 48), (50, 36)]:
        ours = np.asarray(jx.resize_images(jnp.asarray(x[None]), hw))[0]
        t = torch.nn.functional.interpolate(torch.from_numpy(x).permute(2, 0, 1)[None], size=hw,
                                            mode="bilinear", align_corners=False,
                                            antialias=True)
        np.testing.assert_allclose(ours, t[0].permute(1, 2, 0).numpy(), rtol=0, atol=1e-5)


def test_short_batches_run_at_a_padded_size_and_compile_nothing_new(editor):
    """A sweep's remainder runs at the next power of two (repeats of its last view, dropped):
    the same program as the full batch, and each view's edit as it is alone."""
    from jaxedit.compilation import compile_stats

    assert [jx.padded_batch(b, 1) for b in (1, 2, 3, 4, 5, 8, 9)] == [1, 2, 4, 4, 8, 8, 16]
    assert (jx.padded_batch(1, 2), jx.padded_batch(3, 2), jx.padded_batch(5, 3)) == (2, 4, 9)
    e = editor.encode(PROMPT)
    imgs = np.stack([_image(30 + i) for i in range(4)])
    keys = jax.random.split(jax.random.key(7), 4)
    four = editor.edit_many(imgs, imgs, e, keys, timestep_range=(0.4, 0.8))
    before = compile_stats()
    three = editor.edit_many(imgs[:3], imgs[:3], e, keys[:3], timestep_range=(0.4, 0.8))
    assert three.shape == imgs[:3].shape
    assert "_edit_batch_into" not in compile_stats(since=before)["programs"]
    np.testing.assert_allclose(np.asarray(three), np.asarray(four[:3]), rtol=0, atol=1e-6)


def test_views_edited_side_by_side_are_each_views_own_edit(editor):
    """On one CPU device edit_views makes one single-view call per core at once (threads):
    each view gets the edit a call of its own gives, in order."""
    import os

    from jaxedit.editors import edit_views

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert editor.batch == 1
    assert editor.calls_side_by_side == max(1, min(cores, jx.CPU_CALLS))
    imgs = np.stack([_image(60 + i, (20, 16, 3)) for i in range(3)])
    keys = jax.random.split(jax.random.key(5), 3)
    e = editor.encode(PROMPT)
    together = edit_views(editor, imgs, imgs, e, keys, timestep_range=(0.45, 0.85))
    for i, view in enumerate(together):
        alone = editor.edit(imgs[i], imgs[i], e, keys[i], timestep_range=(0.45, 0.85))
        np.testing.assert_array_equal(np.asarray(view), np.asarray(alone))


def test_edit_views_makes_calls_side_by_side_when_the_editor_says_so():
    """edit_views runs ``calls_side_by_side`` calls at once and returns the views in order
    (an editor whose calls wait for each other would hang one call at a time)."""
    import threading

    from jaxedit.editors import edit_views

    class Meeting:
        calls_side_by_side = 2

        def __init__(self):
            self.barrier = threading.Barrier(2, timeout=10)

        def edit(self, image, original, embedding, key, **kw):
            self.barrier.wait()  # both calls in flight at once, or a BrokenBarrierError
            return image + 1

    views = [np.full((2, 2, 3), i, np.float32) for i in range(4)]
    out = edit_views(Meeting(), views, views, None, list(range(4)))
    assert [float(v[0, 0, 0]) for v in out] == [1.0, 2.0, 3.0, 4.0]


def test_warm_up_compiles_the_program_the_run_then_uses(editor):
    """The demo's warm-up (on a thread, during the reconstruction) compiles the editor's
    program for the run's view size, batch and guidance: the run's first edit compiles
    nothing (e(r) given as the difficulty gives it, a NumPy interpolation)."""
    from jaxedit.compilation import compile_stats
    from jaxedit.editors import edit_views, interpolate_embedding, warm_up

    guidance = (5.0, 1.25)  # a program no other test builds
    warm_up(editor, 20, 16, jax.random.key(0), views=2, guidance=guidance)
    e = interpolate_embedding(editor.encode(PROMPT), editor.encode(""), 0.5)
    imgs = np.stack([_image(40 + i, (20, 16, 3)) for i in range(2)])
    before = compile_stats()
    out = edit_views(editor, imgs, imgs, e, jax.random.split(jax.random.key(3), 2),
                     timestep_range=(0.45, 0.85), guidance=guidance)
    assert len(out) == 2 and np.asarray(out[0]).shape == (20, 16, 3)
    assert "_edit_batch_into" not in compile_stats(since=before)["programs"]
