"""How good a trained editor is, on the dataset's held-out cameras (never trained on).

Every figure is measured by editing with an :class:`~jaxedit.editors.base.Editor` that has
``edit_many`` (the JAX InstructPix2Pix) and comparing with the dataset's own outcomes:

- ``full_edit``: PSNR of the edit of the input view (T = ``t_full`` of the schedule, nearly
  pure noise, as IP2P edits a photo) against its target, the nearest outcome for a divergent
  instruction; per instruction, over views and draws, beside the unedited input's, and
  ``per_scene`` both per scene (an instruction of several scenes can be learnt on one only)
  with the input's VAE round trip against the target and ``psnr_ceiling``, the target's own
  round trip against it: about the most an edit decoded from the latents can score (the
  encoder's latent of the target itself; another latent could decode a little nearer), so
  an input that scores more than it (a target that differs from its input by less than the
  autoencoder loses) is, in practice, not to be passed.
- ``identity_psnr_db``: the edit with E("") (no instruction) against the input view, PSNR,
  at T = 0.45 and 0.85 (the ends of ProEdit's SDEdit range) and at ``t_full``;
  ``vae_roundtrip_psnr_db``: the VAE alone (encode to the posterior mean, decode), the best
  any edit through the latent space can keep a view (:func:`vae_roundtrip`);
  ``identity_per_scene``: both per scene (where a shortfall is).
- outcomes of each divergent instruction (:mod:`jaxedit_lab.outcome_class`): every
  fresh-noise edit classed as one outcome, unedited, mixed or other against the unedited
  input; ``unedited_fraction`` over all draws, ``single_outcome_fraction``,
  ``outcome_frequencies``, ``mixed_fraction`` and ``other_fraction`` over the edited draws;
  ``intervals``: the one-outcome share's and each frequency's 95 % interval over the views;
  ``view_spread``: whether a view's draws land on several outcomes as independent draws
  would (the outcome the noise's, not the view's); ``per_scene.SCENE.outcomes``: the same
  classes per scene; ``without_other_gate`` the same where an edit leans however much else
  it changed;
  ``baseline``: the same measure on the unedited input itself, on the E("") edits and on the
  VAE round trips of the same views (what an editor that does not edit scores).
  ``nearest_target``: the old measure (the share of edits nearest each outcome target, and
  ``mixing``, nearer the outcomes' average than any one), with what the unedited input
  scores on it (``unedited_input``): it calls most unedited views one outcome or mixed.
- ``holding``: SDEdit from a view already halfway into outcome c (0.5 input + 0.5 target c):
  the share of edits that stay nearest to c, at T = 0.45 and 0.85, for a small ratio step
  (e(0.625), the next subtask) and for the jump to e(1).
- ``interpolation``: d(input, edit with e(r)) at r = 0, 0.125, ..., 1, by the difficulty's
  distance: ProEdit's premise is that the edit grows with r.

Each draw's key is ``fold_in`` of the run's key by a counter, so a figure is reproducible.
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxedit_lab import outcome_class
from jaxedit.editors.base import editor_guidance, interpolate_embedding
from jaxedit_lab.train_editor.edit_data import EditDataset, outcome_targets

#: SDEdit timesteps of ProEdit's range (:class:`jaxedit.edit.plan.ProEditConfig`'s
#: ``timestep_range``, 0.45-0.85) at which identity is measured, besides ``t_full``.
SDEDIT_RANGE = (0.45, 0.85)

#: Views per editor call (a fixed batch: one compiled program).
CHUNK = 16


def psnr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """PSNR (dB) of images [..., H, W, 3] in [0, 1], over the last three axes."""
    mse = np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2, axis=(-3, -2, -1))
    return -10 * np.log10(np.maximum(mse, 1e-10))


def nearest(images: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For images [B, H, W, 3] and each one's outcomes targets [B, K, H, W, 3]: (index of the
    nearest outcome [B], PSNR to it [B], whether the outcomes' average is nearer [B])."""
    mse = np.mean((images[:, None] - targets) ** 2, axis=(-3, -2, -1))  # [B, K]
    k = np.argmin(mse, axis=1)
    best = mse[np.arange(len(k)), k]
    mean_mse = np.mean((images - targets.mean(1)) ** 2, axis=(-3, -2, -1))
    return k, -10 * np.log10(np.maximum(best, 1e-10)), mean_mse < best


