"""``report.html``: one self-contained page per run directory.

The page is what a person opens to judge an edit. It holds the instruction,
the subtask schedule, a plot of the difficulty d(0, r) with the chosen ratios,
an aggressivity gallery (a slider over subtasks showing the same test views
under the original ones), the depth maps, the turntables and the metrics. For an
ablation run directory (``ablation.json`` of ``python -m experiments ablation``) it
shows the statistics: means with 95% confidence intervals per method and the
paired differences, as tables and a plot.

Self-contained: every image is inlined as a base64 ``data:`` URI, the only
script is a dozen lines of inline JavaScript (the sliders), the only style is
inline CSS, and nothing refers to the network, so the file can be mailed,
archived or opened offline. Images are downscaled (thumbnails of at most
``thumb_px`` pixels, JPEG) so the page stays small (a few MB).

Run-directory layout read here (written by the edit driver)::

    config.json      {"command", "argv", "flags", "jaxedit_version"}   (optional)
    schedule.json    {"prompt", "editor", "mode", "threshold", "difficulty_curve": [[r, d], ...],
                      "subtasks": [{"index", "name", "ratio", "difficulty", "steps", "seconds",
                                    "converged", "snapshot": "subtasks/02_r0.500/scene.ply"}]}
    metrics.json     {name: number, ...}
    original/renders/*.png, original/depth/*.png (optional)
    subtasks/NN_rX.XXX/{renders/*.png, depth/*.png, turntable.webp, metrics.json}
    ablation.json    {settings, runs, summary, differences} (experiments/ablation.py),
                     views/*.png
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import json
import math
import shlex
from pathlib import Path

import numpy as np

from .errors import DataError
from .io.files import atomic_write_text

#: Default budget of the page; thumbnails shrink until it fits.
MAX_BYTES = 10_000_000


# ---------------------------------------------------------------------------
# Reading the run directory
# ---------------------------------------------------------------------------
def read_json(path: Path, *, required: bool = True):
    """Parsed JSON, None when absent and not required; DataError when malformed."""
    path = Path(path)
    if not path.exists():
        if required:
            raise DataError(path, "missing")
        return None
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise DataError(path, f"cannot read ({e.strerror or e})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(path, f"malformed JSON ({e})") from None


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _check_schedule(path: Path, schedule) -> dict:
    """Validate the fields the report uses; one-line DataError otherwise."""
    if not isinstance(schedule, dict):
        raise DataError(path, "must be a JSON object")
    subtasks = schedule.get("subtasks", [])
    if not isinstance(subtasks, list):
        raise DataError(path, "'subtasks' must be a list")
    for i, s in enumerate(subtasks):
        if not isinstance(s, dict):
            raise DataError(path, f"subtasks[{i}] must be an object")
        if not _is_number(s.get("ratio")):
            raise DataError(path, f"subtasks[{i}].ratio must be a number, got {s.get('ratio')!r}")
        for key in ("difficulty", "seconds", "steps"):
            if s.get(key) is not None and not _is_number(s[key]):
                raise DataError(path, f"subtasks[{i}].{key} must be a number or null")
        if s.get("snapshot") is not None and not isinstance(s["snapshot"], str):
            raise DataError(path, f"subtasks[{i}].snapshot must be a path string")
    curve = schedule.get("difficulty_curve") or []
    if not isinstance(curve, list) or not all(
            isinstance(p, (list, tuple)) and len(p) == 2 and all(_is_number(v) or v is None for v in p)
            for p in curve):
        raise DataError(path, "'difficulty_curve' must be a list of [r, d] pairs")
    if schedule.get("threshold") is not None and not _is_number(schedule["threshold"]):
        raise DataError(path, "'threshold' must be a number or null")
    return schedule


def _snapshot_dir(run_dir: Path, subtask: dict, position: int) -> Path | None:
    """The folder of a subtask's snapshot: from its 'snapshot' path, else by index."""
    snap = subtask.get("snapshot")
    if snap:
        p = Path(snap)
        p = p if p.is_absolute() else run_dir / p
        return p.parent if p.suffix else p
    index = subtask.get("index", position)
    found = sorted((run_dir / "subtasks").glob(f"{int(index):02d}_*"))
    return found[0] if found else None


