"""Compile once: the persistent compilation cache, and the record of what compiled.

The accounting is checked on events fed by hand (names, hits, in-flight compiles), and end to
end in two fresh processes sharing one cache folder: the first compiles a program, the second
reads it from the cache and compiles nothing of it.
"""

from __future__ import annotations

import importlib
import io
import json
import os
import subprocess
import sys
import threading

import jax
import jax.numpy as jnp
import pytest

from jaxedit import compilation
from jaxedit.errors import DataError

BACKEND = compilation._BACKEND_COMPILE


def test_counters_separate_compiles_from_cache_hits_per_program():
    c = compilation._Counters()
    c.on_start(BACKEND, 0.0, fun_name="jit(step)")
    assert [n for n, _ in c.in_flight.values()] == ["jit(step)"]
    c.on_duration(BACKEND, 2.0, fun_name="jit(step)")
    c.on_start(BACKEND, 0.0, fun_name="jit(step)")
    c.on_event(compilation._CACHE_HIT)
    c.on_duration(BACKEND, 0.25, fun_name="jit(step)")
    c.on_duration(compilation._TRACE, 0.5, fun_name="step")
    assert not c.in_flight
    step = c.programs["step"]
    assert (step.count, step.cache_hits, step.seconds) == (1, 1, 2.25)
    assert c.trace_seconds == 0.5


def test_compile_stats_counts_a_new_program_once_and_since_gives_the_difference():
    before = compilation.compile_stats()

    def scaled_cumsum_for_test(x):
        return jnp.cumsum(x) * 3.0

    f = jax.jit(scaled_cumsum_for_test)
    f(jnp.arange(7.0)).block_until_ready()
    f(jnp.arange(7.0)).block_until_ready()  # the in-memory cache: no second compile
    stats = compilation.compile_stats(since=before)
    program = stats["programs"]["scaled_cumsum_for_test"]
    assert program["count"] + program["cache_hits"] == 1
    assert stats["count"] + stats["cache_hits"] >= 1 and stats["seconds"] > 0
    assert set(stats) == {"count", "seconds", "cache_hits", "trace_seconds", "lower_seconds",
                          "programs"}
    json.dumps(stats)  # goes into metrics.json as it is
    assert "scaled_cumsum_for_test" not in compilation.compile_stats(
        since=compilation.compile_stats())["programs"]


def test_compiling_now_names_a_compile_in_flight_in_another_thread():
    c = compilation._counters()
    started, finish = threading.Event(), threading.Event()

    def fake_compile():
        c.on_start(BACKEND, 0.0, fun_name="jit(fake_program)")
        started.set()
        finish.wait(5)
        c.on_duration(BACKEND, 0.01, fun_name="jit(fake_program)")

    t = threading.Thread(target=fake_compile)
    t.start()
    started.wait(5)
    name, seconds = compilation.compiling_now()
    assert name == "fake_program" and seconds >= 0
    finish.set()
    t.join()
    assert compilation.compiling_now() is None


def test_progress_says_when_it_is_compiling(monkeypatch):
    from experiments import progress

    monkeypatch.setattr(progress._CompileWatch, "POLL", 0.02)
    monkeypatch.setattr(compilation, "compiling_now", lambda: ("train_chunk", 3.0))
    stream = io.StringIO()
    with progress.Progress(10, "edit", mode="log", stream=stream) as bar:
        deadline = threading.Event()
        for _ in range(100):
            if "compiling train_chunk" in stream.getvalue():
                break
            deadline.wait(0.02)
        bar.update(1)
    assert stream.getvalue().count("compiling train_chunk") == 1  # once per program


