"""Copy a trained editor folder into the package (jaxedit/editors/weights/tiny-ip2p).

    python -m experiments train-editor --out runs/editor --seed 0
    python scripts/bundle_editor.py runs/editor/model [--card CARD.md] [--guidance 2,1.5]

Checks that the folder is a complete diffusers folder that the JAX editor loads and that it
fits the package's budget (20 MB), then replaces the bundled copy whole (staged beside it and
renamed, so an interrupted copy leaves the old one). ``--card`` adds the model card
(README.md of the folder). ``--guidance`` records the (text, image) scales the model is
meant to edit with in its ``instructions.json`` (measured, e.g. by
``scripts/editor_study.py``'s sweep; :func:`jaxedit.editors.recommended_guidance` reads it
back), so that every edit that names none uses them.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.flags import guidance_pair  # noqa: E402

#: The most the bundled weights may weigh (bytes).
BUDGET = 20 * 2 ** 20
#: The files that ship (the rest of a folder, e.g. editor checkpoints, does not).
SHIPPED = ("model_index.json", "instructions.json", "README.md", "*/config.json",
           "*/scheduler_config.json", "*/*.safetensors", "tokenizer/*.json", "tokenizer/*.txt")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder", type=Path, help="the trained diffusers folder (OUT/model)")
    p.add_argument("--card", type=Path, default=None, help="model card to ship as README.md")
    p.add_argument("--guidance", type=guidance_pair, default=None, metavar="TEXT,IMAGE",
                   help="the guidance the model edits with, recorded in instructions.json "
                        "(default: the folder's, else none: InstructPix2Pix's 7.5,1.5)")
    args = p.parse_args(argv)

    from jaxedit.editors.jax_ip2p import JaxIP2PEditor
    from jaxedit.editors import BUNDLED

    JaxIP2PEditor.from_pretrained(args.folder, size=None, steps=1)  # loads, or says why not
    files = sorted({f for pattern in SHIPPED for f in args.folder.glob(pattern) if f.is_file()})
    size = sum(f.stat().st_size for f in files) + (args.card.stat().st_size if args.card else 0)
    if size > BUDGET:
        print(f"error: {args.folder}: {size / 2 ** 20:.1f} MB is over the {BUDGET / 2 ** 20:.0f} MB "
              "budget of the bundled editor", file=sys.stderr)
        return 2
    staging = BUNDLED.with_name(BUNDLED.name + ".staging")
    shutil.rmtree(staging, ignore_errors=True)
    for f in files:
        target = staging / f.relative_to(args.folder)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, target)
    if args.card:
        shutil.copy2(args.card, staging / "README.md")
    if args.guidance is not None:
        listed = staging / "instructions.json"
        table = json.loads(listed.read_text()) if listed.is_file() else {"instructions": []}
        listed.write_text(json.dumps(dict(table, guidance=list(args.guidance)), indent=2) + "\n")
    shutil.rmtree(BUNDLED, ignore_errors=True)
    staging.rename(BUNDLED)
    from jaxedit.editors import recommended_guidance

    print(f"bundled {len(files)} files, {size / 2 ** 20:.1f} MB, into {BUNDLED}; it edits at "
          f"guidance {recommended_guidance(BUNDLED)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