def _pngs(folder: Path | None) -> list[Path]:
    if folder is None or not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))


# ---------------------------------------------------------------------------
# Images -> data URIs
# ---------------------------------------------------------------------------
def _load_thumb(path: Path, thumb_px: int) -> np.ndarray:
    """float32 [h, w, 3] in [0, 1], the image at ``path`` shrunk to fit thumb_px."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im = im.convert("RGBA")
            # Composite transparency over white, like the renders' default background.
            flat = Image.new("RGBA", im.size, (255, 255, 255, 255))
            flat.alpha_composite(im)
            im = flat.convert("RGB")
            # Shrink big views to thumb_px; enlarge tiny ones (at most 4x) so they stay legible.
            scale = min(thumb_px / max(im.size), 4.0)
            if scale < 1.0 or scale >= 1.25:
                size = (max(1, round(im.size[0] * scale)), max(1, round(im.size[1] * scale)))
                im = im.resize(size, Image.Resampling.LANCZOS)
            return np.asarray(im, np.float32) / 255.0
    except (OSError, ValueError) as e:
        raise DataError(path, f"cannot read image ({e})") from None


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def image_uri(image, *, fmt: str = "JPEG", quality: int = 88) -> str:
    """A float [H, W, 3] in [0, 1] (or uint8) image as a data URI (JPEG or PNG)."""
    from PIL import Image

    from .viz import to_uint8

    buf = io.BytesIO()
    Image.fromarray(to_uint8(image)).save(buf, format=fmt, quality=quality, optimize=True)
    return data_uri(buf.getvalue(), "image/jpeg" if fmt == "JPEG" else "image/png")


def _grid_uri(paths: list[Path], thumb_px: int, max_views: int, ncols: int | None = None) -> str | None:
    from .viz import image_grid

    if not paths:
        return None
    paths = _spread(paths, max_views)
    thumbs = [_load_thumb(p, thumb_px) for p in paths]
    return image_uri(image_grid(thumbs, ncols or len(thumbs), pad=2))


def _spread(items: list, k: int) -> list:
    """At most ``k`` items evenly spread over the list (first and last kept)."""
    if len(items) <= k:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, k)).astype(int))
    return [items[i] for i in idx]


def _turntable_uri(path: Path, turntable_px: int, max_frames: int) -> str | None:
    """The turntable WebP inlined; re-encoded smaller when it is large."""
    from PIL import Image

    from .viz import encode_webp, read_webp

    if not path.is_file():
        return None
    frames, durations = read_webp(path)
    seconds = float(durations.sum()) / 1000.0 or len(frames) / 12.0
    if frames.shape[1] <= turntable_px and frames.shape[2] <= turntable_px and len(frames) <= max_frames:
        return data_uri(path.read_bytes(), "image/webp")
    frames = frames[np.round(np.linspace(0, len(frames), min(len(frames), max_frames),
                                         endpoint=False)).astype(int)]
    scale = min(1.0, turntable_px / max(frames.shape[1:3]))
    size = (max(1, round(frames.shape[2] * scale)), max(1, round(frames.shape[1] * scale)))
    small = np.stack([np.asarray(Image.fromarray(f).resize(size, Image.Resampling.LANCZOS))
                      for f in frames])
    # Same orbit duration with fewer frames.
    return data_uri(encode_webp(small, fps=len(small) / max(seconds, 1e-3)), "image/webp")


# ---------------------------------------------------------------------------
# Plots
# ---------------------------------------------------------------------------
def _figure_uri(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return data_uri(buf.getvalue(), "image/png")


def difficulty_plot(schedule: dict) -> str:
    """PNG data URI: d(0, r) over r with the chosen ratios marked, and the
    difficulty of each subtask against the threshold."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    curve = sorted((float(r), float(d)) for r, d in (schedule.get("difficulty_curve") or [])
                   if r is not None and d is not None)
    subtasks = schedule.get("subtasks", [])
    ratios = [float(s["ratio"]) for s in subtasks]
    threshold = schedule.get("threshold")
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.4), gridspec_kw={"width_ratios": [3, 2]})
    if curve:
        rs, ds = np.array(curve).T
        ax0.plot(rs, ds, "-", color="#555555", lw=1.5, label="d(0, r) measured", zorder=1)
        ax0.plot(rs, ds, ".", color="#555555", ms=5, zorder=1)
        marks = np.interp(ratios, rs, ds) if ratios else []
        ax0.scatter(ratios, marks, s=55, color="#d62728", zorder=3, label="chosen ratios r_i")
        # One label per distinct ratio (r_n repeats r = 1 to consolidate).
        groups: dict[float, list[str]] = {}
        for s, r, d in zip(subtasks, ratios, marks):
            groups.setdefault(round(r, 6), []).append(str(s.get("name", "")))
        for r, names_at in groups.items():
            ax0.annotate(", ".join(names_at), (r, float(np.interp(r, rs, ds))),
                         textcoords="offset points", xytext=(-4 if r > 0.9 else 0, 7),
                         ha="right" if r > 0.9 else "center", fontsize=8)
    else:
        ax0.text(0.5, 0.5, "no difficulty curve recorded\n(uniform or single-subtask schedule)",
                 ha="center", va="center", transform=ax0.transAxes, color="#777777")
    for r in ratios:
        ax0.axvline(r, color="#d62728", ls=":", lw=0.8, zorder=0)
    ax0.set_xlim(-0.02, 1.02)
    ax0.set_xlabel("ratio r")
    ax0.set_ylabel("difficulty $d(0, r)$")
    ax0.set_title("Difficulty of reaching r from the original")
    if curve:
        ax0.legend(loc="upper left", fontsize=8)
    diffs = [s.get("difficulty") for s in subtasks]
    names = [str(s.get("name", i)) for i, s in enumerate(subtasks)]
    xs = np.arange(len(subtasks))
    ax1.bar(xs, [d if d is not None else 0.0 for d in diffs],
            color=["#1f77b4" if d is not None else "#cccccc" for d in diffs])
    if threshold is not None:
        ax1.axhline(float(threshold), color="#d62728", ls="--", lw=1, label=f"threshold {threshold:g}")
        ax1.legend(loc="best", fontsize=8)
    ax1.set_xticks(xs, names, rotation=45 if len(xs) > 6 else 0, fontsize=8)
    ax1.set_ylabel("$d(r_{i-1}, r_i)$")
    ax1.set_title("Difficulty of each subtask")
    fig.tight_layout()
    return _figure_uri(fig)


