"""``report.html``: one self-contained page per run directory (images inlined as
``data:`` URIs, inline CSS and JavaScript, nothing from the network), for a person to
judge an edit offline. A layer above the library reports a run kind of its own by passing
``write_report(run_dir, sections=...)``, built from the blocks exported here."""

from __future__ import annotations

from pathlib import Path

from ...errors import DataError
from ...io.files import atomic_write_text
from .html import _e, _page
from .images import image_uri
from .plots import difficulty_plot, training_plot
from .rundir import _check_schedule, read_json, read_train_log
from .sections import _edit_sections, _generic_sections

# The page's building blocks, public for the sections of a run kind outside the library.
from .html import _e as escape, _img as img, _kv_table as kv_table, _reproduce as reproduce
from .html import _table as table
from .images import _figure_uri as figure_uri, _load_thumb as load_thumb
from .rundir import _is_number as is_number

#: Default budget of the page; thumbnails shrink until it fits.
MAX_BYTES = 10_000_000


def write_report(run_dir, *, out=None, title: str | None = None, notes: dict | None = None,
                 thumb_px: int = 192, max_views: int = 8, turntable_px: int = 192,
                 max_frames: int = 48, max_bytes: int = MAX_BYTES,
                 config_path=None, sections=None) -> Path:
    """Write the self-contained ``report.html`` of a run directory.

    Args:
      run_dir: an edit (``schedule.json``) or other run directory (``metrics.json``).
      out: where to write (default ``run_dir/report.html``).
      title: page title (default from the run).
      notes: extra name -> value pairs shown with the instruction.
      thumb_px: longest side of each view in the galleries.
      max_views: at most this many test views per row (evenly spread).
      turntable_px, max_frames: turntables larger than this are re-encoded.
      max_bytes: when the page exceeds it, thumbnails shrink and it is rebuilt.
      config_path: the config.json whose command line reproduces the run (default
        ``run_dir/config.json``).
      sections: builds the page instead of the edit or generic sections (a run kind of a
        layer above the library): ``sections(run_dir, *, thumb_px, max_views, turntable_px,
        max_frames) -> [(anchor, title, html)]``, called again at smaller sizes while the
        page is over ``max_bytes``; it raises DataError on malformed run data.
    Returns:
      The path written.
    Raises:
      DataError: no run data in ``run_dir``, or malformed JSON files.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError(run_dir, "run directory does not exist")
    out = run_dir / "report.html" if out is None else Path(out)
    schedule_path = run_dir / "schedule.json"
    if sections is None and not (schedule_path.is_file() or (run_dir / "metrics.json").is_file()):
        raise DataError(run_dir, "not a run directory (no schedule.json or metrics.json)")

    sizes = dict(thumb_px=thumb_px, max_views=max_views, turntable_px=turntable_px,
                 max_frames=max_frames)
    while True:
        if sections is not None:
            parts = sections(run_dir, **sizes)
            page_title = title or f"jaxedit run: {run_dir.name}"
        elif schedule_path.is_file():
            schedule = _check_schedule(schedule_path, read_json(schedule_path))
            parts = _edit_sections(run_dir, schedule, notes=notes,
                                   config_path=None if config_path is None else Path(config_path),
                                   **sizes)
            page_title = title or f"jaxedit edit: {schedule.get('prompt', run_dir.name)}"
        else:
            parts = _generic_sections(run_dir, **sizes)
            page_title = title or f"jaxedit run: {run_dir.name}"
        body = "\n".join(f'<section id="{a}"><h2>{_e(t)}</h2>\n{h}\n</section>'
                         for a, t, h in parts)
        text = _page(page_title, [(a, t) for a, t, _ in parts], body)
        if len(text) <= max_bytes or sizes["thumb_px"] <= 48:
            break
        sizes = {**sizes, "thumb_px": int(sizes["thumb_px"] * 0.7),
                 "turntable_px": int(sizes["turntable_px"] * 0.7),
                 "max_frames": max(12, int(sizes["max_frames"] * 0.7))}
    atomic_write_text(out, text)
    return out


__all__ = ["MAX_BYTES", "difficulty_plot", "escape", "figure_uri", "image_uri", "img",
           "is_number", "kv_table", "load_thumb", "read_json", "read_train_log", "reproduce",
           "table", "training_plot", "write_report"]
