"""``import jaxedit`` changes nothing in the caller's program, and the layers import downwards."""

import ast
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