ABLATION_METHODS = ("proedit", "nd", "nd_equal", "nd_k", "uniform", "in2n", "nd_equal_steps")
_METHOD_COLOURS = {"proedit": "#d62728", "nd": "#1f77b4", "nd_equal": "#2ca02c",
                   "nd_k": "#17becf", "uniform": "#ff7f0e", "in2n": "#9467bd",
                   "nd_equal_steps": "#8c564b"}


def _summary_index(rows: list[dict]) -> dict:
    return {(r["editor_modes"], r["scene"], r["prompt"], r["method"], r["metric"]): r
            for r in rows}


def ablation_plot(summary: list[dict], *, metrics=("psnr_best", "mode_mixing")) -> str | None:
    """PNG data URI: per editor-modes setting (rows) and metric (columns), the mean and 95%
    CI of every method per scene and instruction (error bars, methods side by side)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    index = _summary_index(summary)
    modes = sorted({r["editor_modes"] for r in summary})
    metrics = [m for m in metrics if any(r["metric"] == m for r in summary)]
    if not modes or not metrics:
        return None
    groups = list(dict.fromkeys((r["scene"], r["prompt"]) for r in summary))
    methods = [m for m in ABLATION_METHODS if any(r["method"] == m for r in summary)]
    fig, axes = plt.subplots(len(modes), len(metrics), squeeze=False,
                             figsize=(max(8.0, 0.55 * len(groups) * len(metrics) + 3),
                                      2.9 * len(modes)))
    width = 0.8 / max(len(methods), 1)
    for i, k in enumerate(modes):
        for j, metric in enumerate(metrics):
            ax = axes[i][j]
            for n, method in enumerate(methods):
                xs, ys, es = [], [], []
                for g, (scene, prompt) in enumerate(groups):
                    r = index.get((k, scene, prompt, method, metric))
                    if r is not None:
                        xs.append(g + (n - (len(methods) - 1) / 2) * width)
                        ys.append(r["mean"])
                        es.append(r["ci"] or 0.0)
                ax.errorbar(xs, ys, yerr=es, fmt="o", ms=4, capsize=2, lw=1,
                            color=_METHOD_COLOURS.get(method, "#555555"), label=method)
            ax.set_xticks(range(len(groups)),
                          [f"{sc}: {pr[:18]}" for sc, pr in groups], rotation=40, ha="right",
                          fontsize=7)
            ax.set_title(f"editor modes = {k}: {metric}", fontsize=9)
            ax.set_ylabel("0: one mode, 1: even blend" if metric == "mode_mixing"
                          else "higher is better", fontsize=8)
            ax.tick_params(axis="y", labelsize=8)
            for g in range(1, len(groups)):
                ax.axvline(g - 0.5, color="#eeeeee", lw=0.8, zorder=0)
    axes[0][0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return _figure_uri(fig)


def ablation_table(summary: list[dict], differences: list[dict], *, editor_modes: int,
                   metric: str, digits: int = 2) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of plain-text cells: one row per (scene, instruction), the mean ± 95% CI
    of every method, then the paired difference proedit - other (``*``: its CI excludes 0)."""
    index, dindex = _summary_index(summary), _summary_index(differences)
    groups = list(dict.fromkeys((r["scene"], r["prompt"]) for r in summary
                                if r["editor_modes"] == editor_modes))
    methods = [m for m in ABLATION_METHODS
               if (editor_modes, *groups[0], m, metric) in index] if groups else []
    others = [m for m in methods if m != "proedit"]

    def cell(r, mark=False):
        if r is None:
            return "-"
        ci = "" if r["ci"] is None else f" ± {r['ci']:.{digits}f}"
        sig = mark and r["ci"] is not None and abs(r["mean"]) > r["ci"]
        return f"{r['mean']:.{digits}f}{ci}" + (" *" if sig else "")

    header = ["scene", "instruction"] + methods + [f"proedit − {m}" for m in others]
    rows = [[scene, prompt] + [cell(index.get((editor_modes, scene, prompt, m, metric)))
                               for m in methods]
            + [cell(dindex.get((editor_modes, scene, prompt, m, metric)), True) for m in others]
            for scene, prompt in groups]
    return header, rows


