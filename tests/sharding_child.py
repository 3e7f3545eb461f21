"""Run by tests/test_sharding.py in a child process with 4 forced host devices.

Prints one JSON line of measured differences between one-device and 4-device programs.
Not a test module: XLA_FLAGS must be set before JAX initialises, the suite runs on one.
"""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from ip2p_standins import standin_editor

from jaxedit import camera as camlib
from jaxedit import gaussians as G
from jaxedit import parallel as par
from jaxedit import train
from jaxedit.edit.buffer import as_view

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def edit_checks(report):
    devices = jax.devices()
    assert len(devices) == 4, devices
    one = standin_editor(size=32, steps=2, devices=devices[:1])
    four = standin_editor(size=32, steps=2, devices=devices)
    rng = np.random.default_rng(0)
    images = rng.uniform(0, 1, (4, 24, 20, 3)).astype(np.float32)
    originals = rng.uniform(0, 1, (4, 24, 20, 3)).astype(np.float32)
    e = one.encode("make it red")
    keys = jax.random.split(jax.random.key(0), 4)
    for b in (4, 3):  # 3 views are padded to 4 and cut back
        ref = one.edit_many(images[:b], originals[:b], e, keys[:b], timestep_range=(0.3, 0.9))
        got = four.edit_many(images[:b], originals[:b], e, keys[:b], timestep_range=(0.3, 0.9))
        report[f"edit_b{b}_max_abs_diff"] = float(np.abs(np.asarray(ref) - np.asarray(got)).max())
        report[f"edit_b{b}_devices"] = len(got.sharding.device_set)
        report[f"edit_b{b}_shape"] = list(got.shape)
    # The networks alone: the UNet on 12 samples sharded 3 per device vs on one device.
    x = jnp.asarray(rng.standard_normal((12, 4, 3, 8)).astype(np.float32))
    ctx = jnp.asarray(rng.standard_normal((12, 77, e.shape[-1])).astype(np.float32))
    t = jnp.arange(12) * 70
    unet = eqx.filter_jit(lambda nets, x, t, c: nets.unet(x, t, c))
    u1 = unet(one.nets, *jax.device_put((x, t, ctx), devices[0]))
    u4 = unet(four.nets, *jax.device_put((x, t, ctx), four.by_view))
    report["unet_max_abs_diff"] = float(np.abs(np.asarray(u1) - np.asarray(u4)).max())
    report["unet_scale"] = float(np.abs(np.asarray(u1)).max())
    # Two device groups: the editor on device 1, its result moved to the trainer's device 0.
    editor = standin_editor(size=32, steps=2, devices=devices[1:2])
    out = editor.edit(images[0], originals[0], e, keys[0], timestep_range=(0.5, 0.5))
    moved = as_view(out, devices[0])
    report["editor_device"] = [d.id for d in out.devices()]
    report["trainer_device"] = [d.id for d in moved.devices()]
    report["moved_equal"] = bool(np.array_equal(np.asarray(out), np.asarray(moved)))


def train_checks(report):
    cams = camlib.hemisphere(4, radius=2.2, width=16, height=16, fov_deg=50.0)
    rng = np.random.default_rng(0)
    images = jnp.asarray(rng.uniform(0.2, 0.8, (4, 16, 16, 3)).astype(np.float32))
    g = G.from_points(rng.normal(scale=0.3, size=(40, 3)), rng.uniform(size=(40, 3)),
                      sh_degree=0)
    state = train.init_state(g, train.TrainConfig(iterations=100, sh_degree=0), 1.0,
                             max_intersections=4096)
    key = jax.random.key(1)
    single = jax.device_put((state, images, cams), jax.devices()[0])
    mesh = par.views_mesh()
    sharded = (par.replicate(state, mesh), par.shard_views(images, mesh),
               par.shard_views(cams, mesh))
    loss1, _, grad1 = par.views_loss_and_grad_jit(*single, key)
    loss4, _, grad4 = par.views_loss_and_grad_jit(*sharded, key)
    step1, m1 = par.views_step_jit(*single, key)
    step4, m4 = par.views_step_jit(*sharded, key)
    report["loss"] = [float(loss1), float(loss4)]
    scale = max(float(jnp.abs(getattr(grad1, f)).max()) for f in FIELDS)
    report["grad_scale"] = scale
    report["grad_max_abs_diff"] = max(
        float(np.abs(np.asarray(getattr(grad1, f)) - np.asarray(getattr(grad4, f))).max())
        for f in FIELDS)
    # Adam's first step is lr x sign(grad): compare it where the gradient is above rounding
    # noise (a component at ~1e-10 may change sign with the all-reduce's summation order).
    worst = 0.0
    for f in FIELDS:
        g1 = np.asarray(getattr(grad1, f))
        signal = np.abs(g1) > 1e-4 * scale
        a, b = np.asarray(getattr(step1.gaussians, f)), np.asarray(getattr(step4.gaussians, f))
        if signal.any():
            worst = max(worst, float(np.abs(a - b)[signal].max()))
    report["step_max_abs_diff_above_noise"] = worst
    report["step_params_devices"] = len(step4.gaussians.means.sharding.device_set)
    report["overflow"] = [bool(m1["overflow"]), bool(m4["overflow"])]


if __name__ == "__main__":
    report = {}
    edit_checks(report)
    train_checks(report)
    print("REPORT " + json.dumps(report))
