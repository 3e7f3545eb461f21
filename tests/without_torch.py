"""Run Python code in a child process where torch, diffusers and transformers cannot be imported.

The JAX editor and jaxedit.models promise to need none of them; an import hook in the child
makes any attempt fail loudly, and the child checks afterwards that none was loaded.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BLOCKED = ("torch", "diffusers", "transformers")

_PRELUDE = f"""
import sys
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {BLOCKED!r}:
            raise ImportError("blocked: " + name)
        return None
sys.meta_path.insert(0, _Block())
"""

_EPILOGUE = f"""
_loaded = [k for k in sys.modules if k.split(".")[0] in {BLOCKED!r}]
assert not _loaded, _loaded
"""


def run_without_torch(body: str, *, timeout: float) -> subprocess.CompletedProcess:
    """Run ``body`` (dedented; it may end by setting ``code``, the exit status) in the child.

    Returns the finished process (stdout and stderr captured as text), run from the repo root.
    """
    script = _PRELUDE + textwrap.dedent(body) + _EPILOGUE + "sys.exit(globals().get('code', 0))\n"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                          timeout=timeout, cwd=ROOT)