def test_cache_switches_and_bound(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXEDIT_COMPILE_CACHE_DIR", str(tmp_path / "xla"))
    assert compilation.persistent_cache_dir() == tmp_path / "xla"
    for off in ("0", "off", "false"):
        monkeypatch.setenv("JAXEDIT_COMPILE_CACHE", off)
        assert compilation.persistent_cache_dir() is None
    monkeypatch.delenv("JAXEDIT_COMPILE_CACHE")
    monkeypatch.setenv("JAXEDIT_COMPILE_CACHE_MB", "64")
    assert compilation.max_cache_bytes() == 64 * 2 ** 20
    for bad in ("-1", "0", "nan", "inf", "lots"):
        monkeypatch.setenv("JAXEDIT_COMPILE_CACHE_MB", bad)
        with pytest.raises(DataError, match="JAXEDIT_COMPILE_CACHE_MB"):
            compilation.max_cache_bytes()
    monkeypatch.setenv("JAXEDIT_COMPILE_CACHE_MIN_S", "0")
    assert compilation.min_compile_seconds() == 0.0
    monkeypatch.delenv("JAXEDIT_COMPILE_CACHE_MIN_S")
    assert compilation.min_compile_seconds() == compilation.MIN_COMPILE_SECONDS
    for bad in ("-0.5", "nan", "inf", "soon"):
        monkeypatch.setenv("JAXEDIT_COMPILE_CACHE_MIN_S", bad)
        with pytest.raises(DataError, match="JAXEDIT_COMPILE_CACHE_MIN_S"):
            compilation.min_compile_seconds()


def test_trim_cache_removes_the_least_recently_used_entries_past_the_bound(tmp_path):
    folder = tmp_path / "xla"
    assert compilation.trim_cache(folder, 10) == 0  # no folder yet: nothing to do
    folder.mkdir()
    for i, name in enumerate("abcd"):  # a: used longest ago ... d: most recently
        entry = folder / f"{name}-cache"
        entry.write_bytes(b"x" * 100)
        (folder / f"{name}-atime").write_bytes(b"t")  # JAX's own sidecar (older folders)
        os.utime(entry, (1000 + i, 1000 + i))
    os.utime(folder / "a-cache", (5000, 1000))  # read recently: a is the newest now
    (folder / "unrelated.txt").write_bytes(b"y" * 1000)  # not an entry: never counted
    assert compilation.trim_cache(folder, 400) == 0
    assert compilation.trim_cache(folder, 250) == 200  # b then c go
    left = sorted(p.name for p in folder.iterdir())
    assert left == ["a-atime", "a-cache", "d-atime", "d-cache", "unrelated.txt"]


_CHILD = """
import json, sys, jax, jax.numpy as jnp
import jaxedit
from jaxedit.compilation import compile_stats
jaxedit.enable_compilation()  # what every command does first
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # cache even a tiny one
def cached_program_for_test(x):
    return jnp.tanh(x @ x.T).sum(0)
before = compile_stats()
jax.jit(cached_program_for_test)(jnp.ones((16, 16))).block_until_ready()
print(json.dumps({"dir": jax.config.jax_compilation_cache_dir,
                  "jax_bound": jax.config.jax_compilation_cache_max_size,
                  "program": compile_stats(since=before)["programs"]["cached_program_for_test"]}))
"""


def _child(env):
    out = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_second_process_reads_the_program_from_the_cache(tmp_path):
    env = {**os.environ, "JAXEDIT_COMPILE_CACHE_DIR": str(tmp_path / "xla"),
           "JAX_PLATFORMS": "cpu"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    cold = _child(env)
    assert cold["dir"] == str(tmp_path / "xla")
    assert cold["jax_bound"] == -1  # bounded by trim_cache at start, not by JAX at each write
    assert (cold["program"]["count"], cold["program"]["cache_hits"]) == (1, 0)
    assert any((tmp_path / "xla").iterdir())
    warm = _child(env)
    assert (warm["program"]["count"], warm["program"]["cache_hits"]) == (0, 1)
    off = _child({**env, "JAXEDIT_COMPILE_CACHE": "0"})
    assert off["dir"] is None and off["program"]["count"] == 1


def test_scenes_of_nearby_sizes_and_frames_share_one_render_program():
    """A run renders its input PLY, each snapshot's alive Gaussians and the trained scene:
    counts the user never chose. They share one program per buffer size, and the pixels are
    those of the unpadded scene."""
    import numpy as np

    from jaxedit import camera as cl
    from jaxedit import gaussians as gl
    from jaxedit.raster import render, render_reference

    render_module = importlib.import_module("jaxedit.raster.render")  # the module, not render()

    rng = np.random.default_rng(0)
    cams = cl.orbit(2, radius=3.0, width=24, height=20)

    def scene(n):
        d = rng.normal(size=(n, 3)) * 0.4
        return gl.from_points(d, rng.uniform(size=(n, 3)), sh_degree=0, init_opacity=0.6)

    before = compilation.compile_stats()
    outs = {n: render(scene(n), cams, background=(1.0, 1.0, 1.0)) for n in (700, 850, 1000)}
    programs = compilation.compile_stats(since=before)["programs"]
    assert programs["render_tiles"]["count"] + programs["render_tiles"]["cache_hits"] <= 2
    for n, out in outs.items():
        assert out.means2d.shape == (2, n, 2) and out.radii.shape == (2, n)
    # The padded frame is the unpadded one: the reference renderer of the same scene agrees.
    g = scene(300)
    out = render(g, cams[0], background=(1.0, 1.0, 1.0))
    ref = render_reference(g, cams[0], background=(1.0, 1.0, 1.0))
    np.testing.assert_allclose(np.asarray(out.rgb), np.asarray(ref.rgb), atol=2e-5)