def vae_roundtrip(editor, images: np.ndarray) -> np.ndarray | None:
    """float32 [B, H, W, 3]: images [B, H, W, 3] in [0, 1] through the editor's VAE alone
    (at its model size: encode, the posterior mean, decode, resized back), in chunks of
    CHUNK; None for an editor without one."""
    if not hasattr(editor, "nets") or not hasattr(editor, "model_hw"):
        return None
    from jaxedit.editors.jax_ip2p import decode, resize_images

    cfg, out = editor.config(), []
    hw = editor.model_hw(*images.shape[1:3])
    for lo in range(0, len(images), CHUNK):
        x = resize_images(jnp.asarray(images[lo:lo + CHUNK], jnp.float32), hw)
        mean, _ = editor.nets.vae.encode((x * 2 - 1).astype(cfg.dtype))
        y = decode(editor.nets.vae, mean.astype(jnp.float32) * cfg.scaling_factor, cfg)
        out.append(np.asarray(jnp.clip(resize_images(y, images.shape[1:3]), 0, 1)))
    return np.concatenate(out)


def vae_ceiling(editor, targets: np.ndarray) -> np.ndarray | None:
    """float [V]: about the most an edit decoded from the editor's latents can score against
    each view's outcome targets [V, K, H, W, 3]: each target's own VAE round trip against
    it, the best outcome's; None for an editor without a VAE."""
    flat = targets.reshape(-1, *targets.shape[2:])
    kept = vae_roundtrip(editor, flat)
    return None if kept is None else psnr(kept, flat).reshape(targets.shape[:2]).max(1)


def outcome_figures(images, originals, targets, views: Sequence[int] | None = None,
                    scenes: Sequence[str] | None = None) -> dict:
    """The outcome measure's figures (:mod:`.outcome_class`) of B edits: images, originals
    [B, H, W, 3], targets [B, K, H, W, 3]; with ``without_other_gate`` and the medians of the
    classification's ``progress`` and ``residual``. ``views`` (B, the view each edit is of)
    adds the intervals of a bootstrap over the views and ``view_spread`` (whether the outcome
    is the draw's or the view's); ``scenes`` (B names) adds the figures per scene
    (``per_scene``: pooled shares could hide a scene that always gets one outcome)."""
    k = targets.shape[1]
    full = [outcome_class.classify(x, u, t) for x, u, t in zip(images, originals, targets)]
    lean = [outcome_class.classify(x, u, t, other_gate=False)["label"]
            for x, u, t in zip(images, originals, targets)]
    labels = [c["label"] for c in full]
    out = outcome_class.summarise(labels, k, groups=views)
    if views is not None:
        out["view_spread"] = outcome_class.view_spread(labels, views, k)
    if scenes is not None:
        out["per_scene"] = {name: outcome_class.summarise(
            [x for x, s in zip(labels, scenes) if s == name], k) for name in dict.fromkeys(scenes)}
    out["without_other_gate"] = outcome_class.summarise(lean, k)
    out["progress_median"] = float(np.median([c["progress"] for c in full]))
    out["residual_median"] = float(np.median([c["residual"] for c in full]))
    return out


def band_figures(images, originals, targets) -> dict:
    """Where B edits' change lies against the outcome each leans to (its largest weight in
    :func:`outcome_class.classify`): images, originals [B, H, W, 3], targets [B, K, H, W, 3].

    Medians over the edits of ``outside_band`` (the share of the change's energy on pixels
    that outcome leaves alone: 0 for the target itself), ``gain_in_band`` (the change's
    RMS over the outcome's on the pixels it changes: 1 at the target's strength) and
    ``cosine_in_band`` (the change's direction against the outcome's there)."""
    outside, gain, cosine = [], [], []
    for x, u, t in zip(images, originals, targets):
        weights = outcome_class.classify(x, u, t, other_gate=False)["weights"]
        d, want = x - u, t[int(np.argmax(weights))] - u
        band = np.abs(want).sum(-1) > BAND_CHANGE
        energy = (d ** 2).sum(-1)
        outside.append(energy[~band].sum() / max(energy.sum(), 1e-12))
        inside, wanted = d[band], want[band]
        gain.append(np.sqrt((inside ** 2).sum() / (wanted ** 2).sum()))
        cosine.append((inside * wanted).sum()
                      / max(np.sqrt((inside ** 2).sum() * (wanted ** 2).sum()), 1e-12))
    return {"outside_band": float(np.median(outside)), "gain_in_band": float(np.median(gain)),
            "cosine_in_band": float(np.median(cosine))}


#: A pixel is in an outcome's band when the outcome changes it by more than this (the sum of
#: |change| over RGB in [0, 1]): well above the uint8 targets' rounding.
BAND_CHANGE = 0.02