# ---------------------------------------------------------------------------
# HTML pieces
# ---------------------------------------------------------------------------
def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _fmt(x) -> str:
    if x is None:
        return "&mdash;"
    if isinstance(x, bool):
        return "yes" if x else "<b>no</b>"
    if isinstance(x, float):
        if not math.isfinite(x):
            return _e(x)
        return f"{x:.4g}" if abs(x) < 1e5 else f"{x:.3e}"
    if isinstance(x, list) and all(_is_number(v) for v in x):
        return "[" + ", ".join(_fmt(v) for v in x) + "]"
    if isinstance(x, (list, dict)):
        return _e(json.dumps(x))
    return _e(x)


def _metric_names(rows) -> list[str]:
    names: list[str] = []
    for row in rows:
        for k, v in (row or {}).items():
            if k not in names and (_is_number(v) or isinstance(v, (str, bool)) or v is None):
                names.append(k)
    return names


def _table(header: list[str], rows: list[list[str]], cls: str = "") -> str:
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _flat(d: dict, prefix: str = "") -> dict:
    """Nested dicts as one level with dotted keys (``utilisation.edits``)."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict) and v:
            out.update(_flat(v, key))
        else:
            out[key] = v
    return out


def _kv_table(d: dict) -> str:
    return _table(["name", "value"], [[_e(k), _fmt(v)] for k, v in _flat(d).items()], "kv")


def _slider(sid: str, frames: list[tuple[str, str]], start: int | None = None) -> str:
    """A range input that shows one of ``frames`` = [(label, inner_html)] at a time.

    Without JavaScript every frame but ``start`` stays hidden, so the page still
    shows something sensible (the most aggressive level by default).
    """
    if not frames:
        return '<p class="missing">nothing recorded</p>'
    start = len(frames) - 1 if start is None else start
    parts = [f'<div class="slider" id="{sid}">',
             f'<div class="controls"><input type="range" min="0" max="{len(frames) - 1}" '
             f'step="1" value="{start}" aria-label="subtask"> '
             f'<span class="slider-label">{_e(frames[start][0])}</span></div>']
    for i, (label, inner) in enumerate(frames):
        hidden = "" if i == start else ' style="display:none"'
        parts.append(f'<div class="frame" data-label="{_e(label)}"{hidden}>{inner}</div>')
    parts.append("</div>")
    return "\n".join(parts)


def _img(uri: str | None, alt: str, cls: str = "") -> str:
    if uri is None:
        return f'<p class="missing">{_e(alt)}: not recorded</p>'
    return f'<img class="{cls}" src="{uri}" alt="{_e(alt)}">'


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;background:#fafafa;color:#222}
main{max-width:1240px;margin:0 auto;padding:16px 24px 48px}
h1{font-size:1.5em;margin:.4em 0}h2{font-size:1.2em;border-bottom:1px solid #ddd;padding-bottom:4px;margin-top:1.6em}
.instruction{font-size:1.35em;background:#fff;border-left:5px solid #d62728;padding:8px 14px;margin:8px 0}
table{border-collapse:collapse;background:#fff;font-size:.92em;margin:6px 0}
td,th{border:1px solid #ddd;padding:3px 9px;text-align:right}th{background:#f0f0f0}
td:first-child,th:first-child{text-align:left}.best{background:#e3f4e1;font-weight:600}
img{max-width:100%;image-rendering:auto}.plot{max-width:100%}
.slider .controls{margin:6px 0 8px}.slider input{width:min(600px,80%);vertical-align:middle}
.slider-label{font-weight:600;margin-left:8px}.row-label{font-size:.85em;color:#555;margin:4px 0 1px}
.cards{display:flex;flex-wrap:wrap;gap:12px}.card{background:#fff;border:1px solid #ddd;padding:6px;margin:0}
.card img{width:192px;height:auto}.card figcaption{font-size:.85em;text-align:center;color:#444}.missing{color:#999;font-style:italic}
code{background:#f0f0f0;padding:1px 4px;border-radius:3px;font-size:.9em;word-break:break-all}
nav a{margin-right:12px}footer{color:#888;font-size:.8em;margin-top:32px}
.compare td{text-align:left;vertical-align:middle}.compare th{text-align:left}
"""

