"""jaxedit.raster.placement.commit, and the compiles it saves: one render program whether the
scene's arrays are fresh (uncommitted), committed or NumPy, and whether the background is
given or black."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxedit.edit.outputs import Renderer
from jaxedit.raster.placement import commit
from jaxedit.raster import render
from jaxedit.raster.render import _render_tiles_jit
from test_raster import CAM, make_scene


def test_commit_keeps_placement_and_values_and_leaves_the_rest_alone():
    device = jax.devices()[0]
    fresh, placed = jnp.arange(3.0), jax.device_put(jnp.ones(2), device)
    host = np.float32([1.5, 2.5])
    out = commit({"fresh": fresh, "placed": placed, "host": host, "scalar": np.float32(2),
                  "python": 0.5, "none": None})
    assert out["fresh"].committed and out["fresh"].devices() == fresh.devices()
    assert np.array_equal(out["fresh"], fresh) and out["placed"] is placed
    assert isinstance(out["host"], jax.Array) and out["host"].committed
    assert np.array_equal(out["host"], host) and out["host"].dtype == np.float32
    assert out["scalar"].committed and out["scalar"].shape == ()
    assert out["python"] == 0.5 and out["none"] is None
    # Under a caller's jit the tracers pass through untouched.
    assert float(jax.jit(lambda x: commit(x) * 2)(fresh)[1]) == 2.0


def test_render_compiles_once_for_fresh_committed_and_host_arrays():
    g = make_scene(3)
    committed = jax.device_put(g, jax.devices()[0])
    host_camera = jax.tree_util.tree_map(np.asarray, CAM)
    first = render(g, CAM)
    size = _render_tiles_jit._cache_size()
    again = [render(committed, CAM), render(g, host_camera),
             render(committed, host_camera, background=jnp.zeros(3))]
    assert _render_tiles_jit._cache_size() == size
    for out in again:
        assert np.array_equal(np.asarray(out.rgb), np.asarray(first.rgb))


def test_renderer_reuses_its_largest_buffer():
    renderer = Renderer((1.0, 1.0, 1.0))
    big, small = make_scene(4, n=48), make_scene(4, n=48, scale=(0.01, 0.02))
    renderer(big, CAM)
    kept = renderer.max_intersections
    size = _render_tiles_jit._cache_size()
    out = renderer(small, CAM)
    assert renderer.max_intersections == kept and _render_tiles_jit._cache_size() == size
    assert np.array_equal(np.asarray(out.rgb), np.asarray(render(
        small, CAM, background=jnp.ones(3)).rgb))
