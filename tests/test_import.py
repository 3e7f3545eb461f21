"""``import jaxedit`` changes nothing in the caller's program, and the layers import downwards."""

import ast
import re
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_PROBE = """
import json, sys
import jax
from jax._src import monitoring
def listeners():
    return {k: len(v) for k, v in vars(monitoring).items()
            if k.startswith("_") and k.endswith("listeners") and isinstance(v, list)}
before, heard = dict(jax.config.values), listeners()
import jaxedit
after = dict(jax.config.values)
changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
layers = sorted(m for m in sys.modules if m.split(".")[:2] == ["jaxedit", "pipelines"]
                or m.split(".")[0] in ("jaxedit_lab", "experiments"))
quiet = heard == listeners()
jaxedit.enable_compilation()
print(json.dumps({"changed": changed, "layers": layers, "listeners": quiet,
                  "listeners_after_enable": heard == listeners(),
                  "changed_by_enable": dict(jax.config.values) != after}))
"""


def test_import_jaxedit_leaves_jax_config_and_listeners_alone(tmp_path):
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "JAX_PLATFORMS": "cpu",
           "JAXEDIT_COMPILE_CACHE_DIR": str(tmp_path / "xla")}
    out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                         cwd=ROOT, env=env, check=True).stdout
    got = json.loads(out.strip().splitlines()[-1])
    assert got["changed"] == [] and got["layers"] == [] and got["listeners"], got
    # the documented switch does what the import no longer does
    assert got["changed_by_enable"] and not got["listeners_after_enable"], got


def _imports(path: Path) -> set[str]:
    """Absolute module names a file imports (relative ones resolved against its package)."""
    rel = path.relative_to(ROOT).with_suffix("")
    package = list(rel.parts[:-1]) if rel.name != "__init__" else list(rel.parts[:-1])
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                names.add(".".join(base + ([node.module] if node.module else [])))
            else:
                names.add(node.module)
    return names


def test_the_library_imports_nothing_above_it():
    above = ("jaxedit_lab", "experiments", "benchmarks", "scripts", "tests")
    bad = {str(p.relative_to(ROOT)): sorted(n for n in _imports(p) if n.split(".")[0] in above)
           for p in sorted((ROOT / "jaxedit").rglob("*.py"))}
    assert not {k: v for k, v in bad.items() if v}


def test_the_lab_is_not_imported_by_the_run_directory_layer():
    """jaxedit.pipelines sits under the lab: the lab may import it, never the reverse."""
    bad = {str(p.relative_to(ROOT)): sorted(n for n in _imports(p) if n.startswith("jaxedit_lab"))
           for p in sorted((ROOT / "jaxedit" / "pipelines").rglob("*.py"))}
    assert not {k: v for k, v in bad.items() if v}


def _layers() -> dict[str, int]:
    """{unit of jaxedit (a top-level module or subpackage): its row in docs/architecture.md's
    table of layers}, read from the table's ``where`` column."""
    rows = [line.split("|")[2] for line in (ROOT / "docs" / "architecture.md").read_text()
            .splitlines() if line.startswith("| ") and "`jaxedit/" in line.split("|")[2]]
    out = {}
    for rank, where in enumerate(rows):
        for name in re.findall(r"`([^`]+)`", where):
            out[name.removeprefix("jaxedit/").removesuffix("/").removesuffix(".py")] = rank
    return out


def _unit(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "jaxedit" and len(parts) > 1 else None


def _unit_graph() -> dict[str, set[str]]:
    """{unit: the other units it imports} over every file of jaxedit/ but its __init__."""
    graph: dict[str, set[str]] = {}
    for path in sorted((ROOT / "jaxedit").rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        if len(rel.parts) == 2 and rel.name == "__init__":
            continue  # the package's facade re-exports every layer
        src = rel.parts[1]
        targets = set()
        for name in _imports(path):
            targets.add(_unit(name))
        for node in ast.walk(ast.parse(path.read_text())):  # `from .. import train`
            if isinstance(node, ast.ImportFrom) and node.level and not node.module and \
                    node.level == len(rel.parts) - 1:
                targets |= {a.name for a in node.names}
        graph.setdefault(src, set()).update(t for t in targets if t and t != src)
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one unit (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                out.append(sorted(part))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_library_has_no_import_circles():
    graph = _unit_graph()
    assert {"train", "densify", "edit", "pipelines"} <= set(graph)
    assert _circles(graph) == []
    # the check can fail: a made-up arrow back closes a circle
    assert _circles(graph | {"densify": graph["densify"] | {"train"}}) == [["densify", "train"]]


def test_every_import_follows_the_architecture_tables_layers():
    layers, graph = _layers(), _unit_graph()
    units = {p.relative_to(ROOT / "jaxedit").parts[0].removesuffix(".py")
             for p in (ROOT / "jaxedit").rglob("*.py")} - {"__init__.py", "__init__"}
    assert sorted(units - set(layers)) == []  # every module has its row
    up = {f"{src} -> {dst}" for src, dsts in graph.items() for dst in dsts
          if layers[dst] > layers[src]}
    assert sorted(up) == []
    assert layers["pipelines"] > layers["edit"] > layers["editors"] > layers["train"]