_JS = """
document.querySelectorAll('.slider').forEach(function (s) {
  var input = s.querySelector('input[type=range]');
  var frames = s.querySelectorAll('.frame');
  var label = s.querySelector('.slider-label');
  function show() {
    frames.forEach(function (f, i) { f.style.display = (i == input.value) ? 'block' : 'none'; });
    label.textContent = frames[input.value].getAttribute('data-label');
  }
  input.addEventListener('input', show);
  show();
});
"""


def _page(title: str, nav: list[tuple[str, str]], body: str) -> str:
    links = "".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in nav)
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{_e(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n<main>\n"
        f"<h1>{_e(title)}</h1>\n<nav>{links}</nav>\n{body}\n"
        f"<footer>written by jaxedit.report on {stamp}; self-contained (no network)</footer>\n"
        f"</main>\n<script>{_JS}</script>\n</body>\n</html>\n")


def _reproduce(config: dict | None) -> str:
    if not config:
        return '<p class="missing">no config.json in this run directory</p>'
    cmd = ["python", "-m", "experiments"] + [str(a) for a in config.get("argv", [])]
    version = config.get("jaxedit_version", "?")
    return (f"<p>jaxedit {_e(version)}. Reproduce with <code>{_e(shlex.join(cmd))}</code> "
            "(the resolved flags are in <code>config.json</code>).</p>")


# The last difficulty plot drawn: write_report rebuilds the page at smaller
# image sizes when it is over budget, and the plot does not depend on them.
_PLOT_MEMO: dict = {}


# ---------------------------------------------------------------------------
# Edit run report
# ---------------------------------------------------------------------------
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

    # Instruction ---------------------------------------------------------
    info = {"editor": schedule.get("editor"), "mode": schedule.get("mode"),
            "threshold": schedule.get("threshold"), "subtasks": len(subtasks)}
    # The level of aggressivity the user picked (edit --select), if any: sliders start there.
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

    # Schedule ------------------------------------------------------------
    rows, total_s, total_steps = [], 0.0, 0
    for i, s in enumerate(subtasks):
        total_s += float(s.get("seconds") or 0.0)
        total_steps += int(s.get("steps") or 0)
        snap = s.get("snapshot")
        name = _e(s.get("name", "")) + (" &#9733;" if i == start else "")
        rows.append([_e(s.get("index", i)), name, f"{float(s['ratio']):.4f}",
                     _fmt(s.get("difficulty")), _fmt(s.get("steps")), _fmt(s.get("seconds")),
                     _fmt(s.get("converged")), f"<code>{_e(snap)}</code>" if snap else "&mdash;"])
    rows.append(["", "<b>total</b>", "", "", _fmt(total_steps), _fmt(round(total_s, 2)), "", ""])
    body = _table(["#", "subtask", "ratio r", "difficulty d(r<sub>i-1</sub>, r<sub>i</sub>)",
                   "iterations", "seconds", "converged", "snapshot"], rows, "schedule")
    unconverged = [s.get("name", i) for i, s in enumerate(subtasks) if s.get("converged") is False]
    if unconverged:
        body += ("<p>Not converged (the max-steps guard fired before the loss plateaued): "
                 f"{_e(', '.join(map(str, unconverged)))}.</p>")
    sections.append(("schedule", "Schedule", body))

    # Difficulty plot (the same at every size: drawn once per schedule) -------
    key = json.dumps(schedule, sort_keys=True, default=str)
    if _PLOT_MEMO.get("key") != key:
        _PLOT_MEMO.update(key=key, uri=difficulty_plot(schedule))
    sections.append(("difficulty", "Difficulty and chosen ratios",
                     _img(_PLOT_MEMO["uri"], "difficulty plot", "plot")))

    # Aggressivity gallery ----------------------------------------------------
    original = _pngs(run_dir / "original" / "renders")
    orig_uri = _grid_uri(original, thumb_px, max_views)
    frames = []
    for label, d in zip(labels, snap_dirs):
        uri = _grid_uri(_pngs(d / "renders" if d else None), thumb_px, max_views)
        # The snapshot's headline numbers help choose a level, next to its pictures.
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

    # Depth maps ----------------------------------------------------------
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

    # Turntables ----------------------------------------------------------
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

    # Metrics -------------------------------------------------------------
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


# ---------------------------------------------------------------------------
# Ablation report
# ---------------------------------------------------------------------------
#: What the simulated ablation can and cannot show (shown on every ablation page).
SIMULATION_NOTE = (
    "The editor here is jaxedit's simulated editor, a test instrument with known noise-free "
    "targets, not InstructPix2Pix. With <b>editor modes = 1</b> each instruction has one "
    "outcome and views differ only by noise that shrinks as the render approaches the target; "
    "with <b>editor modes = K &gt; 1</b> each edit call draws one of K discrete, individually "
    "3D-consistent outcomes, with probabilities that follow how close the current render is "
    "to each (jaxedit.edit.simulated, section 4). The ablation therefore tests how the editing "
    "machinery (schedule, iterative dataset update, adaptive 3DGS) responds to divergent modes "
    "of a known size. It cannot show how large a real diffusion model's feasible output space "
    "is, how its modes are distributed, or how the difficulty measure tracks them; scores are "
    "against the simulated targets only, on small CPU-sized scenes.")


def _ablation_sections(run_dir: Path, ablation: dict, *, thumb_px: int, max_views: int,
                       turntable_px: int, max_frames: int) -> list[tuple[str, str, str]]:
    path = run_dir / "ablation.json"
    if not (isinstance(ablation, dict) and isinstance(ablation.get("runs"), list)
            and isinstance(ablation.get("summary", []), list)
            and isinstance(ablation.get("differences", []), list)):
        raise DataError(path, "must be an object {settings, runs: [...], summary: [...], "
                              "differences: [...]} (python -m experiments ablation)")
    need = ("editor_modes", "scene", "prompt", "method", "metric", "mean", "ci")
    for name in ("summary", "differences"):
        for i, r in enumerate(ablation.get(name, [])):
            if not isinstance(r, dict) or any(k not in r for k in need) \
                    or not _is_number(r["mean"]) or not (r["ci"] is None or _is_number(r["ci"])):
                raise DataError(path, f"{name}[{i}] needs {', '.join(need)} (numbers for "
                                      f"mean and ci)")
    summary, differences = ablation.get("summary", []), ablation.get("differences", [])
    settings = ablation.get("settings") or {}
    config = read_json(run_dir / "config.json", required=False)
    body = (f"<p>{SIMULATION_NOTE}</p><p>{len(ablation['runs'])} edit runs; means and "
            "Student-t 95% confidence intervals over seeds; differences are paired by seed "
            "(proedit minus the other method); &ldquo;all&rdquo; averages the instructions of "
            "a seed first.</p>" + _reproduce(config))
    if settings:
        body += "<h3>Settings</h3>" + _kv_table(settings)
    sections = [("instruction", "Ablation", body)]
    if not summary:
        sections.append(("metrics", "Statistics", '<p class="missing">no summary yet (the run '
                                                  "has not finished)</p>"))
        return sections

    body = ""
    for k in sorted({r["editor_modes"] for r in summary}):
        for metric, digits in (("psnr_best", 2), ("ssim_best", 3), ("mode_mixing", 3),
                               ("multiview_consistency", 2), ("total_steps", 0)):
            header, rows = ablation_table(summary, differences, editor_modes=k, metric=metric,
                                          digits=digits)
            if not rows or len(header) <= 2:
                continue
            body += (f"<h3>editor modes = {k}: {_e(metric)}</h3>"
                     + _table([_e(h) for h in header], [[_e(c) for c in row] for row in rows],
                              "ablation"))
    body += ("<p>psnr_best / ssim_best: best over modes of the per-scene score against that "
             "mode's noise-free target at r = 1 (higher is better); mode_mixing: 0 when the "
             "result is one mode, 1 for an even blend of all; multiview_consistency: "
             "reprojection PSNR between neighbouring test views (dB). <b>*</b>: the 95% CI of "
             "the paired difference excludes 0.</p>")
    plot = ablation_plot(summary)
    if plot:
        body += _img(plot, "means and 95% CIs per method", "plot")
    sections.append(("metrics", "Statistics", body))

    views = sorted((run_dir / "views").glob("*.png")) if (run_dir / "views").is_dir() else []
    if views:
        methods = settings.get("methods") or list(ABLATION_METHODS)
        rows = [[f"<b>{_e(p.stem)}</b>",
                 _img(image_uri(_load_thumb(p, 6 * thumb_px)), p.stem)] for p in views]
        body = (f"<p>Seed 0, test views. Rows of each image: the noise-free target of every "
                f"mode at r = 1, then the final scene of {_e(', '.join(methods))}.</p>"
                + _table(["run", "targets, then methods"], rows, "compare"))
        sections.append(("compare", "Views", body))
    return sections


# ---------------------------------------------------------------------------
# Generic run (e.g. a reconstruction)
# ---------------------------------------------------------------------------
def read_train_log(path: Path) -> list[dict]:
    """Records of a JSON-lines training log (one object per line); DataError when malformed."""
    records = []
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise DataError(path, f"cannot read ({e.strerror or e})") from None
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as e:
            if i == len(lines) - 1:  # a run killed mid-write leaves a partial last line
                break
            raise DataError(path, f"line {i + 1}: malformed JSON ({e})") from None
        if isinstance(rec, dict):
            records.append(rec)
    return records


def training_plot(records: list[dict]) -> str | None:
    """PNG data URI: loss, PSNR and Gaussian count over the training steps."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    keys = [k for k in ("loss", "psnr", "num_gaussians")
            if any(_is_number(r.get(k)) for r in records)]
    if not keys or not any(_is_number(r.get("step")) for r in records):
        return None
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 2.8), squeeze=False)
    for ax, k in zip(axes[0], keys):
        pts = [(r["step"], r[k]) for r in records if _is_number(r.get("step")) and _is_number(r.get(k))]
        xs, ys = zip(*pts)
        ax.plot(xs, ys, lw=1.2, color="#1f77b4")
        ax.set_xlabel("step")
        ax.set_title({"loss": "training loss", "psnr": "training PSNR (dB)",
                      "num_gaussians": "Gaussians"}[k], fontsize=10)
        if k == "loss" and min(ys) > 0:
            ax.set_yscale("log")
    fig.tight_layout()
    return _figure_uri(fig)


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


# ---------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------
def write_report(run_dir, *, out=None, title: str | None = None, notes: dict | None = None,
                 thumb_px: int = 192, max_views: int = 8, turntable_px: int = 192,
                 max_frames: int = 48, max_bytes: int = MAX_BYTES,
                 config_path=None) -> Path:
    """Write the self-contained ``report.html`` of a run directory.

    Args:
      run_dir: an edit run directory (``schedule.json``), an ablation run
        directory (``ablation.json``, ``views/``), or any run
        directory with ``metrics.json`` and ``renders/``.
      out: where to write (default ``run_dir/report.html``).
      title: page title (default from the run).
      notes: extra name -> value pairs shown with the instruction (e.g. timings).
      thumb_px: longest side of each view in the galleries.
      max_views: at most this many test views per row (evenly spread).
      turntable_px, max_frames: turntables larger than this are re-encoded.
      max_bytes: when the page exceeds it, thumbnails shrink and it is rebuilt.
      config_path: the config.json whose command line the page shows as the way
        to reproduce the run (default ``run_dir/config.json``; the demo points it
        at its own).
    Returns:
      The path written.
    Raises:
      DataError: no run data in ``run_dir``, or malformed JSON files.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError(run_dir, "run directory does not exist")
    out = run_dir / "report.html" if out is None else Path(out)
    ablation = read_json(run_dir / "ablation.json", required=False)
    schedule_path = run_dir / "schedule.json"
    if ablation is None and not schedule_path.is_file() and not (run_dir / "metrics.json").is_file():
        raise DataError(run_dir, "not a run directory (no schedule.json, ablation.json or metrics.json)")

    sizes = dict(thumb_px=thumb_px, max_views=max_views, turntable_px=turntable_px,
                 max_frames=max_frames)
    while True:
        if ablation is not None:
            sections = _ablation_sections(run_dir, ablation, **sizes)
            page_title = title or f"jaxedit ablation: {run_dir.name}"
        elif schedule_path.is_file():
            schedule = _check_schedule(schedule_path, read_json(schedule_path))
            sections = _edit_sections(run_dir, schedule, notes=notes,
                                      config_path=None if config_path is None else Path(config_path),
                                      **sizes)
            page_title = title or f"jaxedit edit: {schedule.get('prompt', run_dir.name)}"
        else:
            sections = _generic_sections(run_dir, **sizes)
            page_title = title or f"jaxedit run: {run_dir.name}"
        body = "\n".join(f'<section id="{a}"><h2>{_e(t)}</h2>\n{h}\n</section>'
                         for a, t, h in sections)
        text = _page(page_title, [(a, t) for a, t, _ in sections], body)
        if len(text) <= max_bytes or sizes["thumb_px"] <= 48:
            break
        # Too big: shrink every image by ~30% and try again (a handful of rounds at most).
        sizes = {**sizes, "thumb_px": int(sizes["thumb_px"] * 0.7),
                 "turntable_px": int(sizes["turntable_px"] * 0.7),
                 "max_frames": max(12, int(sizes["max_frames"] * 0.7))}
    atomic_write_text(out, text)
    return out


__all__ = ["MAX_BYTES", "SIMULATION_NOTE", "ablation_plot", "ablation_table", "difficulty_plot",
           "image_uri", "read_json", "read_train_log", "training_plot", "write_report"]
