"""The ablation: ProEdit vs its controls as paired statistics over seeds.

``python -m experiments ablation`` and ``benchmarks/ablation.py`` run :func:`run_ablation`
with an :class:`AblationConfig` (the command's flags are generated from its fields).

Make each built-in scene's dataset and reconstruct it once, then edit the reconstruction with
every method, for every instruction and every seed. Two editors (``editor``):

- ``ip2p``, the mechanism test: the bundled small InstructPix2Pix
  (:func:`jaxedit.editors.bundled_editor`, or the folder ``ip2p_weights``: the committed
  study's instrument is v1), whose outcomes, their separation and whether a view keeps one
  are the network's; one variant, its name, with ``methods``.
- ``simulated``, the test instrument (noise-free targets known; not InstructPix2Pix): an
  editor variant (``variants``) is ``K`` or ``K:GAIN``, K divergent modes per instruction and
  the mode draw's ``mode_step_gain`` (default 1; :mod:`jaxedit_lab.simulated`, section
  4). ``3`` runs ``methods``; ``1`` (one outcome: nothing to keep consistent) and ``3:0``
  (holding a mode does not depend on the step size) run ``control_methods``.

Methods (rows), every one with the same trainer, W, patience, ``edit_every``, ``refine_every``
and a step guard of at least 3 x ``refine_every`` (so adaptive density control runs in every
subtask of every method); :mod:`.methods` builds them:

- ``proedit``: the difficulty-aware schedule, ``target_subtasks`` by instruction kind
  (:data:`.methods.TARGET_SUBTASKS`: about 8 for geometry, 4 otherwise, the paper's figures);
- ``nd``: no decomposition, one edit subtask 0 -> 1 with its own plateau and guard;
- ``nd_equal``: ND with exactly ProEdit's steps (r0 / the sum of ProEdit's edit subtasks / rn,
  the same seed) and exactly its training editor calls, spread by a fractional schedule
  (:func:`.methods.fractional_exchanges`), not an integer ``edit_every``;
- ``nd_replay``: ProEdit's own exchanges (its sweeps, calls and timesteps, so as many
  hottest-timestep edits) replayed in one subtask at r = 1, without its opacity resets;
- ``nd_k``: ProEdit's n edit subtasks all at r = 1, each as long as ProEdit's: the same opacity
  resets, initial sweeps, steps and editor calls, only the ratios differ (progression itself);
- ``uniform``: n uniform ratios i / n (ProEdit's n), plateau and guard as ProEdit's (does the
  difficulty-aware placement matter); where ProEdit's own ratios are uniform, its run is
  reused (``same_run_as``: the same run bit for bit);
- ``in2n``: IN2N on 3DGS, ProEdit's total step count, one view every ``edit_every`` steps.

With ``references``, each (scene, instruction) also scores two reference levels in the same
run (``seed`` -1): the unedited reconstruction and the ceiling, the same trainer fitted
directly to each outcome's targets (the best outcome).

Scores at the held-out views (:func:`.outcomes.outcome_scores`): ``psnr_best`` (best over the
outcomes of the PSNR against the outcome's target), ``outcome_agreement`` (each view classified
to its nearest outcome target), ``mode_mixing`` (0: one outcome, 1: an even blend),
``multiview_consistency``. Per run also: ``plateau_share`` (of the subtasks that can plateau,
the share that ended on their loss plateau, not on the guard; ``guard_ended`` counts the
others; fixed-length subtasks, as ``nd_equal``'s, have none), ``editor_calls``
(training edits; the schedule's difficulty calls separately as ``schedule_calls``),
``hottest_calls`` (at the hottest timestep, t_max), ``calls_by_band`` (per timestep band,
:data:`.methods.BANDS` of them, band 0 the hottest), ``resets``, ``sweeps`` (complete passes
over the views), ``total_steps``, ``maintenance`` (density-control steps), ``agreement`` (the
simulated editor: per sweep, the fraction of views whose drawn mode is the sweep's most common
one), ``device`` (what ran it: a study may be run in parts, ``run_ablation(seeds=...)``, on
several machines). Every record names its ``scene``, ``prompt``, ``method``, ``seed``,
``recon_seed`` (the scene's and reconstruction's seed: ``recon_seed=`` here, ``--seed`` on
the command line, so a second reconstruction, or other views with ``views``/``test_views``,
is a study of its own) and ``editor_weights`` (the ip2p editor's UNet sha256, first 16
digits, also in the settings, so a study resumes only with its own weights; None for other
editors). ``edit_outcomes``: every training edit of the run, in
order, as ``{"subtask", "step" (from the subtask's start), "view", "t", "ratio",
"outcome"}``, ``outcome`` the class of the edited image against the view's photo and its
outcome targets (:mod:`jaxedit_lab.outcome_class`: the outcome's index, "unedited",
"mixed" or "other"; "undefined" where an outcome leaves the view as it is); ``edit_outcome_counts`` counts them. (The reference levels make no
editor calls: ``edit_outcomes`` is None.)

Writes ``RUN_DIR/ablation.json``::

    {"settings": {...}, "runs": [one record per (variant, scene, prompt, seed, method)],
     "summary": [{"editor_modes" (the variant), "scene", "prompt", "method", "metric",
                  "mean", "ci", "low", "high", "n"}],   # Student-t 95% CI over seeds
     "differences": [{..., "method": other, ...}]}     # proedit - other, paired t 95% CI,
                                                        # paired by (scene, instruction, seed)

(``prompt`` "all" averages the complete instructions per seed first) and
``RUN_DIR/ablation.md`` once the study ends, and ``RUN_DIR/views/*.png`` as seed 0's runs
end. Every run is appended to ``RUN_DIR/runs.jsonl`` as it ends, and a run with the same
settings resumes from it.

Cost. The bundled editor's study (``benchmarks/results/cpu/mechanism_ip2p/``: face, 48 px,
16 + 4 views, four instructions, six methods, 20 seeds) takes about 12 minutes of the 2-core
CPU per (instruction, seed), 16 hours in all, run in parts. The simulated defaults (face,
20 px, 6 + 2 views; texture and shape; 20 seeds; variant 3 with five methods, 1 and 3:0 with
proedit and nd) are 360 edit runs, 43 minutes of wall time (the old instrument's record
``benchmarks/results/cpu/mechanism_ablation.json``; README, "What the mechanism test shows").

Modules: :mod:`.methods` (the rows and their budgets), :mod:`.summary` (the statistics
and tables); this one holds the settings and the runs.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from jaxedit.edit import EditData, EditTrainConfig
from jaxedit.edit.outputs import Renderer
from jaxedit.edit.plan import anneal_horizon
from jaxedit.editors.diffusion import DDIM_STEPS
from jaxedit_lab import outcome_class
from jaxedit_lab.simulated import INSTRUCTIONS, SimulatedEditor
from jaxedit_lab.simulated_targets import MAX_MODES
from jaxedit.errors import DataError, check_ranges, ranged
from jaxedit.io import write_image
from jaxedit.io.files import atomic_write_text
from jaxedit.viz import image_grid
from jaxedit.pipelines.cache import prepared_scene
from jaxedit.pipelines.edit_run import run_edit
from jaxedit_lab.ablation.methods import (BANDS, CONTROL_METHODS, FOLLOWERS, MAIN_METHODS, METHODS, TARGET_SUBTASKS,
                      TARGET_SUBTASKS_DEFAULT, CallLog, edits_per_subtask,
                      method_config, periodic_exchanges, sweep_agreement, timestep_bands)
from jaxedit_lab.ablation.outcomes import FixedTargets, outcome_scores, outcome_targets
from jaxedit_lab.ablation.summary import ALL, METRICS, REFERENCES, summarise, tables

__all__ = ["ALL", "AblationConfig", "CONTROL_METHODS", "EDITORS", "MAIN_METHODS", "METHODS",
           "METRICS", "REFERENCES",
           "PROMPTS", "SCENES", "VARIANTS", "parse_variant", "recon_config", "run_ablation",
           "summarise", "tables"]

SCENES = ("face",)
#: Editors of the ablation: the simulated test instrument and the bundled InstructPix2Pix.
EDITORS = ("simulated", "ip2p")
PROMPTS = ("give him a marble texture", "make his head bigger")
VARIANTS = ("3", "1", "3:0")


def parse_variant(text: str) -> tuple[int, float]:
    """``"K"`` or ``"K:GAIN"`` -> (modes, mode_step_gain); a DataError naming ``variants``."""
    parts = str(text).split(":")
    try:
        modes, gain = int(parts[0]), (float(parts[1]) if len(parts) == 2 else 1.0)
    except (ValueError, IndexError):
        modes, gain = 0, -1.0
    if len(parts) > 2 or not 1 <= modes <= MAX_MODES or not gain >= 0:
        raise DataError("variants", f"expected K or K:GAIN with K in 1..{MAX_MODES} and "
                                    f"GAIN >= 0 (like 3,1,3:0), got {text!r}")
    return modes, gain


@dataclasses.dataclass(frozen=True)
class AblationConfig:
    """The ablation's settings (the defaults are the committed mechanism ablation's).

    Attributes:
      scenes: built-in scenes (jaxedit.scenes.list_scenes()).
      prompts: instructions of the simulated editor.
      seeds: seeds per instruction (0 .. N-1).
      variants: editor variants K or K:GAIN (modes, mode_step_gain); the first runs
        methods, the others control_methods.
      methods: rows of the first variant: proedit, nd, nd_equal, nd_replay, nd_k, uniform,
        in2n (all but nd follow proedit's budget, so need proedit).
      control_methods: rows of the other variants (the negative controls).
      size: image size in pixels.
      views: training views.
      test_views: held-out views (scored).
      recon_iters: reconstruction steps.
      refine_every: density-control period of the editing trainer (steps).
      max_steps: per-subtask step guard (at least 3 x refine_every, so density control
        runs in every subtask of every method).
      warmup: W after each opacity reset.
      patience: plateau length ending a subtask.
      edit_every: steps between edits.
      lr_sh_dc: colour learning rate of the editing trainer (same for every method).
      editor: "simulated" (the test instrument, its variants) or "ip2p" (the bundled small
        InstructPix2Pix, :func:`jaxedit.editors.bundled_editor`, at its own size; one
        variant, ``methods`` only).
      ip2p_steps: DDIM steps per edit of the bundled editor (its 10-step edits are within
        37-40 dB PSNR of its 20-step ones on held-out views, at half the cost).
      ip2p_weights: the ip2p editor's diffusers folder (None: the bundled one); it edits
        at the guidance its folder recommends. The committed study's instrument is the
        first bundled model, v1 (``docs/mechanism.md`` says how to get it back).
      references: also score the reference levels of each (scene, instruction): the
        unedited reconstruction and the ceiling (a scene trained directly on one outcome's
        targets, the best of its outcomes).
      points: points in the initial cloud of each procedural scene (unset: the scene's own
        4000; fewer make every training step cheaper at small sizes); rendered scenes bring
        their own.
    """

    scenes: tuple[str, ...] = SCENES
    prompts: tuple[str, ...] = PROMPTS
    seeds: int = ranged(20, low=1)
    variants: tuple[str, ...] = VARIANTS
    methods: tuple[str, ...] = MAIN_METHODS
    control_methods: tuple[str, ...] = CONTROL_METHODS
    size: int = ranged(20, low=8)
    views: int = ranged(6, low=1)
    test_views: int = ranged(2, low=1)
    recon_iters: int = ranged(400, low=1)
    refine_every: int = ranged(10, low=1)
    max_steps: int = ranged(30, low=1)
    warmup: int = ranged(4, low=0)
    patience: int = ranged(6, low=1)
    edit_every: int = ranged(3, low=1)
    lr_sh_dc: float = ranged(0.025, low=0, open=True)
    editor: str = "simulated"
    ip2p_steps: int = ranged(DDIM_STEPS, low=1)
    ip2p_weights: Path | None = None
    references: bool = True
    points: int | None = ranged(None, low=1)

    def __post_init__(self):
        from jaxedit.scenes import list_scenes
        from jaxedit.scenes.library import DATASETS

        check_ranges(self)
        if self.editor not in EDITORS:
            raise DataError("editor", f"unknown editor {self.editor!r}; choose from "
                                      f"{', '.join(EDITORS)}")
        if self.ip2p_weights is not None and self.editor != "ip2p":
            raise DataError("ip2p_weights", f"used only with the ip2p editor (the editor is "
                                            f"{self.editor})")
        bad = [s for s in self.scenes if s not in list_scenes()]
        if bad or not self.scenes:
            raise DataError("scenes", f"unknown scene(s) {bad}; built-in: "
                            f"{', '.join(list_scenes())}" if bad else
                            f"no scene given; built-in: {', '.join(list_scenes())}")
        if not self.prompts:
            raise DataError("prompts", "no instruction given")
        rendered = [s for s in self.scenes if s in DATASETS]
        if self.points is not None and rendered:
            raise DataError("points", f"{', '.join(rendered)}: a rendered scene brings its own "
                                      "points; give --points with procedural scenes only")
        for name in ("methods", "control_methods"):
            rows = getattr(self, name)
            bad = [m for m in rows if m not in METHODS]
            if bad or not rows:
                raise DataError(name, f"unknown method(s) {bad}; choose from "
                                f"{', '.join(METHODS)}" if bad else
                                f"no method given; choose from {', '.join(METHODS)}")
            if any(m in FOLLOWERS for m in rows) and "proedit" not in rows:
                raise DataError(name, f"{', '.join(FOLLOWERS)} take ProEdit's budget: "
                                      f"include proedit")
        if not self.variants:
            raise DataError("variants", "need at least one editor variant")
        for v in self.variants:
            parse_variant(v)
        if self.max_steps < 3 * self.refine_every:
            raise DataError("max_steps", f"must be at least 3 x refine_every "
                                         f"({self.refine_every}) so density control runs in "
                                         f"every subtask, got {self.max_steps}")

    @classmethod
    def smoke(cls) -> "AblationConfig":
        """Tiny sizes for CI: one instruction, two seeds, the mechanism variant and one
        control, no in2n (one more trainer compile)."""
        return cls(scenes=("ball",), prompts=("make it look like autumn",), seeds=2,
                   variants=("3", "3:0"), methods=("proedit", "nd", "nd_equal", "nd_k"),
                   control_methods=("proedit", "nd"), size=16, views=4, test_views=2,
                   recon_iters=30, refine_every=4, max_steps=12, warmup=2, patience=3,
                   edit_every=2, points=400)

    def settings_json(self, kinds: dict[str, str], recon_seed: int, editor: str | None = None
                      ) -> dict:
        """ablation.json's ``settings``: what a resumed run must match (but ``seeds``: a
        study may be extended by more seeds)."""
        rows = self.rows_of(editor)
        return {"editor": editor or self.editor, "references": self.references,
                "scenes": list(self.scenes), "prompts": list(self.prompts), "seeds": self.seeds,
                "variants": list(rows), "methods": rows,
                "size": self.size, "views": self.views, "test_views": self.test_views,
                "recon_iters": self.recon_iters, "refine_every": self.refine_every,
                "max_steps": self.max_steps, "warmup": self.warmup, "patience": self.patience,
                "edit_every": self.edit_every, "lr_sh_dc": self.lr_sh_dc,
                "recon_seed": recon_seed,
                "target_subtasks": {k: TARGET_SUBTASKS.get(k, TARGET_SUBTASKS_DEFAULT)
                                    for k in sorted(set(kinds.values()))},
                **({"ip2p_steps": self.ip2p_steps} if (editor or self.editor) == "ip2p" else {}),
                **({} if self.points is None else {"points": self.points})}

    def rows_of(self, editor: str | None = None) -> dict[str, list[str]]:
        """{variant label: its methods, in the order of METHODS}; an editor other than the
        simulated one has one variant, its name, with ``methods``."""
        editor = editor or self.editor
        if editor != "simulated":
            return {editor: [m for m in METHODS if m in self.methods]}
        labels = [_variant_label(*parse_variant(v)) for v in self.variants]
        return {label: [m for m in METHODS if m in (self.methods if i == 0
                                                    else self.control_methods)]
                for i, label in enumerate(labels)}


def _variant_label(modes: int, gain: float) -> str:
    return str(modes) if gain == 1.0 else f"{modes}:{gain:g}"


def recon_config(iters: int):
    """The reconstruction each scene's edits start from (SH degree 1, a 50k cap)."""
    from jaxedit.densify import DensifyConfig
    from jaxedit.train import TrainConfig
    from jaxedit.pipelines.reconstruct import ReconstructConfig

    dens = DensifyConfig(refine_every=100, warmup=min(500, iters // 5),
                         reset_every=max(iters // 2, 1), max_gaussians=50_000)
    train = TrainConfig(iterations=iters, sh_degree=1, sh_degree_interval=max(iters // 4, 1),
                        densify=dens)
    return ReconstructConfig(train=train, checkpoint_every=0)


def _renders(data, gaussians, background) -> np.ndarray:
    """float32 [M, H, W, 3]: the scene at the held-out views."""
    renderer = Renderer(background)
    return np.stack([np.asarray(renderer.rgb(gaussians, data.test_cameras[i]), np.float32)
                     for i in range(len(data.test_images))])


def _write_views(path: Path, targets, renders: dict) -> None:
    """One PNG: a row per mode target, then a row per method's final test views."""
    rows = list(targets) + [renders[m] for m in renders]
    grid = image_grid(np.concatenate(rows), ncols=len(rows[0]))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.ascontiguousarray(np.clip(grid, 0.0, 1.0)))


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text.lower()).strip("_")[:40]


def _editors(config: AblationConfig, editor=None) -> tuple[dict, str]:
    """({variant label: editor}, the editor's name): the simulated editor's variants, the
    bundled InstructPix2Pix, or ``editor`` (an object given by the caller, e.g. a test's;
    its ``label`` attribute or "custom")."""
    if editor is not None:
        name = str(getattr(editor, "label", "custom"))
        return {name: editor}, name
    if config.editor == "ip2p":
        from jaxedit.edit.buffer import pick_devices
        from jaxedit.editors.jax_ip2p import JaxIP2PEditor

        return {"ip2p": JaxIP2PEditor.from_pretrained(_ip2p_folder(config),
                                                      devices=[pick_devices()[1]],
                                                      steps=config.ip2p_steps)}, "ip2p"
    return {_variant_label(k, g): SimulatedEditor(modes=k, mode_step_gain=g)
            for k, g in map(parse_variant, config.variants)}, "simulated"


def _kind(editor, prompt: str) -> str:
    """The instruction's kind (it sets ProEdit's subtask count); unknown prompts: DataError."""
    try:
        if isinstance(editor, SimulatedEditor):
            editor.encode(prompt)  # unknown instructions fail here
            return INSTRUCTIONS[editor._index(prompt)].kind
        if hasattr(editor, "kind"):
            return str(editor.kind(prompt))
        from jaxedit_lab.train_editor import edit_data

        return edit_data.instruction(prompt).kind
    except DataError as e:
        raise DataError("prompts", e.problem) from None


def _key(r: dict) -> tuple:
    return (str(r["editor_modes"]), r["scene"], r["prompt"], r["seed"], r["method"])


RUNS_FILE = "runs.jsonl"
SETTINGS_FILE = "settings.json"


def _resume(out: Path, settings_json: dict, log) -> list[dict]:
    """The records already in ``out/runs.jsonl`` (a truncated last line, or a second record
    of the same run, is dropped and the file rewritten without it); a DataError when ``out``
    holds a study of other settings (the seed count may differ: a study is extended by more
    seeds)."""
    path, spath = out / RUNS_FILE, out / SETTINGS_FILE
    if spath.exists():
        old = json.loads(spath.read_text())
        same = {k: v for k, v in old.items() if k != "seeds"} == \
            {k: v for k, v in settings_json.items() if k != "seeds"}
        if not same:
            raise DataError(spath, "this folder holds a study of other settings; use another "
                                   "--out (or the same settings to resume it)")
    atomic_write_text(spath, json.dumps(settings_json, indent=2) + "\n")
    runs: list[dict] = []
    if not path.exists():
        return runs
    lines = path.read_text().splitlines()
    bad, seen, repeated = 0, set(), 0
    for line in lines:
        try:
            record = json.loads(line)
        except ValueError:
            bad += 1
            continue
        # A study run in parts and merged (two folders' runs.jsonl concatenated) may hold a
        # run twice; the runs are seeded, so the first copy stands for both.
        if _key(record) in seen:
            repeated += 1
            continue
        seen.add(_key(record))
        runs.append(record)
    if bad or repeated:
        log(f"dropping {bad} unreadable line(s) (an interrupted write) and {repeated} "
            f"repeated run(s) of {path}")
        atomic_write_text(path, "".join(json.dumps(r) + "\n" for r in runs))
    log(f"resuming: {len(runs)} finished records in {path}")
    return runs


def _append(path: Path, record: dict) -> None:
    """One record as one line of ``path``, flushed to disk before the next run starts."""
    import os

    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(record) + "\n")
        f.flush()
        os.fsync(f.fileno())


def finish(out: Path, runs: list[dict], settings_json: dict, *, wall_time_s: float | None = None
           ) -> dict:
    """ablation.json and ablation.md computed from the records (``runs.jsonl``)."""
    summary, differences = summarise(runs)
    payload = {"settings": settings_json, "runs": runs, "summary": summary,
               "differences": differences}
    if wall_time_s is not None:
        payload["wall_time_s"] = wall_time_s
    atomic_write_text(out / "ablation.json", json.dumps(payload, indent=2) + "\n")
    title = "simulated editor" if settings_json.get("editor") == "simulated" else \
        f"editor {settings_json.get('editor')}"
    atomic_write_text(out / "ablation.md", f"# Ablation ({title})\n\n"
                      f"Settings: `{json.dumps(settings_json)}`\n" + tables(summary, differences))
    return payload


def run_ablation(out: Path, config: AblationConfig = AblationConfig(), *, recon_seed: int = 0,
                 report: bool = True, log=print, editor=None, seeds: range | None = None
                 ) -> dict:
    """Run the ablation into ``out``; returns the contents of ablation.json.

    Every finished run (and reference level) is appended to ``out/runs.jsonl`` at once; a
    call with the same settings skips the (variant, scene, instruction, seed, method)
    records already there, so a study can be run in parts. ``ablation.json`` (records,
    summary, paired differences) is computed from the JSONL at the end. Each scene's dataset
    and reconstruction are made once in ``out/SCENE``
    (:func:`jaxedit.pipelines.cache.prepared_scene`). ``editor``: an editor object to use
    instead of ``config.editor`` (tests plant effects with one).

    ``seeds``: the part of the study this call runs (default ``range(config.seeds)``), so
    that a study can be split across processes or machines, each part in its own folder,
    and merged by concatenating their ``runs.jsonl`` (a run recorded twice counts once).
    The reference levels do not depend on the seed: the part holding seed 0 runs them.
    ``ablation.json`` then summarises the records of this folder alone.
    """
    out = Path(out)
    editors, name = _editors(config, editor)
    rows_of = config.rows_of(name)
    first = next(iter(editors.values()))
    prompts = tuple(config.prompts)
    kinds = {p: _kind(first, p) for p in prompts}
    weights_id = _weights_id(name, config) if editor is None else None
    settings_json = config.settings_json(kinds, recon_seed, name)
    if weights_id is not None:  # a study resumes with the weights it began with, no others
        settings_json["editor_weights"] = weights_id
    scenes = config.scenes
    seeds = range(config.seeds) if seeds is None else seeds
    if seeds.step != 1 or not 0 <= seeds.start < seeds.stop <= config.seeds:
        raise DataError("seeds", f"the part {seeds.start}:{seeds.stop} is not a range of "
                                 f"seeds within 0:{config.seeds}")
    references = config.references and 0 in seeds
    out.mkdir(parents=True, exist_ok=True)
    runs = _resume(out, settings_json, log)
    done = {_key(r): r for r in runs}
    jsonl = out / RUNS_FILE
    elapsed0 = sum(r.get("seconds", 0.0) for r in runs)

    device = _device()

    def keep(record):
        record.setdefault("device", device)  # a run reused from ProEdit keeps ProEdit's
        _append(jsonl, record)
        runs.append(record)
        done[_key(record)] = record

    # Every run of the study, the references included: the progress lines count to it.
    total = len(scenes) * len(prompts) * sum(
        len(seeds) * len(rows) + (len(REFERENCES) if references else 0)
        for rows in rows_of.values())
    t_start = time.perf_counter()
    for scene_name in scenes:
        dataset, scene, _ = prepared_scene(out / scene_name, scene_name, size=config.size,
                                           views=config.views, test_views=config.test_views,
                                           seed=recon_seed, points=config.points,
                                           config=recon_config(config.recon_iters), log=log)
        data = EditData.from_dataset(dataset)
        test_idx = np.asarray(dataset.test_indices) if len(dataset.test_indices) else \
            np.asarray(dataset.train_indices)
        settings = EditTrainConfig(lr_sh_dc=config.lr_sh_dc, sh_degree=scene.sh_degree
                                 ).replace_densify(refine_every=config.refine_every)
        n_views = len(data.train_images)
        for label, ed in editors.items():
            for prompt in prompts:
                where = dict(scene_name=scene_name, dataset=dataset, scene_seed=recon_seed)
                targets = outcome_targets(ed, prompt, data.test_images, indices=test_idx,
                                          **where)
                train_targets = outcome_targets(ed, prompt, data.train_images,
                                                indices=np.asarray(dataset.train_indices),
                                                **where)
                tag = dict(editor_modes=label, modes=int(targets.shape[0]),
                           step_gain=getattr(getattr(ed, "params", None), "mode_step_gain", None),
                           scene=scene_name, prompt=prompt, kind=kinds[prompt],
                           recon_seed=recon_seed, editor_weights=weights_id)
                if references:
                    for record in _references(
                            ed, prompt, data, scene, targets, config, settings, kinds[prompt],
                            done=lambda m: (label, scene_name, prompt, -1, m) in done,
                            train_targets=lambda: train_targets):
                        keep(record | tag | {"seed": -1, "edit_outcomes": None})
                        log(f"{label} {scene_name} {kinds[prompt]} reference {record['method']}: "
                            f"psnr_best {record['psnr_best']:.2f}, agreement "
                            f"{record['outcome_agreement']:.2f}")
                for seed in seeds:
                    renders, lead = {}, None
                    for method in rows_of[label]:
                        prior = done.get((label, scene_name, prompt, seed, method))
                        lead_run = done.get((label, scene_name, prompt, seed, "proedit"))
                        if prior is None and method == "uniform" and _same_plan_as_uniform(
                                lead_run):
                            prior = _uniform_from(lead_run)
                            keep(prior)
                            log(f"[{len(done)}/{total}] {label} {scene_name} {kinds[prompt]} "
                                f"seed {seed} uniform: ProEdit's own ratios, its run reused")
                        if prior is None:
                            cfg = method_config(method, kind=kinds[prompt], lead=lead,
                                                warmup=config.warmup, patience=config.patience,
                                                max_steps=config.max_steps,
                                                edit_every=config.edit_every, views=n_views)
                            observer = _edit_observer(data.train_images, train_targets)
                            record, rgb = _run_one(CallLog(ed, observer), prompt, data, scene,
                                                   cfg, settings, seed, targets)
                            record.update(tag, seed=seed, method=method)
                            keep(record)
                            renders[method] = rgb
                            prior = record
                            log(f"[{len(done)}/{total}] {label} {scene_name} {kinds[prompt]} "
                                f"seed {seed} {method}: psnr_best {record['psnr_best']:.2f}, "
                                f"agreement {record['outcome_agreement']:.2f}, mixing "
                                f"{record['mode_mixing']:.2f}, {record['total_steps']} steps, "
                                f"{record['editor_calls']} calls {record['calls_by_band']}, "
                                f"plateau {record['plateau_share']}, "
                                f"{elapsed0 + time.perf_counter() - t_start:.0f} s so far")
                        if method == "proedit":
                            cfg = method_config("proedit", kind=kinds[prompt], lead=None,
                                                warmup=config.warmup, patience=config.patience,
                                                max_steps=config.max_steps,
                                                edit_every=config.edit_every, views=n_views)
                            lead = {"steps": prior["subtask_steps"],
                                    "edits": prior["edits_per_subtask"],
                                    "horizon": anneal_horizon(cfg, cfg.max_steps)}
                    if seed == 0 and renders:
                        _write_views(out / "views" / f"m{_slug(label)}_{scene_name}_"
                                     f"{_slug(prompt)}.png", targets, renders)
    payload = finish(out, runs, settings_json,
                     wall_time_s=elapsed0 + time.perf_counter() - t_start)
    if report:
        from jaxedit_lab.ablation.report import write_ablation_report

        write_ablation_report(out)
    return payload


def _device() -> str:
    """What computed the runs, e.g. ``"cpu"`` or ``"gpu NVIDIA H200"``: a study run in parts
    on several machines says which part ran where (float rounding differs between them, so
    a run is reproducible bit for bit only on its own kind of device)."""
    import jax

    d = jax.devices()[0]
    return d.platform if d.platform == "cpu" else f"{d.platform} {d.device_kind}"


def _references(editor, prompt, data, scene, targets, config, settings, kind, *, done,
                train_targets):
    """The reference levels of one (scene, instruction) not yet ``done(method)``: the unedited
    reconstruction, and the ceiling: the same editing trainer (ND, its own plateau and
    guard) trained directly on one outcome's targets, the best outcome by ``psnr_best``
    (every outcome's scores in ``per_outcome``)."""
    background = method_config("nd", kind=kind, lead=None, warmup=config.warmup,
                               patience=config.patience, max_steps=config.max_steps,
                               edit_every=config.edit_every, views=1).background
    if not done("unedited"):
        t0 = time.perf_counter()
        yield {**outcome_scores(_renders(data, scene, background), targets), "method": "unedited",
               "reference": True, "seconds": time.perf_counter() - t0}
    if not done("ceiling"):
        t0 = time.perf_counter()
        train = train_targets()
        cfg = method_config("nd", kind=kind, lead=None, warmup=config.warmup,
                            patience=config.patience, max_steps=config.max_steps,
                            edit_every=config.edit_every, views=len(data.train_images))
        per = []
        for k in range(train.shape[0]):
            fixed = FixedTargets(editor, data.train_images, train[k])
            res = run_edit(fixed, prompt, data, scene, config=cfg, settings=settings, seed=0,
                           run_dir=None, report=False, hooks=cfg.hooks(),
                           identity=None)
            rgb = _renders(data, res["gaussians"], cfg.background)
            # scored against outcome k's own target: the ceiling of holding that outcome
            own = outcome_scores(rgb, targets[k:k + 1])
            per.append({**outcome_scores(rgb, targets), "psnr_own": own["psnr_best"],
                        "plateau_share": _plateau(res["schedule"]["subtasks"])[1]})
        best = max(range(len(per)), key=lambda k: per[k]["psnr_best"])
        yield {**per[best], "method": "ceiling", "reference": True, "outcome": best,
               "per_outcome": per, "seconds": time.perf_counter() - t0}


def _same_plan_as_uniform(proedit: dict | None) -> bool:
    """Whether ProEdit's scheduler picked uniform ratios (r_0 = 0, i / n, then the
    consolidation at 1): then the uniform method's run is ProEdit's, bit for bit (the same
    configuration, plan and seed; only the schedule's bookkeeping differs)."""
    if proedit is None:
        return False
    ratios = list(proedit["ratios"])
    n = len(ratios) - 2  # r0, n edit subtasks, rn
    uniform = [0.0] + [i / n for i in range(1, n + 1)] + [1.0]
    return n >= 1 and np.allclose(ratios, uniform, rtol=0.0, atol=1e-12)


def _uniform_from(proedit: dict) -> dict:
    """The uniform method's record when it is ProEdit's run (:func:`_same_plan_as_uniform`):
    ProEdit's scores and training budget, marked ``same_run_as``; no seconds of its own
    (``cpu_seconds`` None), and ``schedule_calls`` (the difficulty's bookkeeping, which a
    uniform run measures on its own ratios) None: not run."""
    return {**proedit, "method": "uniform", "same_run_as": "proedit", "seconds": 0.0,
            "cpu_seconds": None, "schedule_calls": None}


def _plateau(subtasks) -> tuple[list, float | None]:
    """(per subtask: ended on its loss plateau (True), on a guard (False), or a fixed budget
    (None); the share of the subtasks that could plateau that did)."""
    ended = [s["converged"] for s in subtasks]
    could = [e for e in ended if e is not None]
    return ended, (sum(bool(e) for e in could) / len(could) if could else None)


def _edit_counts(cfg, subtasks, views: int) -> list[int]:
    """Training edits per subtask: its explicit exchanges before its end, or the periodic
    schedule's (:func:`.methods.edits_per_subtask`)."""
    warmup = cfg.warmup  # the plan's W (IN2N's is 0: ProEditConfig.for_mode)
    out = []
    for i, s in enumerate(subtasks):
        plan = None if cfg.edit_plan is None else cfg.edit_plan[i]
        if plan is not None:
            out.append(sum(c for st, c, _ in plan if st < s["steps"] - warmup))
        else:
            out.append(edits_per_subtask(s["steps"], warmup=warmup, every=cfg.edit_every,
                                         views=views, initial_sweep=cfg.initial_sweep))
    return out


def _run_one(editor: CallLog, prompt, data, scene, cfg, settings, seed, targets):
    """(record, test renders) of one edit run; ``targets`` [K, M, H, W, 3] the outcomes'."""
    t0, c0 = time.perf_counter(), time.process_time()
    settings = settings.classic() if cfg.mode == "in2n" else settings  # IN2N's density control
    res = run_edit(editor, prompt, data, scene, config=cfg, settings=settings, seed=seed,
                   run_dir=None, report=False, hooks=cfg.hooks(),
                   identity=None)
    rgb = _renders(data, res["gaussians"], cfg.background)
    scores = outcome_scores(rgb, targets)
    m, subtasks = res["metrics"], res["schedule"]["subtasks"]
    n_views = len(data.train_images)
    edits = _edit_counts(cfg, subtasks, n_views)
    calls = int(m["utilisation"]["edits"])
    if sum(edits) != calls or editor.calls < calls:
        raise RuntimeError(f"counted {sum(edits)} training edits ({editor.calls} logged), "
                           f"the subtasks made {calls}")
    times = editor.timesteps[editor.calls - calls:]
    t_range = tuple(cfg.timestep_range)
    agreement = None
    if editor.modes is not None:
        agreement = sweep_agreement(editor.modes[len(editor.modes) - calls:], edits, n_views)
        # the refine subtask edits with e(0): every mode's target is the original, its draws
        # mean nothing
        agreement = [[] if s["kind"] == "refine" else a for s, a in zip(subtasks, agreement)]
    flat = [a for sub in (agreement or []) for a in sub]
    ended, share = _plateau(subtasks)
    outcomes = None
    if editor.observe is not None:
        seen = editor.observed[len(editor.observed) - calls:]
        at = _edit_steps(cfg, subtasks, n_views)
        if not len(at) == len(seen) == len(times) == calls:
            raise RuntimeError(f"{len(at)} edit steps and {len(seen)} logged outcomes for "
                               f"{calls} edits")
        ratio = [0.0 if s["kind"] == "refine" else float(s["ratio"]) for s in subtasks]
        outcomes = [{"subtask": i, "step": step, "view": view, "t": float(t),
                     "ratio": ratio[i], "outcome": label}
                    for (i, step), (view, label), t in zip(at, seen, times)]
    counts = None if outcomes is None else \
        dict(sorted(Counter(str(e["outcome"]) for e in outcomes).items()))
    return ({**scores, "edit_outcomes": outcomes, "edit_outcome_counts": counts,
             "psnr_vs_target": m.get("psnr_vs_target"),
             "multiview_consistency": m.get("multiview_consistency"),
             "total_steps": int(m["total_steps"]), "subtasks": len(subtasks),
             "subtask_steps": [int(s["steps"]) for s in subtasks],
             "ratios": [s["ratio"] for s in subtasks],
             "editor_calls": calls, "schedule_calls": editor.calls - calls,
             "edits_per_subtask": edits, "edit_every": cfg.edit_every,
             "edit_schedule": "explicit" if cfg.edit_plan is not None else "periodic",
             "calls_by_band": timestep_bands(times, t_range),
             "hottest_calls": sum(t >= t_range[1] - 1e-9 for t in times),
             "timestep_bands": BANDS,
             "resets": sum(cfg.mode != "in2n" for _ in subtasks),
             "sweeps": sum(e // n_views for e in edits),
             "initial_sweeps": sum(1 for _ in _sweeps(cfg, subtasks, n_views)),
             "guard_ended": sum(s["guard"] is not None for s in subtasks),
             "plateau_ended": ended, "plateau_share": share,
             "maintenance": sum(int(s["density"]["refinements"]) for s in subtasks),
             "agreement": agreement, "agreement_final": flat[-1] if flat else None,
             "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0},
            rgb)


def _edit_steps(cfg, subtasks, views: int) -> list[tuple[int, int]]:
    """(subtask, step from the subtask's start) of every training edit, in the order the
    subtasks made them (the exchanges :func:`_edit_counts` counts)."""
    warmup = 0 if cfg.mode == "in2n" else cfg.warmup
    out = []
    for i, s in enumerate(subtasks):
        plan = None if cfg.edit_plan is None else cfg.edit_plan[i]
        if plan is not None:
            out += [(i, warmup + st) for st, c, _ in plan if st < s["steps"] - warmup
                    for _ in range(c)]
        else:
            for st, c, _ in periodic_exchanges(s["steps"], warmup=warmup, every=cfg.edit_every,
                                               views=views, initial_sweep=cfg.initial_sweep):
                out += [(i, warmup + st)] * c
    return out


def _edit_observer(originals, train_targets):
    """``(original, edited) -> (view, outcome)`` for :class:`.methods.CallLog`: the training
    view whose photo ``original`` is (the nearest: an editor may be handed a device copy) and
    the class of ``edited`` against it and its outcome targets (``train_targets`` [K, N, H,
    W, 3]; :func:`jaxedit_lab.outcome_class.classify`); "undefined" on a view where an
    outcome's target is the photo itself (a local edit of a part the view does not show),
    which cannot tell that outcome from no edit."""
    photos = np.asarray(originals, np.float32)
    targets = np.asarray(train_targets, np.float32)

    def observe(original, edited):
        o = np.asarray(original, np.float32)
        view = int(np.argmin(np.mean((photos - o) ** 2, axis=(1, 2, 3))))
        try:
            label = outcome_class.classify(np.asarray(edited, np.float32), photos[view],
                                           targets[:, view])["label"]
        except ValueError:
            label = "undefined"
        return view, label

    return observe


def _ip2p_folder(config: AblationConfig) -> Path:
    """The ip2p editor's diffusers folder: ``ip2p_weights``, else the bundled one."""
    from jaxedit.editors import bundled_editor

    return bundled_editor() if config.ip2p_weights is None else Path(config.ip2p_weights)


def _weights_id(name: str, config: AblationConfig) -> str | None:
    """The ip2p editor's UNet weights, sha256's first 16 digits; None for the others."""
    if name != "ip2p":
        return None
    import hashlib

    files = sorted((_ip2p_folder(config) / "unet").glob("*.safetensors"))
    digest = hashlib.sha256()
    for f in files:
        digest.update(f.read_bytes())
    return digest.hexdigest()[:16]


def _sweeps(cfg, subtasks, views: int):
    """The exchanges that edited every view at once (initial sweeps) of a run."""
    warmup = cfg.warmup  # the plan's W (IN2N's is 0: ProEditConfig.for_mode)
    for i, s in enumerate(subtasks):
        plan = None if cfg.edit_plan is None else cfg.edit_plan[i]
        if plan is None:
            if cfg.initial_sweep and s["steps"] > warmup:
                yield i
        else:
            yield from (i for st, c, _ in plan if c >= views and st < s["steps"] - warmup)
