"""The page's sections, [(anchor, title, html)], for an edit run and any other run."""

from __future__ import annotations

import json
from pathlib import Path

from ...errors import DataError
from .html import _e, _fmt, _img, _kv_table, _metric_names, _reproduce, _slider, _table
from .images import _grid_uri, _load_thumb, _turntable_uri, image_uri
from .plots import difficulty_plot, training_plot, tree_plot
from .rundir import _is_number, _pngs, _snapshot_dir, read_json, read_train_log


# The last difficulty plot: rebuilding the page at smaller sizes need not redraw it.
_PLOT_MEMO: dict = {}


# Edit run
def moved_cells(metrics: dict | None) -> list[str]:
    """The schedule table's cells of how far a snapshot moved from the input scene."""
    m = metrics or {}
    if not _is_number(m.get("psnr_vs_input")):
        return ["&mdash;"] * 3
    return [f"{m['psnr_vs_input']:.2f}", f"{m['ssim_vs_input']:.3f} / {m['lpips_vs_input']:.3f}",
            f"{m['num_gaussians']} ({m['gaussians_vs_input']:.2f}&times;)"]


def identity_paragraph(identity: dict | None) -> str:
    """The editor's identity on this scene (schedule.json's ``"identity"``), one paragraph."""
    if not isinstance(identity, dict):
        return ""
    verdict = ("clears the floor" if identity.get("passed") else
               "is <b>under the floor</b> (edited anyway: --accept-low-identity)")
    return (f"<p>Editor identity on this scene: PSNR {identity['psnr']:.1f} dB, LPIPS "
            f"{identity['lpips']:.3f} (e(0) at t = {identity['timestep']:.2f} on "
            f"{len(identity['views'])} difficulty views; floor {identity['min_psnr']:g} dB, "
            f"LPIPS {identity['max_lpips']:g}): it {verdict}.</p>")


