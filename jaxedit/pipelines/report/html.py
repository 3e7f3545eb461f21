"""The page's HTML pieces: tables, sliders, images, inline CSS/JS and the page shell."""

from __future__ import annotations

import datetime as _dt
import html
import json
import math
import shlex

from .rundir import _is_number


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
    """A range input that shows one of ``frames`` = [(label, inner_html)] at a time
    (``start``, default the last, without JavaScript)."""
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
        f"<footer>written by jaxedit.pipelines.report on {stamp}; self-contained (no network)</footer>\n"
        f"</main>\n<script>{_JS}</script>\n</body>\n</html>\n")


def _reproduce(config: dict | None) -> str:
    if not config:
        return '<p class="missing">no config.json in this run directory</p>'
    cmd = ["python", "-m", "experiments"] + [str(a) for a in config.get("argv", [])]
    version = config.get("jaxedit_version", "?")
    return (f"<p>jaxedit {_e(version)}. Reproduce with <code>{_e(shlex.join(cmd))}</code> "
            "(the resolved flags are in <code>config.json</code>).</p>")
