"""Run by tests/test_distributed.py: one of 2 processes x 2 forced CPU devices on 127.0.0.1.

    python tests/distributed_child.py PORT PROCESS_ID OUT_DIR

Joins the runtime (:func:`jaxedit.parallel.distributed.initialize`), then compares, on every
process, the cross-process program with the same math on one local device:

* a sharded edit batch: the JAX editor (stand-in networks) with a mesh over all 4 devices of
  both processes, gathered (:func:`jaxedit.parallel.fetch`), vs the same editor on 1 device;
* the split edit of the pipeline (:class:`jaxedit.parallel.distributed.SplitEditor`): 5 views of the
  simulated editor, 3 edited by process 0 and 2 by process 1, gathered, vs one process's edits;
* the data-parallel loss and gradient (:func:`jaxedit.parallel.views_loss_and_grad_jit`) over
  4 views sharded over the 4 devices vs 1 device.

Writes OUT_DIR/report_<PROCESS_ID>.json. Not a test module.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from jaxedit.parallel import distributed

T0 = time.perf_counter()
PORT, PID, OUT = int(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3])
distributed.initialize(distributed.DistributedConfig(
    coordinator=f"127.0.0.1:{PORT}", num_processes=2, process_id=PID, init_timeout=60,
    heartbeat_timeout=10))

import jax  # noqa: E402  (after the runtime is joined)
import numpy as np  # noqa: E402
from ip2p_standins import standin_editor  # noqa: E402

from jaxedit import camera as camlib  # noqa: E402
from jaxedit import gaussians as G  # noqa: E402
from jaxedit import parallel as par  # noqa: E402
from jaxedit import train  # noqa: E402
from jaxedit_lab.simulated import SimulatedEditor  # noqa: E402

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def max_diff(a, b) -> float:
    return float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max())


def edit_checks(report):
    """The JAX editor's batch sharded over both processes' devices vs one device."""
    local = jax.local_devices()[:1]
    rng = np.random.default_rng(0)  # the same inputs on every process
    images = rng.uniform(0, 1, (4, 24, 20, 3)).astype(np.float32)
    originals = rng.uniform(0, 1, (4, 24, 20, 3)).astype(np.float32)
    keys = np.asarray(jax.random.key_data(jax.random.split(jax.random.key(0), 4)))  # host data
    one = standin_editor(size=32, steps=2, devices=local)
    every = standin_editor(size=32, steps=2, devices=jax.devices())
    e = np.asarray(one.encode("make it red"))  # host data: the same on every process
    for b in (4,):  # padding (3 views on 4 devices) is tests/test_sharding.py's, in one process
        ref = one.edit_many(images[:b], originals[:b], e, keys[:b], timestep_range=(0.3, 0.9))
        # This JAX cannot device_put a typed key array from the host onto other processes'
        # devices: the keys go in already placed as the editor places them (by view).
        global_keys = jax.random.wrap_key_data(jax.device_put(keys[:b], every.by_view))
        got = every.edit_many(images[:b], originals[:b], e, global_keys,
                              timestep_range=(0.3, 0.9))
        report[f"edit_b{b}_processes"] = len({d.process_index for d in got.sharding.device_set})
        report[f"edit_b{b}_devices"] = len(got.sharding.device_set)
        got = par.fetch(got)
        report[f"edit_b{b}_shape"] = list(got.shape)
        report[f"edit_b{b}_max_abs_diff"] = max_diff(ref, got)


def split_checks(report):
    """:class:`SplitEditor` of the simulated editor: each process edits its slice."""
    editor = SimulatedEditor()
    split = distributed.SplitEditor(editor)
    rng = np.random.default_rng(1)
    images = rng.uniform(0, 1, (5, 16, 16, 3)).astype(np.float32)
    keys = jax.random.split(jax.random.key(2), 5)
    e = editor.encode("turn him into a bronze statue")
    ref = np.stack([np.asarray(editor.edit(images[i], images[i], e, keys[i],
                                           timestep_range=(0.5, 0.5))) for i in range(5)])
    got = split.edit_many(images, images, e, keys, timestep_range=(0.5, 0.5))
    report["split_batch"] = split.batch
    report["split_mine"] = list(range(5))[distributed.process_slice(5, PID, 2)]
    report["split_bit_equal"] = bool(np.array_equal(ref, got))
    report["split_max_abs_diff"] = max_diff(ref, got)


def train_checks(report):
    """The data-parallel loss and gradient over both processes vs one device."""
    cams = camlib.hemisphere(4, radius=2.2, width=16, height=16, fov_deg=50.0)
    rng = np.random.default_rng(0)
    images = rng.uniform(0.2, 0.8, (4, 16, 16, 3)).astype(np.float32)
    g = G.from_points(rng.normal(scale=0.3, size=(40, 3)), rng.uniform(size=(40, 3)),
                      sh_degree=0)
    state = train.init_state(g, train.TrainConfig(iterations=100, sh_degree=0), 1.0,
                             max_intersections=4096)
    key = jax.random.key(1)
    single = jax.device_put((state, images, cams), jax.local_devices()[0])
    mesh = par.views_mesh()  # every process's devices
    sharded = (par.replicate(state, mesh), par.shard_views(images, mesh),
               par.shard_views(cams, mesh))
    # Each process's own 2 views, placed from process-local data, must be the same arrays.
    mine = par.shard_local_views(images[2 * PID:2 * PID + 2], mesh)
    report["local_views_equal"] = bool(np.array_equal(par.fetch(mine), images))
    loss1, _, grad1 = par.views_loss_and_grad_jit(*single, key)
    loss2, _, grad2 = par.views_loss_and_grad_jit(*sharded, key)
    report["loss"] = [float(loss1), float(par.fetch(loss2))]
    report["images_processes"] = len({d.process_index for d in sharded[1].sharding.device_set})
    scale = max(float(np.abs(np.asarray(getattr(grad1, f))).max()) for f in FIELDS)
    report["grad_scale"] = scale
    report["grad_max_abs_diff"] = max(max_diff(getattr(grad1, f), par.fetch(getattr(grad2, f)))
                                      for f in FIELDS)
    report["grad_bit_equal"] = all(np.array_equal(np.asarray(getattr(grad1, f)),
                                                  par.fetch(getattr(grad2, f))) for f in FIELDS)


if __name__ == "__main__":
    report = {"process_index": jax.process_index(), "process_count": jax.process_count(),
              "devices": len(jax.devices()), "local_devices": len(jax.local_devices())}
    for name, check in (("edit", edit_checks), ("split", split_checks), ("train", train_checks)):
        t = time.perf_counter()
        check(report)
        report[f"{name}_seconds"] = round(time.perf_counter() - t, 2)
    distributed.barrier("distributed-child-done")
    report["seconds"] = round(time.perf_counter() - T0, 2)
    (OUT / f"report_{PID}.json").write_text(json.dumps(report))