def _edit_sections(run_dir: Path, schedule: dict, *, thumb_px: int, max_views: int,
                   turntable_px: int, max_frames: int, notes: dict | None,
                   config_path: Path | None = None) -> list[tuple[str, str, str]]:
    """[(anchor, title, html)] of an edit run directory."""
    config = read_json(config_path or run_dir / "config.json", required=False)
    metrics = read_json(run_dir / "metrics.json", required=False) or {}
    subtasks = schedule.get("subtasks", [])
    snap_dirs = [_snapshot_dir(run_dir, s, i) for i, s in enumerate(subtasks)]
    labels = [f"{s.get('name', i)}  (r = {float(s['ratio']):.3f})" for i, s in enumerate(subtasks)]
    sections = []

    info = {"editor": schedule.get("editor"), "mode": schedule.get("mode"),
            "threshold": schedule.get("threshold"), "subtasks": len(subtasks)}
    selected = read_json(run_dir / "selected.json", required=False)
    start = None
    if isinstance(selected, dict):
        positions = [i for i, s in enumerate(subtasks) if s.get("index", i) == selected.get("index")]
        start = positions[-1] if positions else None
        if start is not None:
            info["selected (selected.ply)"] = labels[start]
    if notes:
        info.update(notes)
    body = (f'<div class="instruction">&ldquo;{_e(schedule.get("prompt", "?"))}&rdquo;</div>'
            + _kv_table(info) + _reproduce(config))
    if str(schedule.get("editor", "")).startswith("simulated"):
        body += ("<p>The edits come from the <b>simulated editor</b>: an offline test instrument "
                 "with a known ground-truth target, not a diffusion model such as "
                 "InstructPix2Pix.</p>")
    sections.append(("instruction", "Instruction", body))

    local = schedule.get("local")
    if isinstance(local, dict):
        sections.append(("local", "Local edit", _local_body(run_dir, local, thumb_px=thumb_px,
                                                             max_views=max_views)))

    rows, total_s, total_steps = [], 0.0, 0
    for i, s in enumerate(subtasks):
        total_s += float(s.get("seconds") or 0.0)
        total_steps += int(s.get("steps") or 0)
        snap = s.get("snapshot")
        name = _e(s.get("name", "")) + (" &#9733;" if i == start else "")
        rows.append([_e(s.get("index", i)), name, f"{float(s['ratio']):.4f}",
                     _fmt(s.get("difficulty")), _fmt(s.get("steps")), _fmt(s.get("seconds")),
                     _fmt(s.get("converged")), *moved_cells(s.get("metrics")),
                     f"<code>{_e(snap)}</code>" if snap else "&mdash;"])
    rows.append(["", "<b>total</b>", "", "", _fmt(total_steps), _fmt(round(total_s, 2)), "",
                 "", "", "", ""])
    body = (identity_paragraph(schedule.get("identity"))
            + _table(["#", "subtask", "ratio r", "difficulty d(r<sub>i-1</sub>, r<sub>i</sub>)",
                      "iterations", "seconds", "converged", "PSNR vs input (dB)",
                      "SSIM / LPIPS vs input", "Gaussians (vs input)", "snapshot"], rows,
                     "schedule"))
    unconverged = [s.get("name", i) for i, s in enumerate(subtasks) if s.get("converged") is False]
    if unconverged:
        body += ("<p>Not converged (the max-steps guard fired before the loss plateaued): "
                 f"{_e(', '.join(map(str, unconverged)))}.</p>")
    sections.append(("schedule", "Schedule", body))

    tree = _tree_body(run_dir, schedule, thumb_px=thumb_px, max_views=max_views)
    if tree:
        sections.append(("tree", "Tree of edits", tree))

    key = json.dumps(schedule, sort_keys=True, default=str)
    if _PLOT_MEMO.get("key") != key:
        _PLOT_MEMO.update(key=key, uri=difficulty_plot(schedule))
    sections.append(("difficulty", "Difficulty and chosen ratios",
                     _img(_PLOT_MEMO["uri"], "difficulty plot", "plot")))

    original = _pngs(run_dir / "original" / "renders")
    orig_uri = _grid_uri(original, thumb_px, max_views)
    frames = []
    for label, d in zip(labels, snap_dirs):
        uri = _grid_uri(_pngs(d / "renders" if d else None), thumb_px, max_views)
        snap_metrics = (read_json(d / "metrics.json", required=False) if d else None) or {}
        headline = ", ".join(f"{k} {_fmt(snap_metrics[k])}" for k in
                             ("psnr_vs_target", "ssim_vs_target", "multiview_consistency",
                              "num_gaussians") if _is_number(snap_metrics.get(k)))
        inner = ('<div class="row-label">original</div>' + _img(orig_uri, "original views")
                 + f'<div class="row-label">after subtask {_e(label)}'
                 + (f" &mdash; {headline}" if headline else "") + "</div>"
                 + _img(uri, f"renders of {label}"))
        frames.append((label, inner))
    body = ("<p>Drag the slider to choose the level of aggressivity: each subtask's snapshot at "
            "the same test views (bottom) under the original scene (top). Keep a level with "
            "<code>python -m experiments edit --out RUN_DIR --select-only --select INDEX</code> "
            "(writes <code>selected.ply</code>).</p>"
            + _slider("gallery-slider", frames, start))
    sections.append(("gallery", "Aggressivity gallery", body))

    frames = []
    orig_depth = _grid_uri(_pngs(run_dir / "original" / "depth"), thumb_px, max_views)
    for label, d in zip(labels, snap_dirs):
        uri = _grid_uri(_pngs(d / "depth" if d else None), thumb_px, max_views)
        inner = ""
        if orig_depth:
            inner += '<div class="row-label">original</div>' + _img(orig_depth, "original depth")
        inner += f'<div class="row-label">{_e(label)}</div>' + _img(uri, f"depth of {label}")
        frames.append((label, inner))
    body = ("<p>Expected depth, near = red, far = blue (one colour range per snapshot).</p>"
            + _slider("depth-slider", frames, start))
    sections.append(("depth", "Depth maps", body))

    cards = []
    orig_tt = _turntable_uri(run_dir / "original" / "turntable.webp", turntable_px, max_frames)
    if orig_tt:
        cards.append(f'<figure class="card"><img src="{orig_tt}" alt="turntable original">'
                     "<figcaption>original</figcaption></figure>")
    for label, d in zip(labels, snap_dirs):
        uri = _turntable_uri(d / "turntable.webp", turntable_px, max_frames) if d else None
        if uri:
            cards.append(f'<figure class="card"><img src="{uri}" alt="turntable {_e(label)}">'
                         f"<figcaption>{_e(label)}</figcaption></figure>")
    body = (f'<div class="cards">{"".join(cards)}</div>' if cards
            else '<p class="missing">no turntables recorded</p>')
    sections.append(("turntables", "Turntables", body))

    body = _kv_table(metrics) if metrics else '<p class="missing">no metrics.json</p>'
    per = [(label, read_json(d / "metrics.json", required=False) if d else None)
           for label, d in zip(labels, snap_dirs)]
    per = [(label, m) for label, m in per if isinstance(m, dict) and m]
    if per:
        names = _metric_names(m for _, m in per)
        body += "<h3>Per subtask</h3>" + _table(
            ["subtask"] + [_e(n) for n in names],
            [[_e(label)] + [_fmt(m.get(n)) for n in names] for label, m in per], "per-subtask")
    sections.append(("metrics", "Metrics", body))
    return sections


