"""Why the bundled editor's draws blend and its identity drifts: a cheap study of a weights
folder on a few held-out views (issue 51, point 2), minutes where the full quality
benchmark (``benchmarks/editor_quality.py``) takes an hour.

Per guidance setting, on ``--per-scene`` held-out views of each scene (fresh noise, T = 0.98
unless said, the benchmark's DDIM steps):

- identity: the edit with E("") against the input, at T = 0.45, 0.85 and 0.98, for image
  guidance 1.5 (the default) and 1.0 (the text guidance does nothing with E("")); beside it
  the VAE round trip, the best any edit through the latent space can keep;
- the one-outcome instructions of every scene (bronze, black and white): PSNR of the edit to
  its target against the input's PSNR to it;
- the divergent ones (splash, neon): the outcome measure's classes
  (:mod:`jaxedit_lab.outcome_class`) over ``--draws`` draws per view;

for text guidance 7.5 (the default), 3 and 1.5, at each of ``--edit-t`` (T = 0.98, and 0.85
the top of ProEdit's SDEdit range); with ``--holding``, the quality benchmark's holding
figures of the divergent instructions on the same views (from a view halfway into an
outcome, the share of edits that stay in it at T = 0.45 and 0.85), at the default guidance;
for each divergent edit where its change lies (:func:`band_figures`: inside the band of the
outcome it leans to or outside it, and how strongly), beside the same figures of the
outcome targets' VAE round trips (the floor of a latent edit); with ``--noise-bins``,
whether the outcome follows the noise as ``train-editor --outcome-from-noise`` teaches
(the SDEdit noise's checkerboard projection set to each outcome's bin: the share of edits
that lean to that outcome, 1/K by chance), and how far the views' latents spread along that
direction (:func:`projection_spread`).
And, from the config alone, what the empty prompt is trained towards
(:func:`empty_prompt_shares`).

    python scripts/editor_study.py --out /tmp/study.json
    python scripts/editor_study.py --weights runs/editor-v2/model --out /tmp/study-v2.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import jax


def empty_prompt_shares(identity_share: float, drop: float, empty_is_identity: bool) -> dict:
    """Of the examples a UNet step sees with the empty prompt and the input image (the branch
    E("") + image that identity and the image guidance use), the share whose target is the
    input itself and the share whose target is an edit, as
    :func:`jaxedit_lab.train_editor.tiny_ip2p.draw_batch` draws them."""
    identity = identity_share * (1 - 2 * drop)  # its image dropped with probability 2 drop
    dropped = (1 - identity_share) * drop  # an instruction's text dropped, its image kept
    identity, edits = (identity + dropped, 0.0) if empty_is_identity else (identity, dropped)
    total = identity + edits
    return {"identity": identity / total, "edit": edits / total,
            "share_of_all_examples": total}


def noise_bins(editor, data, i, views, inputs, key, t=0.98, guidance=(3.0, 1.5)) -> float:
    """The share of instruction ``i``'s edits of ``views`` that lean to (largest weight of
    the outcome measure) the outcome whose bin (:func:`outcome_of_noise`) their SDEdit noise
    is in: each view's noise drawn once, then its projection on :func:`outcome_direction`
    set to each bin's centre in turn (one draw per view and bin). 1/K where the outcome
    ignores that bin."""
    import jax.numpy as jnp
    from scipy.stats import norm

    from jaxedit.editors.diffusion import timestep_bounds
    from jaxedit.editors.jax_ip2p import edit_with_noise_jit, latent_factor
    from jaxedit_lab.outcome_class import classify
    from jaxedit_lab.train_editor.edit_data import outcome_targets
    from jaxedit_lab.train_editor.tiny_ip2p import outcome_direction, outcome_of_noise

    k = len(data.instructions[i].outcomes)
    b, (height, width) = len(views), editor.model_hw(*inputs.shape[1:3])
    f = latent_factor(editor.nets.vae)
    base = jax.random.normal(key, (b, height // f, width // f, 4))
    direction = outcome_direction(*base.shape[1:])
    projection = jnp.einsum("bhwc,hwc->b", base, direction)
    images = jnp.asarray(inputs[views])
    step = timestep_bounds((t, t), editor.num_train_timesteps)[0]
    hits = 0
    for c in range(k):
        centre = float(norm.ppf((c + 0.5) / k))
        noise = base + (centre - projection)[:, None, None, None] * direction
        assert (np.asarray(outcome_of_noise(noise, jnp.full(b, k))) == c).all()
        x = np.asarray(edit_with_noise_jit(
            editor.nets, images, images, editor.encode(data.instructions[i].prompt),
            editor.encode(""), jnp.full(b, step, jnp.int32), jnp.zeros_like(noise), noise,
            editor.schedule, editor.config(guidance)))
        hits += sum(int(np.argmax(classify(x[j], inputs[v], outcome_targets(data, v, i),
                                           other_gate=False)["weights"]) == c)
                    for j, v in enumerate(views))
    return hits / (k * b)


def projection_spread(editor, images: np.ndarray) -> dict:
    """Std over ``images`` [B, H, W, 3] of their scaled latents' projection on
    :func:`outcome_direction` and on the uniform unit direction: how much of a view's latent
    lies where ``outcome_of_noise`` reads the noise (the noise's own: 1)."""
    import jax.numpy as jnp

    from jaxedit.editors.jax_ip2p import encode_latents, resize_images
    from jaxedit_lab.train_editor.tiny_ip2p import outcome_direction

    x = resize_images(jnp.asarray(images, jnp.float32), editor.model_hw(*images.shape[1:3]))
    z = np.asarray(encode_latents(editor.nets.vae, x, x, 0.0, editor.config())[0])  # means
    along = np.einsum("bhwc,hwc->b", z, outcome_direction(*z.shape[1:]))
    uniform = z.reshape(len(z), -1).sum(1) / np.sqrt(z[0].size)
    return {"checkerboard": float(along.std()), "uniform": float(uniform.std())}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", type=Path, default=None)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--per-scene", type=int, default=2)
    p.add_argument("--draws", type=int, default=2)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--text-scales", default="7.5,3,1.5")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--novel", action="store_true",
                   help="cameras off the training orbits (edit_data.novel_views) instead of "
                        "the held-out ones")
    p.add_argument("--image-scales", default="1.5,1")
    p.add_argument("--edit-image-scales", default="1.5",
                   help="image guidance of the instructions' edits, each with every text "
                        "scale (a higher one holds the edit closer to the input)")
    p.add_argument("--edit-t", default="0.98",
                   help="the instructions' SDEdit strengths T (comma-separated)")
    p.add_argument("--holding", action="store_true",
                   help="also the divergent instructions' holding figures (default guidance)")
    p.add_argument("--noise-bins", action="store_true",
                   help="also whether the divergent outcomes follow the noise's bin "
                        "(outcome_of_noise), at T = 0.98 and text guidance 3")
    p.add_argument("--sheet", type=Path, default=None,
                   help="PNG of the edits at the first guidance pair: a row per view, the input "
                        "then bronze, black and white, the divergent draws")
    args = p.parse_args(argv)

    from jaxedit.editors import bundled_editor
    from jaxedit.editors.jax_ip2p import JaxIP2PEditor
    from jaxedit_lab.train_editor import rebuild_dataset, trained_on
    from jaxedit_lab.train_editor.edit_data import novel_dataset, outcome_targets
    from jaxedit_lab.train_editor.quality import (band_figures, holding, nearest,
                                                        outcome_figures, psnr, vae_roundtrip)
    from jaxedit_lab.train_editor.quality import run_edits as _run

    folder = args.weights or bundled_editor()
    settings = trained_on(folder)
    t0 = time.perf_counter()
    data = None if args.novel else rebuild_dataset(settings)
    if args.novel:
        data = novel_dataset(int(settings["size"]), args.per_scene, tuple(settings["scenes"]),
                             int(settings["procedural_views"]))
        views = np.arange(len(data.inputs))
    else:
        held = np.flatnonzero(data.held_out)
        views = np.concatenate([
            held[data.scene[held] == s][:: max(1, (data.scene[held] == s).sum()
                                              // args.per_scene)][: args.per_scene]
            for s in range(len(data.scenes))])
    editor = JaxIP2PEditor.from_pretrained(folder, steps=args.steps)
    inputs = data.inputs.astype(np.float32) / 255
    key = jax.random.key(args.seed)
    counter = iter(range(1 << 30))

    def edits(rows, embeddings, t, guidance):
        return _run(editor, inputs[rows], inputs[rows], np.stack(embeddings),
                    jax.random.fold_in(key, next(counter)), t, guidance)

    null = editor.encode("")
    out: dict = {"empty_prompt_branch": {
        "text dropout keeps the edit (v1)": empty_prompt_shares(0.1, 0.05, False),
        "empty_is_identity (v2)": empty_prompt_shares(0.1, 0.05, True)},
        "weights": str(folder), "views": [int(v) for v in views],
                 "scenes": [data.scenes[data.scene[v]] for v in views], "steps": args.steps,
                 "draws": args.draws}
    rt = vae_roundtrip(editor, inputs[views])
    out["vae_roundtrip_psnr_db"] = float(np.mean(psnr(rt, inputs[views])))
    out["identity_psnr_db"] = {}
    for image_scale in (float(x) for x in args.image_scales.split(",")):
        got = {}
        for t in (0.45, 0.85, 0.98):
            x = edits(list(views), [null] * len(views), t, (7.5, image_scale))
            got[f"{t:g}"] = float(np.mean(psnr(x, inputs[views])))
        out["identity_psnr_db"][f"image {image_scale:g}"] = got
        print("identity", image_scale, got, "roundtrip", out["vae_roundtrip_psnr_db"],
              flush=True)

    single = [i for i, ins in enumerate(data.instructions)
              if len(ins.outcomes) == 1 and ins.scenes is None]
    divergent = [i for i, ins in enumerate(data.instructions) if len(ins.outcomes) > 1]
    out["band_floor"] = {}  # the outcome targets through the VAE alone
    for i in divergent:
        targets = np.stack([outcome_targets(data, v, i) for v in views])
        k = targets.shape[1]
        trips = vae_roundtrip(editor, targets.reshape(-1, *targets.shape[2:]))
        out["band_floor"][data.instructions[i].prompt] = band_figures(
            trips, np.repeat(inputs[views], k, 0), np.repeat(targets, k, 0))
    out["by_text_scale"] = {}
    pairs = [(float(t), float(i), float(strength)) for strength in args.edit_t.split(",")
             for i in args.edit_image_scales.split(",") for t in args.text_scales.split(",")]
    for scale, image_scale, strength in pairs:
        entry: dict = {}
        rows, embs, which = [], [], []
        for i in single:
            rows += list(views)
            embs += [editor.encode(data.instructions[i].prompt)] * len(views)
            which += [i] * len(views)
        for i in divergent:
            for v in views:
                rows += [v] * args.draws
                embs += [editor.encode(data.instructions[i].prompt)] * args.draws
                which += [i] * args.draws
        x = edits(rows, embs, strength, (scale, image_scale))
        rows, which = np.asarray(rows), np.asarray(which)
        for i in single + divergent:
            sel = which == i
            targets = np.stack([outcome_targets(data, v, i) for v in rows[sel]])
            ins = data.instructions[i]
            e = {"psnr": float(np.mean(nearest(x[sel], targets)[1])),
                 "psnr_unedited": float(np.mean(nearest(inputs[rows[sel]], targets)[1]))}
            if len(ins.outcomes) > 1:
                f = outcome_figures(x[sel], inputs[rows[sel]], targets)
                e["band"] = band_figures(x[sel], inputs[rows[sel]], targets)
                e.update({k: f[k] for k in ("unedited_fraction", "single_outcome_fraction",
                                            "outcome_frequencies", "mixed_fraction",
                                            "other_fraction", "progress_median",
                                            "residual_median")})
                e["without_other_gate"] = {k: f["without_other_gate"][k] for k in (
                    "single_outcome_fraction", "outcome_frequencies", "mixed_fraction")}
            entry[ins.prompt] = e
        name = f"{scale:g}" if image_scale == 1.5 else f"{scale:g} image {image_scale:g}"
        name += "" if strength == 0.98 else f" T {strength:g}"
        out["by_text_scale"][name] = entry
        if args.sheet is not None and (scale, image_scale, strength) == pairs[0]:
            # rows: views; the input, then its edits
            from jaxedit.io.images import write_image

            grid = [np.concatenate([inputs[v], *x[rows == v]], 1) for v in views]
            write_image(args.sheet, np.concatenate(grid, 0))
        print("text scale", name, json.dumps(entry), flush=True)
    if args.holding:
        out["holding"] = {}
        for i in divergent:
            ins = data.instructions[i]
            out["holding"][ins.prompt] = holding(
                lambda images, originals, embs, t: _run(
                    editor, images, originals, np.stack(embs),
                    jax.random.fold_in(key, next(counter)), t),
                inputs, data, i, list(views), editor.encode(ins.prompt), null)
            print("holding", ins.prompt, out["holding"][ins.prompt], flush=True)
    if args.noise_bins:
        out["noise_bins"] = {data.instructions[i].prompt: noise_bins(
            editor, data, i, list(views), inputs, jax.random.fold_in(key, next(counter)))
            for i in divergent}
        shown = np.concatenate([inputs[views]] + [
            np.concatenate([outcome_targets(data, v, i) for v in views]) for i in divergent])
        out["latent_projection_std"] = projection_spread(editor, shown)
        print("noise bins", out["noise_bins"], out["latent_projection_std"], flush=True)
    out["seconds"] = round(time.perf_counter() - t0, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print("wrote", args.out)


if __name__ == "__main__":
    from jaxedit.errors import DataError

    try:
        main()
    except DataError as e:  # --weights: a folder with no training record, unreadable weights
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
