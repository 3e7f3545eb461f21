"""Suite-wide settings: one compilation cache for the run, and a bound on memory mappings.

Compile once: every test, every xdist worker (``-n auto``) and every command the CLI tests
start in a subprocess share one persistent compilation cache (``JAXEDIT_COMPILE_CACHE_DIR``, a
fresh folder per run unless the caller sets one, holding every program:
``JAXEDIT_COMPILE_CACHE_MIN_S=0``), so a program that one test compiled is read back, not
compiled again, by the next process or by a test that builds the same program from a new
closure.

Memory mappings: keep the test process under the kernel's limit.

XLA:CPU maps each compiled program's code and data sections separately, and JAX keeps every
program compiled in the session alive in its caches. The whole suite compiles thousands of
programs (the Stable Diffusion networks, the splatter at many sizes, trainers); past
``vm.max_map_count`` (65530 by default) LLVM cannot map the next one and aborts the process.
That happened at test_train after 93% of the suite (pycolmap's crash handler, loaded by the
capture tests, then turned the abort into a hang). So after each test module, once the
mappings pass half the limit, JAX's caches are dropped: later modules recompile what they
use, and nothing else changes.
"""

from __future__ import annotations

import gc
import os
import shutil
import tempfile

import pytest

# Set before the cache is switched on below; the subprocesses inherit it through the
# environment.
_OWN_CACHE = None
if not os.environ.get("JAXEDIT_COMPILE_CACHE_DIR"):
    _OWN_CACHE = tempfile.mkdtemp(prefix="jaxedit-test-xla-")
    os.environ["JAXEDIT_COMPILE_CACHE_DIR"] = _OWN_CACHE
# Every program, however quick to compile: the suite's processes (xdist workers, the commands
# the CLI tests start) build the same small programs again and again, and a read is cheaper.
os.environ.setdefault("JAXEDIT_COMPILE_CACHE_MIN_S", "0")

# The suite runs as the commands do: the persistent cache and the record of compiles on
# (``import jaxedit`` alone switches neither).
import jaxedit  # noqa: E402

jaxedit.enable_compilation()


# Two tiers. The README's command (`python -m pytest tests -n auto`) runs the default tier: every
# unit, property and oracle test, and end-to-end runs of the main commands. Tests marked `slow`
# (several processes, networks trained, studies and scale runs with a quality bar) run with
# --slow (CI, every time) or -m slow (that tier alone); a test named by its node id always runs.
def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true",
                     help="also run the tests marked slow (CI runs every test)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--slow") or config.option.markexpr:
        _longest_files_first(items, ("test_suite.json", "test_suite_slow.json"))
        return
    named = [a.replace(os.sep, "/") for a in config.args if "::" in a]

    def wanted(item):
        return item.get_closest_marker("slow") is None or any(
            item.nodeid == n or item.nodeid.startswith((n + "[", n + "::")) or n.endswith(item.nodeid)
            for n in named)

    keep, left_out = [], []
    for item in items:
        (keep if wanted(item) else left_out).append(item)
    if left_out:
        config.hook.pytest_deselected(items=left_out)
        items[:] = keep
    _longest_files_first(items, ("test_suite.json",))


def _longest_files_first(items, tables: tuple[str, ...]) -> None:
    """Order the test files by their measured time, longest first (stable within a file).

    xdist hands a file (``--dist loadfile``) to the next free worker in this order
    (``--no-loadscope-reorder``), so the long files start first and the short ones fill in
    at the end: the longest-processing-time rule, which keeps one worker from running a
    long file alone while the other is idle. The times are the suite's own benchmark
    (``tables`` in ``benchmarks/results/cpu``: the default tier's, and the slow tier's when
    it runs); a file they lack counts as 0 s.
    """
    import json
    from pathlib import Path

    seconds: dict[str, float] = {}
    results = Path(__file__).parents[1] / "benchmarks" / "results" / "cpu"
    for table in (results / name for name in tables):
        try:
            files = json.loads(table.read_text()).get("files_s", {})
        except (OSError, ValueError):
            continue
        for name, s in files.items():
            seconds[name] = seconds.get(name, 0.0) + float(s)
    if seconds:
        items.sort(key=lambda item: -seconds.get(item.nodeid.split("::")[0], 0.0))


def pytest_sessionfinish(session, exitstatus):
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


# The suite's own cost (benchmarks/test_suite.py): with JAXEDIT_TEST_PROFILE=FILE each test's
# wall time and the XLA compiles it caused in this process go to FILE, one JSON line a test.
_PROFILE = os.environ.get("JAXEDIT_TEST_PROFILE")
if _PROFILE:
    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        import json
        import time

        from jaxedit.compilation import compile_stats

        before, t0 = compile_stats(), time.perf_counter()
        yield
        seconds = time.perf_counter() - t0
        compiled = compile_stats(since=before)
        with open(_PROFILE, "a") as f:
            f.write(json.dumps({"test": item.nodeid, "seconds": round(seconds, 3),
                                "compile_seconds": compiled["seconds"],
                                "compiles": compiled["count"],
                                "cache_hits": compiled["cache_hits"],
                                "programs": {name: [p["count"], p["seconds"]] for name, p
                                             in compiled["programs"].items()}}) + "\n")


def _count_mappings() -> int:
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux: no such limit to guard
        return 0


def _mapping_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return 65530


@pytest.fixture(autouse=True, scope="module")
def _bounded_mappings():
    yield
    if _count_mappings() > _mapping_limit() // 2:
        import jax

        jax.clear_caches()
        gc.collect()
