"""report.html from synthetic run directories: content, self-containment, Chromium screenshot."""

from __future__ import annotations

import html.parser
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from jaxedit import DataError
from jaxedit.io import write_image
from jaxedit.pipelines.report import write_report
from jaxedit.viz import colorize_depth, write_turntable

SIZE = 48
VIEWS = 3


def _view(view: int, ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A fake render of view ``view`` at aggressivity ``ratio``: a disk whose colour
    moves from blue to orange with the ratio, offset per view; with depth and alpha."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    cx = SIZE / 2 + 6 * np.cos(view)
    r2 = ((xx - cx) ** 2 + (yy - SIZE / 2) ** 2) / (SIZE * 0.32) ** 2
    alpha = np.clip(1.5 - r2, 0.0, 1.0)
    colour = (1 - ratio) * np.array([0.2, 0.3, 0.9]) + ratio * np.array([0.95, 0.55, 0.1])
    shade = 0.6 + 0.4 * np.sqrt(np.clip(1 - r2, 0, 1))
    rgb = alpha[..., None] * colour * shade[..., None] + (1 - alpha[..., None])
    depth = 3.0 - np.sqrt(np.clip(1 - r2, 0, 1))
    return rgb.astype(np.float32), alpha, depth


def make_run(run_dir: Path, ratios=(0.0, 0.4, 1.0, 1.0), *, prompt="Make it <orange> & bright",
             turntables: bool = True) -> Path:
    """A run directory laid out as the edit driver writes it (no rendering needed)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    for v in range(VIEWS):
        rgb, alpha, depth = _view(v, 0.0)
        write_image(run_dir / "original" / "renders" / f"view_{v:03d}.png", rgb)
        write_image(run_dir / "original" / "depth" / f"view_{v:03d}.png", colorize_depth(depth, alpha))
    names = ["r0"] + [f"r{i}" for i in range(1, len(ratios) - 1)] + ["rn"]
    subtasks = []
    for i, (name, r) in enumerate(zip(names, ratios)):
        folder = f"subtasks/{i:02d}_r{r:.3f}"
        for v in range(VIEWS):
            rgb, alpha, depth = _view(v, r)
            write_image(run_dir / folder / "renders" / f"view_{v:03d}.png", rgb)
            write_image(run_dir / folder / "depth" / f"view_{v:03d}.png", colorize_depth(depth, alpha))
        (run_dir / folder / "scene.ply").write_bytes(b"ply\n")  # the report only links it
        if turntables:
            frames = np.stack([_view(f, r)[0] for f in range(6)])
            write_turntable(run_dir / folder / "turntable.webp", frames, fps=6, mp4=False)
        (run_dir / folder / "metrics.json").write_text(json.dumps(
            {"psnr_vs_target": 20 + 10 * r, "num_gaussians": 1000 + i}))
        subtasks.append({"index": i, "name": name, "ratio": r,
                         "difficulty": None if i == 0 else round(0.1 + 0.05 * i, 3),
                         "steps": 100 * (i + 1), "seconds": 1.5 * (i + 1),
                         "converged": i != 1, "snapshot": f"{folder}/scene.ply"})
    curve = [[r, 0.6 * r ** 1.5] for r in np.linspace(0, 1, 9).tolist()]
    (run_dir / "schedule.json").write_text(json.dumps({
        "prompt": prompt, "editor": "simulated", "mode": "proedit", "threshold": 0.25,
        "difficulty_curve": curve, "subtasks": subtasks}))
    (run_dir / "metrics.json").write_text(json.dumps(
        {"psnr_vs_target": 29.5, "ssim_vs_target": 0.91, "num_gaussians": 1003,
         "wall_time_s": 12.0, "utilisation": {"edits": 17, "trainer_waits": 3}}))
    (run_dir / "config.json").write_text(json.dumps(
        {"command": "edit", "argv": ["edit", "--prompt", prompt, "--out", str(run_dir)],
         "jaxedit_version": "0.1.0", "flags": {}}))
    return run_dir


class _Collector(html.parser.HTMLParser):
    """Collects tags, ids, src/href values and checks that tags balance."""

    VOID = {"meta", "img", "input", "br", "hr", "link"}

    def __init__(self):
        super().__init__()
        self.ids, self.urls, self.tags, self.stack, self.errors = set(), [], [], [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        attrs = dict(attrs)
        if "id" in attrs:
            self.ids.add(attrs["id"])
        for key in ("src", "href"):
            if key in attrs:
                self.urls.append(attrs[key])
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unbalanced </{tag}> (open: {self.stack[-3:]})")
        else:
            self.stack.pop()


def _parse(text: str) -> _Collector:
    c = _Collector()
    c.feed(text)
    c.close()
    return c


def test_edit_report_is_self_contained_and_complete(tmp_path):
    run = make_run(tmp_path / "run")
    path = write_report(run)
    assert path == run / "report.html"
    text = path.read_text()
    doc = _parse(text)
    assert not doc.errors and not doc.stack, (doc.errors, doc.stack)
    assert text.startswith("<!DOCTYPE html>")
    # Every section of the contract is there.
    assert {"instruction", "schedule", "difficulty", "gallery", "depth", "turntables",
            "metrics"} <= doc.ids
    # Self-contained: every src is a data URI, no link leaves the page, nothing says http.
    assert doc.urls and all(u.startswith(("data:", "#")) for u in doc.urls), doc.urls[:5]
    assert not re.search(r"(src|href)\s*=\s*[\"']?\s*(https?:|//)", text)
    assert "<link" not in text and "@import" not in text
    # The prompt is escaped, not injected.
    assert "&ldquo;Make it &lt;orange&gt; &amp; bright&rdquo;" in text
    # Inline images: the plot (PNG), galleries (JPEG), turntables (WebP).
    assert "data:image/png;base64," in text and "data:image/jpeg;base64," in text
    assert text.count("data:image/webp;base64,") == 4
    # The schedule table holds every subtask with its ratio and iterations, and the total.
    for r, steps in [("0.0000", 100), ("0.4000", 200), ("1.0000", 300)]:
        assert f"<td>{r}</td>" in text and f"<td>{steps}</td>" in text
    assert "<td>1000</td>" in text  # total iterations 100+200+300+400
    assert "Not converged" in text  # r1 did not converge
    # One slider frame per subtask in both the gallery and the depth section.
    assert text.count('class="frame"') == 2 * 4
    assert "simulated editor</b>: an offline test instrument" in text
    # Each gallery frame quotes its snapshot's headline numbers.
    assert "after subtask r1  (r = 0.400) &mdash; psnr_vs_target 24, num_gaussians 1001" in text
    # Nested metrics are flattened to dotted names.
    assert "<td>utilisation.edits</td><td>17</td>" in text
    assert len(text) < 2_000_000


def test_selected_level_is_shown_and_preselected(tmp_path):
    run = make_run(tmp_path / "run", turntables=False)
    (run / "selected.json").write_text(json.dumps(
        {"index": 1, "name": "r1", "ratio": 0.4, "snapshot": "subtasks/01_r0.400/scene.ply"}))
    text = write_report(run).read_text()
    assert "<td>selected (selected.ply)</td><td>r1  (r = 0.400)</td>" in text
    assert "<td>r1 &#9733;</td>" in text
    # Both sliders start on the selected subtask; its frames are the visible ones.
    assert text.count('value="1" aria-label="subtask"') == 2
    visible = re.findall(r'<div class="frame" data-label="([^"]*)">', text)
    assert visible == ["r1  (r = 0.400)"] * 2


def test_report_shrinks_to_budget_and_validates(tmp_path):
    run = make_run(tmp_path / "run", turntables=False)
    big = write_report(run, out=tmp_path / "big.html").stat().st_size
    small = write_report(run, out=tmp_path / "small.html", max_bytes=big // 2).stat().st_size
    assert small < big
    # Malformed or missing inputs: one DataError naming the file.
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="not a run directory"):
        write_report(tmp_path / "empty")
    with pytest.raises(DataError, match="does not exist"):
        write_report(tmp_path / "nowhere")
    (run / "schedule.json").write_text("{not json")
    with pytest.raises(DataError, match="schedule.json: malformed JSON"):
        write_report(run)
    (run / "schedule.json").write_text(json.dumps({"subtasks": [{"ratio": "half"}]}))
    with pytest.raises(DataError, match=r"subtasks\[0\].ratio"):
        write_report(run)


def test_a_run_kind_outside_the_library_brings_its_own_sections(tmp_path):
    # The seam the lab's ablation page uses: the sections replace the edit/generic ones and
    # are asked again at smaller sizes while the page is over budget.
    (tmp_path / "study.json").write_text(json.dumps({"answer": 42}))
    sizes = []

    def sections(run_dir, *, thumb_px, max_views, turntable_px, max_frames):
        sizes.append(thumb_px)
        answer = json.loads((run_dir / "study.json").read_text())["answer"]
        return [("study", "Study", f"<p>answer {answer}</p>" + "x" * (thumb_px * 100))]

    with pytest.raises(DataError, match="not a run directory"):
        write_report(tmp_path)  # the library alone knows no study.json
    text = write_report(tmp_path, sections=sections, title="my study", max_bytes=15_000,
                        thumb_px=192).read_text()
    assert "<title>my study</title>" in text and '<section id="study"><h2>Study</h2>' in text
    assert "answer 42" in text and len(text) <= 15_000
    assert sizes[0] == 192 and sizes == sorted(sizes, reverse=True) and len(sizes) > 1


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not on PATH (CI installs Debian's chromium)")
def test_report_renders_in_headless_chromium(tmp_path):
    from PIL import Image

    run = make_run(tmp_path / "run")
    page = write_report(run)
    shot = tmp_path / "shot.png"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
           "--no-first-run", "--disable-background-networking", "--disable-component-update",
           "--disable-sync", f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}",
           "--window-size=1280,2000", "--hide-scrollbars", page.resolve().as_uri()]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=90)
    assert shot.is_file(), f"no screenshot (rc {proc.returncode}): {proc.stderr[-500:]}"
    img = np.asarray(Image.open(shot).convert("RGB"), np.float32)
    assert img.shape[:2] == (2000, 1280)
    # Not blank: the page draws text, tables and images, so many distinct colours and
    # a good share of non-background pixels; the orange of the last subtask is visible.
    assert img.std() > 20
    assert len(np.unique(img.reshape(-1, 3).astype(np.uint8), axis=0)) > 500
    orange = (img[..., 0] > 200) & (img[..., 1] > 100) & (img[..., 1] < 170) & (img[..., 2] < 80)
    assert orange.sum() > 100


def test_generic_run_report_with_training_curves(tmp_path):
    run = tmp_path / "recon"
    for v in range(2):
        write_image(run / "test" / f"{v:03d}_frame.png", _view(v, 0.0)[0])
    (run / "metrics.json").write_text(json.dumps({"test_psnr": 31.25, "per_view": [30.123456, 32.5]}))
    lines = [json.dumps({"step": s, "loss": 1.0 / s, "psnr": 10 + s / 10, "num_gaussians": 100 + s})
             for s in range(10, 110, 10)]
    (run / "train_log.jsonl").write_text("\n".join(lines) + '\n{"step": 110, "lo')  # killed mid-line
    text = write_report(run).read_text()
    doc = _parse(text)
    assert not doc.errors and {"run", "views", "training", "metrics"} <= doc.ids
    assert "<td>31.25</td>" in text and "<td>[30.12, 32.5]</td>" in text
    assert text.count("data:image/png;base64,") == 1  # the training plot
    (run / "train_log.jsonl").write_text('{"step": 1}\nnot json\n{"step": 2}\n')
    with pytest.raises(DataError, match="train_log.jsonl: line 2"):
        write_report(run)