def _tree_body(run_dir: Path, schedule: dict, *, thumb_px: int, max_views: int) -> str:
    """The branches of a steered run (``tree.json``) as a table, strips and a plot; "" without."""
    from ...edit.steer import RunTree
    from ..snapshots import branch_folder

    raw = read_json(run_dir / "tree.json", required=False)
    if raw is None:
        return ""
    try:
        tree = RunTree.from_json(raw)
    except (ValueError, KeyError, TypeError) as e:
        raise DataError(run_dir / "tree.json", f"malformed run tree ({e})") from None
    rows, strips, lines = [], [], []
    for name in tree.names():
        branch = tree.get(name)
        folder = branch_folder(run_dir, name)
        sched = schedule if branch is None else read_json(folder / "schedule.json",
                                                          required=False) or {}
        subtasks = [s for s in sched.get("subtasks", []) if s.get("snapshot")]
        status = ("done" if (folder / "metrics.json").is_file() else
                  "open" if sched else "planned")
        op = "root" if branch is None else branch.op
        if sched.get("experimental"):
            op += " (experimental)"
        rows.append([f"<b>{_e(name)}</b>", _e(op),
                     _e("" if branch is None else branch.parent),
                     _e(sched.get("prompt", "") if branch is None or branch.prompt is None
                        else branch.prompt),
                     _e(sched.get("seed", "")), _e(status),
                     _e(", ".join(f"{float(s['ratio']):.3f}" for s in subtasks))])
        views = [(_pngs(folder / Path(s["snapshot"]).parent / "renders") or [None])[0]
                 for s in subtasks]
        uri = _grid_uri([v for v in views if v is not None], thumb_px // 2, 16)
        strips.append(f'<div><div class="row-label">{_e(name)}: '
                      + ", ".join(f"{_e(s['name'])} r = {float(s['ratio']):.3f}" for s in subtasks)
                      + "</div>" + _img(uri, f"snapshots of {name}") + "</div>")
        steps = [(s["ratio"], s.get("difficulty")) for s in sched.get("subtasks", [])
                 if s.get("kind") == "edit"]
        lines.append({"name": name, "steps": steps})
    return ("<p>Branches grown from the run's snapshots (<code>edit --out RUN --from NODE "
            "--refine | --prompt TEXT | --seed N</code>, <code>--extend R_MAX</code>); keep one "
            "with <code>edit --out RUN --select-only --select BRANCH:INDEX</code>.</p>"
            + _table(["branch", "operation", "from", "instruction", "seed", "status",
                      "snapshots at r"], rows, "tree")
            + "".join(strips)
            + "<div>" + _img(tree_plot(lines, schedule.get("threshold")), "branch difficulties",
                             "plot") + "</div>")


def _local_body(run_dir: Path, local: dict, *, thumb_px: int, max_views: int) -> str:
    """A local edit's figures (schedule.json's ``"local"``) and its region over the test views."""
    uri = _grid_uri(_pngs(run_dir / "local"), thumb_px, max_views)
    figures = {k: (", ".join(v) if isinstance(v, list) else v) for k, v in local.items()}
    body = ("<p>Only the editable Gaussians changed; the others were frozen (bit for bit the "
            "input). Red: the region, the rendered relevance of the editable Gaussians at the "
            "held-out views.</p>" + _kv_table(figures))
    return body + (_img(uri, "relevance over the held-out views") if uri
                   else '<p class="missing">no relevance images recorded</p>')


# Any other run (e.g. a reconstruction)
def _generic_sections(run_dir: Path, *, thumb_px: int, max_views: int,
                      turntable_px: int, max_frames: int) -> list[tuple[str, str, str]]:
    config = read_json(run_dir / "config.json", required=False)
    metrics = read_json(run_dir / "metrics.json", required=False) or {}
    sections = [("run", "Run", _reproduce(config))]
    # Test-view renders: renders/ (snapshots, render command: frames/) or test/ (reconstruct).
    folder = next((run_dir / f for f in ("renders", "test", "frames") if (run_dir / f).is_dir()),
                  None)
    views = _grid_uri(_pngs(folder), thumb_px, max_views)
    depth = _grid_uri(_pngs(run_dir / "depth"), thumb_px, max_views)
    body = _img(views, "test-view renders")
    if (run_dir / "test_compare.png").is_file():
        body += ('<div class="row-label">ground truth vs render</div>'
                 + _img(image_uri(_load_thumb(run_dir / "test_compare.png", 4 * thumb_px)),
                        "comparison"))
    if depth:
        body += '<div class="row-label">depth</div>' + _img(depth, "depth maps")
    tt = _turntable_uri(run_dir / "turntable.webp", turntable_px, max_frames)
    if tt:
        body += '<div class="row-label">turntable</div>' + _img(tt, "turntable")
    sections.append(("views", "Views", body))
    if (run_dir / "train_log.jsonl").is_file():
        plot = training_plot(read_train_log(run_dir / "train_log.jsonl"))
        if plot:
            sections.append(("training", "Training", _img(plot, "training curves", "plot")))
    sections.append(("metrics", "Metrics",
                     _kv_table(metrics) if metrics else '<p class="missing">no metrics.json</p>'))
    return sections
