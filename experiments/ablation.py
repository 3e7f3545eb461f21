"""``python -m experiments ablation``: ProEdit vs its controls as paired statistics over seeds.

With the simulated editor (a test instrument whose noise-free targets are known; not
InstructPix2Pix) on built-in scenes: make each scene's dataset and reconstruct it once, then
edit the reconstruction with every method, for every instruction, for every seed, and for every
editor variant. An editor variant (``--variants``) is ``K`` or ``K:GAIN``: K divergent modes per
instruction and the mode draw's ``mode_step_gain`` (default 1; see
:mod:`jaxedit.edit.simulated`, section 4). The mechanism test is variant ``3``; ``1`` (one
outcome: nothing to keep consistent) and ``3:0`` (holding a mode does not depend on the step
size) are the negative controls, run with ``--control-methods``.

Methods (rows), every one with the same trainer, W, patience, ``edit_every``, ``refine_every``
and a step guard of at least 3 x ``refine_every`` (so adaptive density control runs in every
subtask of every method):

- ``proedit``: the difficulty-aware schedule, ``target_subtasks`` by instruction kind
  (:data:`TARGET_SUBTASKS`: about 8 for geometry, 4 otherwise, the paper's figures);
- ``nd``: no decomposition, one edit subtask 0 -> 1 with its own plateau and guard;
- ``nd_equal``: ND with ProEdit's steps (r0 / the sum of ProEdit's edit subtasks / rn, the same
  seed) AND ProEdit's training editor calls (``edit_every`` chosen to match them);
- ``nd_k``: ProEdit's n edit subtasks all at r = 1, each as long as ProEdit's: the same opacity
  resets, initial sweeps, steps and editor calls, only the ratios differ (progression itself);
- ``uniform``: n uniform ratios i / n (ProEdit's n), plateau and guard as ProEdit's (does the
  difficulty-aware placement matter);
- ``in2n``: IN2N on 3DGS, ProEdit's total step count, one view every ``edit_every`` steps.

Scores at the held-out views (:func:`jaxedit.metrics.mode_scores`): ``psnr_best`` (best over modes
of the PSNR against the mode's noise-free target at r = 1), ``mode_mixing`` (0: one mode, 1: an
even blend), ``multiview_consistency``. Per run also: ``editor_calls`` (training edits; the
schedule's difficulty calls separately as ``schedule_calls``), ``sweeps`` (complete passes over
the views), ``total_steps``, ``guard_ended`` (subtasks the step guard, not the plateau, ended),
``maintenance`` (density-control steps), ``agreement`` (per sweep, the fraction of views whose
drawn mode is the sweep's most common one; ``agreement_final`` the last sweep's).

Writes ``RUN_DIR/ablation.json``::

    {"settings": {...}, "runs": [one record per (variant, scene, prompt, seed, method)],
     "summary": [{"editor_modes" (the variant), "scene", "prompt", "method", "metric",
                  "mean", "ci", "low", "high", "n"}],   # Student-t 95% CI over seeds
     "differences": [{..., "method": other, ...}]}     # proedit - other, paired t 95% CI,
                                                        # paired by (scene, instruction, seed)

(``prompt`` "all" averages the instructions per seed first), ``RUN_DIR/ablation.md`` and
``RUN_DIR/views/*.png`` (seed 0). The file is rewritten after every run; a run with the same
settings resumes from it.

Cost. The defaults (face, 20 px, 6 + 2 views; texture and shape; 20 seeds; variant 3 with five
methods, 1 and 3:0 with proedit and nd) are 360 edit runs, about 8 s each for texture and 13 s
for shape on the shared 2-core machine: 43 minutes of wall time with the gain-0 control in a
second process (the record ``benchmarks/results/cpu/mechanism_ablation.json``; README, "What
the mechanism test shows").
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

HELP = ("ablation: proedit vs nd, nd at equal steps and calls, nd-k, uniform and in2n over "
        "seeds, with paired 95-percent confidence intervals (simulated editor)")

METHODS = ("proedit", "nd", "nd_equal", "nd_k", "uniform", "in2n")
#: The default rows of the mechanism variant (in2n, one more trainer compile and no
#: schedule, is asked for with --methods).
MAIN_METHODS = ("proedit", "nd", "nd_equal", "nd_k", "uniform")
#: Methods that take ProEdit's run of the same seed as their budget.
FOLLOWERS = ("nd_equal", "nd_k", "uniform", "in2n")
SCENES = ("face",)
PROMPTS = ("give him a marble texture", "make his head bigger")
VARIANTS = ("3", "1", "3:0")
CONTROL_METHODS = ("proedit", "nd")
#: ProEdit's subtask count by instruction kind (paper: ~8 for geometry, ~4 for texture edits).
TARGET_SUBTASKS = {"shape": 8}
TARGET_SUBTASKS_DEFAULT = 4
#: Metrics summarised with confidence intervals.
METRICS = ("psnr_best", "ssim_best", "mode_mixing", "agreement_final", "multiview_consistency",
           "psnr_vs_target", "total_steps", "editor_calls", "sweeps", "guard_ended",
           "maintenance", "cpu_seconds")
ALL = "all"


def _csv(text: str) -> list[str]:
    return [t.strip() for t in str(text).split(",") if t.strip()]


def parse_variant(text: str) -> tuple[int, float]:
    """``"K"`` or ``"K:GAIN"`` -> (modes, mode_step_gain); a DataError otherwise."""
    from jaxedit import DataError
    from jaxedit.edit.simulated import MAX_MODES

    parts = str(text).split(":")
    try:
        modes, gain = int(parts[0]), (float(parts[1]) if len(parts) == 2 else 1.0)
    except (ValueError, IndexError):
        modes, gain = 0, -1.0
    if len(parts) > 2 or not 1 <= modes <= MAX_MODES or not gain >= 0:
        raise DataError("--variants", f"expected K or K:GAIN with K in 1..{MAX_MODES} and "
                                      f"GAIN >= 0 (like 3,1,3:0), got {text!r}")
    return modes, gain


def add_arguments(p) -> None:
    p.add_argument("--scenes", default=",".join(SCENES),
                   help="comma-separated built-in scenes (jaxedit.scenes.list_scenes())")
    p.add_argument("--prompts", default=",".join(PROMPTS),
                   help="comma-separated instructions of the simulated editor")
    p.add_argument("--seeds", type=int, default=20, help="seeds per instruction (0 .. N-1)")
    p.add_argument("--variants", default=",".join(VARIANTS),
                   help="comma-separated editor variants K or K:GAIN (modes, mode_step_gain); "
                        "the first runs --methods, the others --control-methods")
    p.add_argument("--methods", default=",".join(MAIN_METHODS),
                   help="rows of the first variant: " + ", ".join(METHODS)
                        + " (all but nd follow proedit's budget, so need proedit)")
    p.add_argument("--control-methods", default=",".join(CONTROL_METHODS),
                   help="rows of the other variants (the negative controls)")
    p.add_argument("--size", type=int, default=20, help="image size in pixels")
    p.add_argument("--views", type=int, default=6, help="training views")
    p.add_argument("--test-views", type=int, default=2, help="held-out views (scored)")
    p.add_argument("--recon-iters", type=int, default=400, help="reconstruction steps")
    p.add_argument("--refine-every", type=int, default=10,
                   help="density-control period of the editing trainer (steps)")
    p.add_argument("--max-steps", type=int, default=30,
                   help="per-subtask step guard (at least 3 x --refine-every)")
    p.add_argument("--warmup", type=int, default=4, help="W after each opacity reset")
    p.add_argument("--patience", type=int, default=6, help="plateau length ending a subtask")
    p.add_argument("--edit-every", type=int, default=3, help="steps between edits")
    p.add_argument("--lr-sh-dc", type=float, default=0.025,
                   help="colour learning rate of the editing trainer (same for every method)")
    p.add_argument("--smoke", action="store_true", help="tiny sizes (CI): seconds, not minutes")


def smoke_overrides() -> dict:
    """Tiny sizes for CI: one instruction, two seeds, the mechanism variant and one control,
    no in2n (one more trainer compile)."""
    return dict(scenes=("ball",), prompts=("make it look like autumn",), seeds=2,
                variants=("3", "3:0"), methods=("proedit", "nd", "nd_equal", "nd_k"),
                control_methods=("proedit", "nd"), size=16, views=4, test_views=2,
                recon_iters=30, refine_every=4, max_steps=12, warmup=2, patience=3,
                edit_every=2)


def stamp_prepared(out: Path, wanted: dict) -> None:
    """:func:`jaxedit.pipelines.cache.stamp_prepared` (kept here for this module's callers)."""
    from jaxedit.pipelines.cache import stamp_prepared as stamp

    stamp(out, wanted)


def prepare(out: Path, *, scene_name: str, size: int, views: int, test_views: int,
            recon_iters: int, seed: int, log=print):
    """(EditData, reconstructed Gaussians, recon metrics): dataset + reconstruction, cached on disk."""
    from jaxedit.edit import EditData
    from jaxedit.io import load_nerfstudio, load_ply
    from jaxedit.pipelines.reconstruct import reconstruct
    from jaxedit.scenes import make_scene
    from jaxedit.train import DensifyConfig, TrainConfig

    data_dir, recon_dir = out / "data", out / "recon"
    wanted = {"scene": scene_name, "size": size, "views": views, "test_views": test_views,
              "recon_iters": recon_iters, "seed": seed}
    stamp_prepared(out, wanted)
    if not (data_dir / "transforms.json").exists():
        log(f"making the {scene_name} scene ({views}+{test_views} views, {size}px)")
        make_scene(scene_name, data_dir, size=size, views=views, test_views=test_views, seed=seed)
    dataset = load_nerfstudio(data_dir)
    if not (recon_dir / "scene.ply").exists():
        log(f"reconstructing {scene_name} ({recon_iters} steps)")
        dens = DensifyConfig(refine_every=100, warmup=min(500, recon_iters // 5),
                             reset_every=max(recon_iters // 2, 1), max_gaussians=50_000)
        config = TrainConfig(iterations=recon_iters, sh_degree=1, sh_degree_interval=max(
            recon_iters // 4, 1), densify=dens)
        reconstruct(dataset, recon_dir, config, seed=seed, checkpoint_every=0)
    recon = json.loads((recon_dir / "metrics.json").read_text())
    return EditData.from_dataset(dataset), load_ply(recon_dir / "scene.ply"), recon


# ---------------------------------------------------------------------------
# Statistics (pure)
# ---------------------------------------------------------------------------
def _values(runs, *, prompts, method, metric, seeds) -> list[float] | None:
    """Per-seed values of one scene and editor setting, averaged over ``prompts`` (one prompt,
    or the complete ones for "all"); None if a seed lacks any of them."""
    out = []
    for seed in seeds:
        vals = [r[metric] for r in runs if r["method"] == method and r["seed"] == seed
                and r["prompt"] in prompts and r.get(metric) is not None]
        if len(vals) != len(prompts):
            return None
        out.append(sum(vals) / len(vals))
    return out


def summarise(runs: list[dict]) -> tuple[list[dict], list[dict]]:
    """(summary rows, paired-difference rows) of the run records; see the module docstring."""
    from jaxedit.metrics import mean_ci, paired_differences

    summary, differences = [], []
    groups = sorted({(r["editor_modes"], r["scene"]) for r in runs})
    for modes, scene in groups:
        mine = [r for r in runs if r["editor_modes"] == modes and r["scene"] == scene]
        prompts = list(dict.fromkeys(r["prompt"] for r in mine))
        methods = [m for m in METHODS if any(r["method"] == m for r in mine)]
        seeds = sorted({r["seed"] for r in mine})
        # An interrupted run has a partial last instruction: each row uses the seeds that
        # every method finished (so differences stay paired), "all" the complete instructions.
        done = {(r["prompt"], r["seed"]) for r in mine
                if all(any(q["prompt"] == r["prompt"] and q["seed"] == r["seed"]
                           and q["method"] == m for q in mine) for m in methods)}
        finished = {p: [sd for sd in seeds if (p, sd) in done] for p in prompts}
        complete = [p for p in prompts if len(finished[p]) == len(seeds)]
        for prompt in prompts + ([ALL] if len(complete) > 1 else []):
            over = complete if prompt == ALL else [prompt]
            use = seeds if prompt == ALL else finished[prompt]
            if not use:
                continue
            for metric in METRICS:
                base = None
                for method in methods:
                    vals = _values(mine, prompts=over, method=method, metric=metric, seeds=use)
                    if vals is None:
                        continue
                    key = {"editor_modes": modes, "scene": scene, "prompt": prompt,
                           "method": method, "metric": metric}
                    summary.append(key | mean_ci(vals))
                    if method == "proedit":
                        base = vals
                    elif base is not None:
                        differences.append(key | paired_differences(base, vals))
    return summary, differences


def tables(summary: list[dict], differences: list[dict], *,
           metrics=("psnr_best", "mode_mixing", "multiview_consistency")) -> str:
    """Markdown: per editor-modes setting and metric, (scene, instruction) x methods with
    mean ± 95% CI, then the paired differences proedit - other (``*``: CI excludes 0)."""
    from jaxedit.pipelines.report import ablation_table

    text = []
    for modes in sorted({r["editor_modes"] for r in summary}):
        for metric in metrics:
            digits = 3 if metric.startswith(("ssim", "mode")) else 2
            header, rows = ablation_table(summary, differences, editor_modes=modes,
                                          metric=metric, digits=digits)
            text.append(f"\n### editor modes = {modes}: {metric} (mean ± 95% CI over seeds)\n")
            text.append("| " + " | ".join(header) + " |")
            text.append("|" + "---|" * len(header))
            text += ["| " + " | ".join(row) + " |" for row in rows]
    text.append("\n`*`: the 95% CI of the paired difference excludes 0.")
    return "\n".join(text) + "\n"


# ---------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------
def _score(editor, prompt, data, gaussians, background) -> tuple[dict, object, object]:
    """(mode scores, renders [N, H, W, 3], mode targets [K, N, H, W, 3]) at the test views."""
    import numpy as np

    from jaxedit.edit.outputs import Renderer
    from jaxedit.metrics import mode_scores

    renderer = Renderer(background)
    rgb = np.stack([renderer.rgb(gaussians, data.test_cameras[i])
                    for i in range(len(data.test_images))])
    targets = np.stack([editor.mode_targets(o, 1.0, prompt) for o in data.test_images], axis=1)
    return mode_scores(rgb, targets), rgb, targets


def _write_views(path: Path, targets, renders: dict) -> None:
    """One PNG: a row per mode target, then a row per method's final test views."""
    import numpy as np

    from jaxedit.io import write_image
    from jaxedit.viz import image_grid

    rows = list(targets) + [renders[m] for m in renders]
    grid = image_grid(np.concatenate(rows), ncols=len(rows[0]))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.ascontiguousarray(np.clip(grid, 0.0, 1.0)))


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text.lower()).strip("_")[:40]


def edits_per_subtask(steps: int, *, warmup: int, every: int, views: int,
                      initial_sweep: bool) -> int:
    """Training edits of a deterministic subtask of ``steps`` steps: the driver exchanges with
    the editor at steps s >= W with (s - W) % every == 0 and s < steps
    (:class:`jaxedit.edit.buffer.SyncEditSource` decides how many views each exchange edits)."""
    from jaxedit.edit.buffer import SyncEditSource

    source = SyncEditSource(lambda job, scene: None, list(range(views)), every=every,
                            initial_sweep=initial_sweep)
    return sum(len(source.jobs_at(s)) for s in range(0, max(steps - warmup, 0), every))


def sweep_agreement(modes, edits: list[int], views: int) -> list[list[float]]:
    """Per subtask, per complete sweep (``views`` consecutive edits: every view once), the
    fraction of views drawn in the sweep's most common mode. ``modes`` int [sum(edits)] in
    the order the edits were made, ``edits`` the count of each subtask."""
    import numpy as np

    modes = np.asarray(modes, int)
    if len(modes) != sum(edits):
        raise ValueError(f"{len(modes)} recorded modes for {sum(edits)} edits")
    out, at = [], 0
    for count in edits:
        sub = modes[at:at + count]
        at += count
        out.append([float(np.bincount(sub[i:i + views]).max()) / views
                    for i in range(0, count - views + 1, views)])
    return out


def match_edit_every(target_edits: int, steps: list[int], *, warmup: int, views: int,
                     most: int) -> int:
    """The ``edit_every`` (1 .. most) whose training edits over subtasks of ``steps`` come
    closest to ``target_edits`` (ties: the larger, fewer exchanges)."""
    def edits(every):
        return sum(edits_per_subtask(s, warmup=warmup, every=every, views=views,
                                     initial_sweep=True) for s in steps)
    return min(range(1, most + 1), key=lambda e: (abs(edits(e) - target_edits), -e))


class ModeLog:
    """An editor that remembers the mode of every ``edit`` call (the mode draw is the
    simulated editor's :meth:`edit_with_mode`); everything else is the editor's."""

    def __init__(self, editor):
        self.editor = editor
        self.modes: list[int] = []

    def __getattr__(self, name):
        return getattr(self.editor, name)

    def edit(self, image, original, embedding, key, **kwargs):
        out, mode = self.editor.edit_with_mode(image, original, embedding, key, **kwargs)
        self.modes.append(mode)
        return out


def method_config(method: str, *, kind: str, lead: dict | None, warmup: int, patience: int,
                  max_steps: int, edit_every: int, views: int):
    """The :class:`ProEditConfig` of ``method``; ``lead`` is ProEdit's run of the same seed
    ({"steps": per subtask, "edits": training edits, "horizon": its annealing horizon})."""
    from jaxedit.edit.plan import ProEditConfig

    # the difficulty over 3 views and no plotted curve: the schedule's editor calls are
    # bookkeeping here, not part of any method's training budget
    common = dict(max_steps=max_steps, patience=patience, edit_every=edit_every,
                  asynchronous=False, difficulty_views=3, curve_points=2)
    if method == "proedit":
        return ProEditConfig.for_mode("proedit", warmup=warmup, target_subtasks=TARGET_SUBTASKS.get(
            kind, TARGET_SUBTASKS_DEFAULT), **common)
    if method == "nd":
        return ProEditConfig.for_mode("nd", warmup=warmup, **common)
    steps, n = lead["steps"], len(lead["steps"]) - 2  # r0, n edit subtasks, rn
    if method == "uniform":
        return ProEditConfig.for_mode("proedit", warmup=warmup, subtasks=n, **common)
    if method == "in2n":
        return ProEditConfig.for_mode("in2n", max_steps=sum(steps), patience=patience,
                                      edit_every=edit_every, asynchronous=False, curve_points=2)
    fixed = dict(common, anneal_steps=lead["horizon"])
    if method == "nd_k":
        return ProEditConfig.for_mode("nd", warmup=warmup, nd_subtasks=n,
                                      subtask_steps=tuple(steps), **fixed)
    if method == "nd_equal":
        lengths = (steps[0], sum(steps[1:-1]), steps[-1])
        every = match_edit_every(lead["edits"], list(lengths), warmup=warmup, views=views,
                                 most=edit_every)
        return ProEditConfig.for_mode("nd", warmup=warmup, subtask_steps=lengths,
                                      **dict(fixed, edit_every=every))
    raise ValueError(method)


def _variant_label(modes: int, gain: float) -> str:
    return str(modes) if gain == 1.0 else f"{modes}:{gain:g}"


def run_ablation(out: Path, *, scenes=SCENES, prompts=PROMPTS, seeds=20, variants=VARIANTS,
                 methods=MAIN_METHODS, control_methods=CONTROL_METHODS, size=20, views=6,
                 test_views=2, recon_iters=400, refine_every=10, max_steps=30, warmup=4,
                 patience=6, edit_every=3, lr_sh_dc=0.025, recon_seed=0, report=True,
                 log=print) -> dict:
    """Run the ablation into ``out``; returns the contents of ablation.json."""
    from jaxedit import DataError
    from jaxedit.edit.plan import anneal_horizon
    from jaxedit.edit import TrainSettings
    from jaxedit.edit.simulated import VOCABULARY, SimulatedEditor
    from jaxedit.io.files import atomic_write_text
    from jaxedit.scenes import list_scenes

    out = Path(out)
    bad = [s for s in scenes if s not in list_scenes()]
    if bad or not scenes:
        raise DataError("--scenes", f"unknown scene(s) {bad}; built-in: {', '.join(list_scenes())}"
                        if bad else f"no scene given; built-in: {', '.join(list_scenes())}")
    for flag, rows in (("--methods", methods), ("--control-methods", control_methods)):
        bad = [m for m in rows if m not in METHODS]
        if bad or not rows:
            raise DataError(flag, f"unknown method(s) {bad}; choose from {', '.join(METHODS)}"
                            if bad else f"no method given; choose from {', '.join(METHODS)}")
        if any(m in FOLLOWERS for m in rows) and "proedit" not in rows:
            raise DataError(flag, f"{', '.join(FOLLOWERS)} take ProEdit's budget: include proedit")
    if seeds < 1:
        raise DataError("--seeds", f"must be >= 1, got {seeds}")
    if max_steps < 3 * refine_every:
        raise DataError("--max-steps", f"must be at least 3 x --refine-every ({refine_every}) so "
                                       f"density control runs in every subtask, got {max_steps}")
    parsed = [parse_variant(v) for v in variants]
    if not parsed:
        raise DataError("--variants", "need at least one editor variant")
    editors = {_variant_label(k, g): SimulatedEditor(modes=k, mode_step_gain=g) for k, g in parsed}
    rows_of = {label: [m for m in METHODS if m in (methods if i == 0 else control_methods)]
               for i, label in enumerate(editors)}
    first = next(iter(editors.values()))
    prompts = tuple(prompts) if prompts else first.instructions
    kinds = {}
    for p in prompts:
        try:
            first.encode(p)  # unknown instructions fail here
        except DataError as e:
            raise DataError("--prompts", e.problem) from None
        kinds[p] = VOCABULARY[first._index(p)].kind
    settings_json = {"scenes": list(scenes), "prompts": list(prompts), "seeds": seeds,
                     "variants": list(editors), "methods": rows_of, "size": size,
                     "views": views, "test_views": test_views, "recon_iters": recon_iters,
                     "refine_every": refine_every, "max_steps": max_steps, "warmup": warmup,
                     "patience": patience, "edit_every": edit_every, "lr_sh_dc": lr_sh_dc,
                     "recon_seed": recon_seed,
                     "target_subtasks": {k: TARGET_SUBTASKS.get(k, TARGET_SUBTASKS_DEFAULT)
                                         for k in sorted(set(kinds.values()))}}
    out.mkdir(parents=True, exist_ok=True)
    path = out / "ablation.json"
    runs: list[dict] = []
    if path.exists():
        old = json.loads(path.read_text())
        if isinstance(old, dict) and old.get("settings") == settings_json:
            runs = list(old.get("runs", []))
            log(f"resuming: {len(runs)} finished runs in {path}")
    elapsed0 = sum(r.get("seconds", 0.0) for r in runs)

    def save(extra=None):
        payload = {"settings": settings_json, "runs": runs} | (extra or {})
        atomic_write_text(path, json.dumps(payload, indent=2) + "\n")

    total = len(scenes) * len(prompts) * seeds * sum(len(r) for r in rows_of.values())
    t_start = time.perf_counter()
    for scene_name in scenes:
        data, scene, recon = prepare(out / scene_name, scene_name=scene_name, size=size,
                                     views=views, test_views=test_views,
                                     recon_iters=recon_iters, seed=recon_seed, log=log)
        settings = TrainSettings(lr_sh_dc=lr_sh_dc, sh_degree=scene.sh_degree
                                 ).replace_densify(refine_every=refine_every)
        n_views = len(data.train_images)
        for label, editor in editors.items():
            for prompt in prompts:
                for seed in range(seeds):
                    renders, lead = {}, None
                    for method in rows_of[label]:
                        tag = (label, scene_name, prompt, seed, method)
                        prior = next((r for r in runs if (r["editor_modes"], r["scene"],
                                                          r["prompt"], r["seed"],
                                                          r["method"]) == tag), None)
                        if prior is None:
                            cfg = method_config(method, kind=kinds[prompt], lead=lead,
                                                warmup=warmup, patience=patience,
                                                max_steps=max_steps, edit_every=edit_every,
                                                views=n_views)
                            record, rgb, targets = _run_one(
                                ModeLog(editor), prompt, data, scene, cfg, settings, seed)
                            record.update(editor_modes=label, modes=editor.modes,
                                          step_gain=editor.params.mode_step_gain,
                                          scene=scene_name, prompt=prompt, kind=kinds[prompt],
                                          seed=seed, method=method)
                            runs.append(record)
                            renders[method] = rgb
                            save()
                            prior = record
                            log(f"[{len(runs)}/{total}] {label} {scene_name} {kinds[prompt]} "
                                f"seed {seed} {method}: psnr_best {record['psnr_best']:.2f}, "
                                f"mixing {record['mode_mixing']:.2f}, agreement "
                                f"{record['agreement_final']}, {record['total_steps']} steps, "
                                f"{record['editor_calls']} calls, "
                                f"{elapsed0 + time.perf_counter() - t_start:.0f} s so far")
                        if method == "proedit":
                            cfg = method_config("proedit", kind=kinds[prompt], lead=None,
                                                warmup=warmup, patience=patience,
                                                max_steps=max_steps, edit_every=edit_every,
                                                views=n_views)
                            lead = {"steps": prior["subtask_steps"],
                                    "edits": prior["editor_calls"],
                                    "horizon": anneal_horizon(cfg, warmup)}
                    if seed == 0 and renders:
                        _write_views(out / "views" / f"m{_slug(label)}_{scene_name}_"
                                     f"{_slug(prompt)}.png", targets, renders)
    summary, differences = summarise(runs)
    save({"summary": summary, "differences": differences,
          "wall_time_s": elapsed0 + time.perf_counter() - t_start})
    atomic_write_text(out / "ablation.md", "# Ablation (simulated editor)\n\n"
                      f"Settings: `{json.dumps(settings_json)}`\n" + tables(summary, differences))
    if report:
        from jaxedit.pipelines.report import write_report

        write_report(out)
    return {"settings": settings_json, "runs": runs, "summary": summary,
            "differences": differences}


def _run_one(editor: ModeLog, prompt, data, scene, cfg, settings, seed):
    """(record, test renders, mode targets) of one edit run."""
    t0, c0 = time.perf_counter(), time.process_time()
    from jaxedit.pipelines import run_edit

    res = run_edit(editor, prompt, data, scene, config=cfg, settings=settings, seed=seed,
                   run_dir=None, report=False)
    scores, rgb, targets = _score(editor.editor, prompt, data, res["gaussians"], cfg.background)
    m, subtasks = res["metrics"], res["schedule"]["subtasks"]
    n_views = len(data.train_images)
    warmup = 0 if cfg.mode == "in2n" else cfg.warmup
    edits = [edits_per_subtask(s["steps"], warmup=warmup, every=cfg.edit_every, views=n_views,
                               initial_sweep=cfg.initial_sweep) for s in subtasks]
    calls = int(m["utilisation"]["edits"])
    if sum(edits) != calls:
        raise RuntimeError(f"counted {sum(edits)} training edits, the driver made {calls}")
    agreement = sweep_agreement(editor.modes[len(editor.modes) - calls:], edits, n_views)
    sweeps = sum(len(a) for a in agreement)
    # the refine subtask edits with e(0): every mode's target is the original, its draws mean
    # nothing
    agreement = [[] if s["kind"] == "refine" else a for s, a in zip(subtasks, agreement)]
    flat = [a for sub in agreement for a in sub]
    return ({**scores, "psnr_vs_target": m.get("psnr_vs_target"),
             "multiview_consistency": m.get("multiview_consistency"),
             "total_steps": int(m["total_steps"]), "subtasks": len(subtasks),
             "subtask_steps": [int(s["steps"]) for s in subtasks],
             "ratios": [s["ratio"] for s in subtasks],
             "editor_calls": calls, "schedule_calls": len(editor.modes) - calls,
             "edits_per_subtask": edits, "edit_every": cfg.edit_every,
             "sweeps": sweeps,
             "guard_ended": sum(s["guard"] is not None for s in subtasks),
             "maintenance": sum(int(s["density"]["refinements"]) for s in subtasks),
             "agreement": agreement, "agreement_final": flat[-1] if flat else None,
             "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0},
            rgb, targets)


def run(args) -> dict:
    from jaxedit import DataError

    from experiments.cli import check_minimums

    if args.out is None:
        raise DataError("--out", "required (the ablation run directory)")
    check_minimums(args, {"size": 8, "views": 1, "test_views": 1, "recon_iters": 1,
                          "max_steps": 1, "warmup": 0, "patience": 1, "seeds": 1,
                          "refine_every": 1, "edit_every": 1})
    if not args.lr_sh_dc > 0:
        raise DataError("--lr-sh-dc", f"must be > 0, got {args.lr_sh_dc}")
    if not _csv(args.prompts):
        raise DataError("--prompts", f"no instruction given in {args.prompts!r} (leave the flag "
                                     f"out for all of them)")
    if args.smoke:
        # --smoke sets these itself: a value given beside it would be silently dropped.
        defaults = argparse.ArgumentParser()
        add_arguments(defaults)
        given = [f"--{k.replace('_', '-')}" for k in smoke_overrides()
                 if getattr(args, k) != defaults.get_default(k)]
        if given:
            raise DataError(given[0], f"--smoke sets {', '.join(given)} itself; give either "
                                      f"--smoke or {', '.join(given)}")
    kw = dict(scenes=tuple(_csv(args.scenes)), prompts=tuple(_csv(args.prompts)) or None,
              seeds=args.seeds, variants=tuple(_csv(args.variants)),
              methods=tuple(_csv(args.methods)), control_methods=tuple(_csv(args.control_methods)),
              size=args.size, views=args.views, test_views=args.test_views,
              recon_iters=args.recon_iters, refine_every=args.refine_every,
              max_steps=args.max_steps, warmup=args.warmup, patience=args.patience,
              edit_every=args.edit_every)
    if args.smoke:
        kw.update(smoke_overrides())
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    result = run_ablation(args.out, lr_sh_dc=args.lr_sh_dc, recon_seed=args.seed, log=log, **kw)
    return {f"m{r['editor_modes']} {r['scene']} {r['method']} {r['metric']}":
            round(r["mean"], 4) for r in result["summary"]
            if r["prompt"] in (ALL, result["settings"]["prompts"][0])
            and r["metric"] in ("psnr_best", "mode_mixing")
            and (r["prompt"] == ALL or len(result["settings"]["prompts"]) == 1)}