def run_edits(editor, images: np.ndarray, originals: np.ndarray, embeddings: np.ndarray,
              key: jax.Array, t: float, guidance=None) -> np.ndarray:
    """Edit B views (images, originals [B, H, W, 3]; embeddings [B, L, D]) at T = t, in
    chunks of CHUNK (the last one padded), each view with its own key, at ``guidance`` (None:
    the editor's own): float32 [B, H, W, 3]."""
    b = len(images)
    keys = jax.random.split(key, b)
    out = []
    for lo in range(0, b, CHUNK):
        idx = np.minimum(np.arange(lo, lo + CHUNK), b - 1)
        edited = editor.edit_many(jnp.asarray(images[idx]), jnp.asarray(originals[idx]),
                                  jnp.asarray(embeddings[idx]), keys[idx],
                                  timestep_range=(t, t), guidance=guidance)
        out.append(np.asarray(edited)[: min(CHUNK, b - lo)])
    return np.concatenate(out)


def _views_of(data: EditDataset, i: int, views: Sequence[int]) -> list[int]:
    ins = data.instructions[i]
    return [int(v) for v in views if ins.applies_to(data.scenes[data.scene[v]])]


def _scene_means(data: EditDataset, views: Sequence[int], values) -> dict[str, float]:
    """{scene: mean of ``values`` over that scene's views alone} (values [V], one per entry
    of ``views``, a view possibly repeated: one per draw)."""
    scene, values = data.scene[np.asarray(views)], np.asarray(values)
    return {data.scenes[s]: float(np.mean(values[scene == s])) for s in np.unique(scene)}


def _identity_per_scene(data: EditDataset, views: Sequence[int], inputs: np.ndarray,
                        identity: dict, roundtrip: np.ndarray) -> dict:
    """{scene: {"identity_psnr_db": {T: dB}, "vae_roundtrip_psnr_db": dB}} over ``views``
    (inputs, each identity[T] and roundtrip [V, H, W, 3] in the same order)."""
    at_t = {f"{t:g}": _scene_means(data, views, psnr(x, inputs)) for t, x in identity.items()}
    kept = _scene_means(data, views, psnr(roundtrip, inputs))
    return {name: {"identity_psnr_db": {t: by[name] for t, by in at_t.items()},
                   "vae_roundtrip_psnr_db": kept[name]} for name in kept}


