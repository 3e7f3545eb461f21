"""The editors' identity on the built-in scenes: where the edit's identity floor comes from.

    python benchmarks/editor_identity.py [--smoke] [--out DIR] [--timestep T]

For every built-in scene at 64 px (the bundled editor's size), the check ``edit`` runs
before its first subtask (:func:`jaxedit.edit.identity.measure_identity`): the difficulty
views (the seeded 16 of ``edit --seed 0``) edited with e(0) as the difficulty oracle edits
them (conditioned on themselves, at its t = 0.98: the edits the schedule reuses), PSNR and
LPIPS-AlexNet against the views. The views are the dataset's photos, which a reconstruction
renders closely (the edit itself checks its own renders). Editors: the bundled small
InstructPix2Pix, the same networks with every UNet weight redrawn at random (a deliberately
poor editor), and the lab's simulated editor. Writes ``DIR/editor_identity.json``.
``--smoke``: one scene, 4 views; ``--scenes NAME ...``: those. ``--timestep T``: the edits at
T instead (0.85, the run's t_max, is where r_0 makes its first edits), written as
``DIR/editor_identity_t{100 T}.json``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from common import machine_info, parse_args, write_json


#: The difficulty oracle's timestep (DifficultyOracle's default), where the check edits.
ORACLE_T = 0.98


def extra(p):
    p.add_argument("--scenes", nargs="*", default=None, help="built-in scenes (default: all)")
    p.add_argument("--timestep", type=float, default=ORACLE_T,
                   help="SDEdit timestep of e(0) (default: the difficulty oracle's, 0.98)")


def random_unet(editor, seed: int = 0):
    """``editor`` with its UNet's weights redrawn from a normal of each array's own std."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    leaves, tree = jax.tree_util.tree_flatten(eqx.filter(editor.nets.unet, eqx.is_array))
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    drawn = [jnp.std(x) * jax.random.normal(k, x.shape, x.dtype) + jnp.mean(x)
             for x, k in zip(leaves, keys)]
    unet = eqx.combine(jax.tree_util.tree_unflatten(tree, drawn), editor.nets.unet)
    editor.nets = eqx.tree_at(lambda n: n.unet, editor.nets, unet)
    editor.name = "bundled-random-unet"
    return editor


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import jax
    import numpy as np

    from jaxedit import scenes
    from jaxedit.edit.difficulty import DifficultyOracle, difficulty_view_subset
    from jaxedit.edit.identity import measure_identity
    from jaxedit.editors.jax_ip2p import JaxIP2PEditor
    from jaxedit.io import load_nerfstudio
    from jaxedit_lab.simulated import SimulatedEditor

    names = args.scenes or (["person"] if args.smoke else scenes.list_scenes())
    count = 4 if args.smoke else None
    editors = {"bundled": JaxIP2PEditor.bundled(),
               "random-unet": random_unet(JaxIP2PEditor.bundled()),
               "simulated": SimulatedEditor()}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            folder = scenes.make_scene(name, Path(tmp) / name, **scenes.size_arguments(name, 64))
            data = load_nerfstudio(folder)
            photos = np.asarray(data.images, np.float32)[np.asarray(data.train_indices)]
            views = difficulty_view_subset(len(photos), count, jax.random.key(0))
            for label, editor in editors.items():
                t0 = time.perf_counter()
                oracle = DifficultyOracle(editor, photos, "", views=views, seed=0,
                                          timestep_range=(args.timestep, args.timestep))
                fig = measure_identity(oracle, photos)
                rows.append({"scene": name, "editor": label, "size": int(photos.shape[2]),
                             "psnr": fig["psnr"], "lpips": fig["lpips"],
                             "psnr_min_view": min(fig["psnr_per_view"]),
                             "lpips_max_view": max(fig["lpips_per_view"]),
                             "views": len(views), "editor_calls": fig["editor_calls"],
                             "seconds": time.perf_counter() - t0})
                print(f"{name:9s} {label:12s} PSNR {fig['psnr']:5.1f} dB  LPIPS "
                      f"{fig['lpips']:.3f}", flush=True)
    suffix = "" if args.timestep == ORACLE_T else f"_t{round(args.timestep * 100)}"
    name = "editor_identity" + suffix
    write_json(args.out, name, {"smoke": args.smoke, "timestep": args.timestep,
                                "rows": rows, "machine": machine_info()})


if __name__ == "__main__":
    main()