def evaluate(editor, data: EditDataset, views: Sequence[int], key: jax.Array, *,
             distance: Callable | None = None, draws: int = 4, t_full: float = 0.98,
             hold_views: int = 16, interp_views: int = 8,
             ratios: Sequence[float] = tuple(np.linspace(0, 1, 9)),
             guidance: tuple[float, float] | None = None,
             log: Callable[[str], None] = lambda s: None) -> dict:
    """All the figures of the module docstring, over the held-out ``views`` (rows of
    ``data.inputs``), every edit at ``guidance`` (text, image; None: the editor's own, as
    a run uses it). ``distance(a, b) -> float`` is the difficulty's (interpolation only;
    None skips it)."""
    guidance = editor_guidance(editor, guidance)
    inputs = data.inputs.astype(np.float32) / 255
    null = editor.encode("")
    counter = iter(range(1 << 30))

    def edits(images, originals, embedding_list, t):
        return run_edits(editor, images, originals, np.stack(embedding_list),
                         jax.random.fold_in(key, next(counter)), t, guidance)

    result: dict = {"t_full": t_full, "draws": draws, "views": len(views),
                    "guidance": list(guidance), "instructions": {}}
    vs_all = list(views)
    identity = {}
    for t in (*SDEDIT_RANGE, t_full):
        identity[t] = edits(inputs[vs_all], inputs[vs_all], [null] * len(vs_all), t)
    ident = identity[t_full]
    result["identity_psnr"] = float(np.mean(psnr(ident, inputs[vs_all])))  # at t_full
    result["identity_psnr_db"] = {f"{t:g}": float(np.mean(psnr(x, inputs[vs_all])))
                                  for t, x in identity.items()}
    result["identity_t098_psnr_db"] = result["identity_psnr_db"].get("0.98")
    roundtrip = vae_roundtrip(editor, inputs[vs_all])
    result["vae_roundtrip_psnr_db"] = None if roundtrip is None else \
        float(np.mean(psnr(roundtrip, inputs[vs_all])))
    if roundtrip is not None:
        result["identity_per_scene"] = _identity_per_scene(data, vs_all, inputs[vs_all],
                                                           identity, roundtrip)
    log(f"identity (dB) {result['identity_psnr_db']}, VAE round trip "
        f"{result['vae_roundtrip_psnr_db']}")
    at = {v: j for j, v in enumerate(vs_all)}

    for i, ins in enumerate(data.instructions):
        vs = _views_of(data, i, views)
        if not vs:
            continue
        e = editor.encode(ins.prompt)
        k_out = len(ins.outcomes)
        n = draws if k_out > 1 else max(1, draws // 2)
        rows = [v for v in vs for _ in range(n)]
        out = edits(inputs[rows], inputs[rows], [e] * len(rows), t_full)
        targets = np.stack([outcome_targets(data, v, i) for v in rows])  # [B, K, H, W, 3]
        which, best_psnr, mixed = nearest(out, targets)
        input_psnr = nearest(inputs[rows], targets)[1]
        per_scene = {"psnr": _scene_means(data, rows, best_psnr),
                     "psnr_unedited": _scene_means(data, rows, input_psnr)}
        one = np.stack([outcome_targets(data, v, i) for v in vs])  # [V, K, H, W, 3]
        if roundtrip is not None:  # the input through the autoencoder: what keeping it costs
            per_scene["psnr_vae_roundtrip"] = _scene_means(
                data, rows, nearest(roundtrip[[at[v] for v in rows]], targets)[1])
            # The target through it: about the most an edit can score (an input above it stays).
            per_scene["psnr_ceiling"] = _scene_means(data, vs, vae_ceiling(editor, one))
        entry = {"kind": ins.kind, "outcomes": list(ins.outcomes), "views": len(vs),
                 "edits": len(rows), "psnr": float(np.mean(best_psnr)),
                 "psnr_unedited": float(np.mean(input_psnr)),
                 "per_scene": {name: {k: by[name] for k, by in per_scene.items()}
                               for name in per_scene["psnr"]}}
        if k_out > 1:
            figures = outcome_figures(out, inputs[rows], targets, views=rows,
                                      scenes=[data.scenes[data.scene[v]] for v in rows])
            # Beside the edits' per-scene PSNRs, their outcomes per scene.
            for name, by_scene in figures.pop("per_scene").items():
                entry["per_scene"][name]["outcomes"] = by_scene
            entry.update(figures)
            rows_at = [at[v] for v in vs]
            entry["baseline"] = {
                "input": outcome_figures(inputs[vs], inputs[vs], one),
                "identity_edit": outcome_figures(ident[rows_at], inputs[vs], one)}
            if roundtrip is not None:
                entry["baseline"]["vae_roundtrip"] = outcome_figures(roundtrip[rows_at],
                                                                     inputs[vs], one)
            u_which, _, u_mixed = nearest(inputs[vs], one)
            entry["nearest_target"] = {
                "frequencies": [float(np.mean(which == k)) for k in range(k_out)],
                "mixing": float(np.mean(mixed)),
                "unedited_input": {"frequencies": [float(np.mean(u_which == k))
                                                   for k in range(k_out)],
                                   "mixing": float(np.mean(u_mixed))}}
            if hold_views:
                entry["holding"] = holding(edits, inputs, data, i, vs[:hold_views], e, null)
        if distance is not None:
            entry["interpolation"] = _interpolation(edits, inputs, vs[:interp_views], e, null,
                                                    ratios, distance, t_full)
        result["instructions"][ins.prompt] = entry
        log(f"{ins.prompt}: {entry['psnr']:.2f} dB"
            + (f", unedited {entry['unedited_fraction']:.2f}, of the edited: one outcome "
               f"{entry['single_outcome_fraction']}, outcomes {entry['outcome_frequencies']}, "
               f"mixed {entry['mixed_fraction']}, other {entry['other_fraction']}"
               if k_out > 1 else ""))
    return result


def holding(edits, inputs, data, i, vs, e, null) -> dict:
    """P(stay in c) from a view halfway into outcome c, per T and step (see the docstring):
    ``edits(images, originals, embeddings, t)`` edits, ``vs`` the views, ``e`` and ``null``
    instruction ``i``'s embedding and E("")."""
    k_out = len(data.instructions[i].outcomes)
    start, targets, wanted = [], [], []
    for v in vs:
        outs = outcome_targets(data, v, i)
        for c in range(k_out):
            start.append(0.5 * inputs[v] + 0.5 * outs[c])
            targets.append(outs)
            wanted.append(c)
    start, targets, wanted = np.stack(start), np.stack(targets), np.asarray(wanted)
    originals = np.stack([inputs[v] for v in vs for _ in range(k_out)])
    out = {}
    for t in (0.45, 0.85):
        for name, ratio in (("small_step", 0.625), ("jump", 1.0)):
            emb = interpolate_embedding(e, null, ratio)
            edited = edits(start, originals, [emb] * len(start), t)
            out[f"t{t}_{name}"] = float(np.mean(nearest(edited, targets)[0] == wanted))
    return out


def _interpolation(edits, inputs, vs, e, null, ratios, distance, t) -> list[list[float]]:
    """[[r, mean d(input, edit with e(r))]] over ``vs``."""
    curve = []
    for r in ratios:
        emb = interpolate_embedding(e, null, float(r))
        edited = edits(inputs[vs], inputs[vs], [emb] * len(vs), t)
        curve.append([float(r), float(np.mean([distance(inputs[v], x)
                                               for v, x in zip(vs, edited)]))])
    return curve
