"""Steering an edit (issue 72): the run tree, refine / branch / extend / stop / keep, on the
library and the command line, with their bad inputs."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import cli
from jaxedit import DataError
from jaxedit import gaussians as G
from jaxedit.edit.schedule import decompose_interval, split_ratio
from jaxedit.edit.steer import (Branch, NodeRef, RunTree, check_name, extend_steps,
                                parse_node, path_embeddings, refine_steps)
from jaxedit.io import save_ply
from jaxedit.io.files import folder_lock
from jaxedit.pipelines import steer_run
from jaxedit.pipelines.report import write_report

sys.path.insert(0, str(Path(__file__).parent))
from cli_expect import contents, fails  # noqa: E402
from test_cli_bad_inputs import _dataset  # noqa: E402
from test_clip_metrics import clip_dir  # noqa: E402,F401 - a fixture

PROMPT = "turn him into a bronze statue"


# ---------------------------------------------------------------- pure pieces

def square_distance(a, b):
    return abs(b * b - a * a)


def test_split_ratio_meets_where_the_halves_are_equally_hard():
    x, d1, d2 = split_ratio(square_distance, 0.0, 1.0, iterations=12)
    assert x == pytest.approx(np.sqrt(0.5), abs=1e-3)
    assert d1 == pytest.approx(d2, abs=2e-3) and max(d1, d2) < square_distance(0.0, 1.0)
    # the default: the midpoint and one regula falsi step, two probes (each an editor call
    # per difficulty view); within 1/32 of the bracket, no harder than the midpoint
    probed = []

    def counted(a, b):
        probed.append((a, b))
        return square_distance(a, b)
    x1, a1, b1 = split_ratio(counted, 0.2, 0.6)
    assert len({r for pair in probed for r in pair} - {0.2, 0.6}) == 2
    assert abs(x1 - np.sqrt((0.2 ** 2 + 0.6 ** 2) / 2)) <= 0.4 / 32
    assert max(a1, b1) <= max(square_distance(0.2, 0.4), square_distance(0.4, 0.6))
    assert x1 == split_ratio(square_distance, 0.2, 0.6)[0]
    with pytest.raises(DataError, match="go up"):
        split_ratio(square_distance, 0.5, 0.5)


def test_decompose_interval_bisects_past_one():
    ratios, diffs = decompose_interval(lambda a, b: abs(b - a), 1.0, 1.5, threshold=0.13)
    assert ratios == pytest.approx((1.0, 1.125, 1.25, 1.375, 1.5))
    assert all(d <= 0.13 for d in diffs)


def test_refine_and_extend_steps_reuse_an_oracle():
    calls = []

    def oracle(a, b):
        calls.append((a, b))
        return abs(b - a)

    fields, ratios, diffs = refine_steps(0.25, 0.75, [1.0], threshold=0.3)(oracle)
    assert ratios == pytest.approx([0.25, 0.5, 0.75, 1.0]) and fields["schedule_method"] == "refine"
    assert diffs == pytest.approx([0.25, 0.25, 0.25]) and all(d <= 0.3 for d in diffs)
    # a split still over the threshold is bisected further
    _, ratios, diffs = refine_steps(0.0, 1.0, [], threshold=0.2)(oracle)
    assert all(d <= 0.2 for d in diffs) and ratios[0] == 0.0 and ratios[-1] == 1.0
    _, ratios, _ = refine_steps(0.25, 0.75, [], threshold=None, ratio=0.3)(oracle)
    assert ratios == pytest.approx([0.25, 0.3, 0.75])
    _, ratios, diffs = extend_steps(1.0, 1.5, threshold=0.26)(oracle)
    assert ratios == pytest.approx([1.0, 1.25, 1.5])
    with pytest.raises(DataError, match="--ratio"):
        refine_steps(0.25, 0.75, [], threshold=None, ratio=0.8)
    with pytest.raises(DataError, match="--extend"):
        extend_steps(1.0, 1.0, threshold=None)


def test_tree_json_round_trip_names_and_refusals():
    assert parse_node("2") == NodeRef("main", 2) and parse_node("b1:-1") == NodeRef("b1", -1)
    with pytest.raises(DataError, match="--from"):
        parse_node("b1:x")
    b1 = Branch("b1", "refine", NodeRef("main", 2), NodeRef("main", 1), 0.25, "main", seed=3,
                settings={"ratio": None})
    b2 = Branch("b2", "branch", NodeRef("b1", 1), NodeRef("b1", 1), 0.0, "b2", prompt="marble")
    tree = RunTree().add(b1).add(b2)
    assert RunTree.from_json(json.loads(json.dumps(tree.to_json()))) == tree
    assert tree.next_name() == "b3" and tree.children("main") == (b1,)
    with pytest.raises(DataError, match="already"):
        tree.add(b1)
    with pytest.raises(DataError, match="no branch"):
        tree.get("b9")
    orphan = dict(tree.to_json(), branches=[b2.to_json()])
    with pytest.raises(ValueError, match="unknown parent"):
        RunTree.from_json(orphan)
    with pytest.raises(ValueError):
        RunTree.from_json({"version": 99, "branches": []})


@pytest.mark.parametrize("name", ["/abs", "../up", "a/b", "", ".", "main", "original",
                                  "x" * 65, "b 1", 3])
def test_a_branch_name_cannot_leave_the_run(name, tmp_path):
    with pytest.raises(DataError, match="--name"):
        check_name(name)
    if name != "main":  # the main branch's folder is the run's own
        with pytest.raises(DataError):
            steer_run.branch_dir(tmp_path, name)
    with pytest.raises(DataError, match="--name"):
        RunTree().add(Branch(name, "branch", NodeRef(), NodeRef(), 0.0, "main"))
    entry = Branch("b1", "branch", NodeRef(), NodeRef(), 0.0, "main").to_json()
    with pytest.raises((ValueError, TypeError)):  # tree.json read back: the same rule
        RunTree.from_json({"version": 1, "branches": [dict(entry, name=name)]})
    assert check_name("b-2_x") == "b-2_x"


@pytest.mark.parametrize("field,value", [("seed", "3"), ("seed", True), ("from_ratio", "0.5"),
                                         ("prompt", 7), ("settings", []), ("parent", 0),
                                         ("path", "../up"), ("path", "b9"), ("op", "merge"),
                                         ("start", "b9:0")])
def test_tree_json_fields_are_checked_on_read(field, value):
    entry = Branch("b1", "branch", NodeRef(), NodeRef(), 0.0, "main", seed=1).to_json()
    assert RunTree.from_json({"version": 1, "branches": [entry]}).branches[0].seed == 1
    with pytest.raises((ValueError, TypeError)):
        RunTree.from_json({"version": 1, "branches": [dict(entry, **{field: value})]})


def test_a_new_instruction_starts_its_path_where_the_parent_stood():
    vocab = {"": np.zeros(3), "bronze": np.array([1.0, 0, 0]), "patina": np.array([0, 1.0, 0]),
             "gold": np.array([0, 0, 1.0])}
    ratios = {NodeRef("main", 2): 0.5, NodeRef("b1", 0): 0.25}
    tree = (RunTree()
            .add(Branch("b1", "branch", NodeRef("main", 2), NodeRef("main", 2), 0.0, "b1",
                        prompt="patina"))
            .add(Branch("b2", "branch", NodeRef("b1", 0), NodeRef("b1", 0), 0.0, "b2",
                        prompt="gold"))
            .add(Branch("b3", "refine", NodeRef("b1", 0), None, 0.0, "b1")))
    emb = lambda name: path_embeddings(tree, name, ratios.get, vocab.get, "bronze")  # noqa: E731
    e_to, e_from = emb("main")
    assert np.array_equal(e_to, vocab["bronze"]) and np.array_equal(e_from, vocab[""])
    e_to, e_from = emb("b1")  # e_b1(0) = e_main(0.5)
    assert np.allclose(e_from, [0.5, 0, 0]) and np.array_equal(e_to, vocab["patina"])
    e_to, e_from = emb("b2")  # e_b2(0) = e_b1(0.25) = 0.25 patina + 0.75 e_main(0.5)
    assert np.allclose(e_from, [0.375, 0.25, 0]) and np.array_equal(e_to, vocab["gold"])
    assert all(np.array_equal(a, b) for a, b in zip(emb("b3"), emb("b1")))


# ---------------------------------------------------------------- a run on disk

BASE = ["--sync", "--max-steps", "40", "--warmup", "5", "--patience", "10", "--test-views", "1",
        "--turntable-frames", "0", "--accept-low-identity", "--target-subtasks", "3", "--quiet",
        "--no-report"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished tiny run (simulated editor, the difficulty schedule) and its inputs."""
    d = tmp_path_factory.mktemp("steer")
    rng = np.random.default_rng(1)
    data = _dataset(d / "data")
    scene = d / "scene.ply"
    save_ply(scene, G.from_points(rng.normal(scale=0.3, size=(30, 3)), rng.uniform(size=(30, 3)),
                                  sh_degree=0))
    out = d / "run"
    assert cli.main(["edit", "--data", str(data), "--scene", str(scene), "--prompt", PROMPT,
                     "--out", str(out), *BASE]) == 0
    return out


def fresh_copy(run, tmp_path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    return copy


def schedule(folder: Path) -> dict:
    return json.loads((folder / "schedule.json").read_text())


def test_refine_splits_the_step_and_recomputes_nothing_of_the_parent(run, tmp_path, capsys):
    out = fresh_copy(run, tmp_path)
    main = schedule(out)
    k = next(r["index"] for r in main["subtasks"] if r["kind"] == "edit" and r["index"] > 1)
    before = contents(out)
    assert cli.main(["edit", "--out", str(out), "--from", str(k), "--refine", "--quiet",
                     "--no-report"]) == 0
    # the parent's files are untouched; the branch has its own folder and tree entry
    assert {n: b for n, b in contents(out).items() if n in before and n != "difficulty.npz"} == \
        {n: b for n, b in before.items() if n != "difficulty.npz"}
    tree = steer_run.read_tree(out)
    (b1,) = tree.branches
    assert (b1.op, b1.parent, b1.start) == ("refine", NodeRef("main", k), NodeRef("main", k - 1))
    sub = schedule(out / "branches" / "b1")
    r_prev, r_k = main["subtasks"][k - 1]["ratio"], main["subtasks"][k]["ratio"]
    edits = [r for r in sub["subtasks"] if r["kind"] == "edit"]
    assert r_prev < edits[0]["ratio"] < r_k and edits[1]["ratio"] == r_k
    assert all(r["difficulty"] <= main["threshold"] + 1e-12 for r in edits[:2])
    assert sub["resumed_from"] == f"main:{k - 1}" and sub["start_ratio"] == r_prev
    # only the split's new ratios were edited: at most 3 halvings x the difficulty views
    views = main["difficulty"]["num_views"]
    assert 0 < sub["editor_calls_for_schedule"] <= 4 * views
    assert all((out / "branches" / "b1" / r["snapshot"]).is_file() for r in sub["subtasks"])
    capsys.readouterr()
    assert cli.main(["edit", "--out", str(out), "--tree"]) == 0
    printed = capsys.readouterr().out
    assert f"b1 refine of main:{k}" in printed and "b1:0 edit" in printed
    page = write_report(out).read_text()
    assert '<section id="tree">' in page and f"main:{k}" in page
    strip = page.split('alt="snapshots of b1"')[0].rsplit("<img", 1)[1]
    assert 'src="data:image/jpeg;base64,' in strip
    # a run without branches reads as before: no tree section
    plain = write_report(run, out=tmp_path / "plain.html").read_text()
    assert '<section id="tree">' not in plain and '<section id="schedule">' in plain


def test_the_same_branch_twice_gives_the_same_bytes_and_keep_selects_it(run, tmp_path):
    a, b = fresh_copy(run, tmp_path / "a"), fresh_copy(run, tmp_path / "b")
    for out in (a, b):
        assert cli.main(["edit", "--out", str(out), "--from", "1", "--seed", "5", "--quiet",
                         "--no-report"]) == 0
    sa, sb = schedule(a / "branches" / "b1"), schedule(b / "branches" / "b1")
    assert sa["seed"] == 5 and sa["editor_calls_for_schedule"] == 0  # the memo's edits
    for ra, rb in zip(sa["subtasks"], sb["subtasks"]):
        pa, pb = a / "branches/b1" / ra["snapshot"], b / "branches/b1" / rb["snapshot"]
        assert pa.read_bytes() == pb.read_bytes()
    assert cli.main(["edit", "--out", str(a), "--select", "b1:-1", "--select-only",
                     "--quiet"]) == 0
    last = a / "branches/b1" / sa["subtasks"][-1]["snapshot"]
    assert (a / "selected.ply").read_bytes() == last.read_bytes()
    assert json.loads((a / "selected.json").read_text())["branch"] == "b1"


def test_a_branch_starts_on_its_parents_buffers_and_compiles_no_training_step(
        run, tmp_path, monkeypatch):
    import jaxedit.pipelines.edit_run as pipeline
    from jaxedit.compilation import compile_stats

    out = fresh_copy(run, tmp_path)
    record = schedule(out)["subtasks"][0]
    shapes = record["shapes"]
    assert shapes["capacity"] >= record["num_gaussians"] and shapes["max_intersections"] > 0
    scene, got = steer_run.start_scene(out, NodeRef("main", 0))
    assert got == shapes and scene.capacity == shapes["capacity"]
    seen = []

    def compile_chunk(ctx, st):  # the training chunk's program: the parent's, in memory
        before = compile_stats()
        real(ctx, st)
        seen.append(compile_stats(since=before)["programs"].get("_edit_chunk"))

    real = pipeline.compile_chunk
    monkeypatch.setattr(pipeline, "compile_chunk", compile_chunk)
    assert cli.main(["edit", "--out", str(out), "--from", "0", "--seed", "4", "--quiet",
                     "--no-report"]) == 0
    assert seen == [None]
    # a run recorded before the shapes were: the scene as it is on disk, sized anew
    main = schedule(out)
    main["subtasks"][0].pop("shapes")
    (out / "schedule.json").write_text(json.dumps(main))
    scene, got = steer_run.start_scene(out, NodeRef("main", 0))
    assert got is None and scene.capacity == record["num_gaussians"]


def test_extend_goes_past_one(run, tmp_path):
    out = fresh_copy(run, tmp_path)
    assert cli.main(["edit", "--out", str(out), "--extend", "1.5", "--name", "far", "--quiet",
                     "--no-report"]) == 0
    sub = schedule(out / "branches" / "far")
    ratios = [r["ratio"] for r in sub["subtasks"]]
    assert sub["start_ratio"] == 1.0 and ratios[-1] == 1.5 and all(r > 1.0 for r in ratios)
    assert sub["subtasks"][-1]["kind"] == "consolidate"
    assert sub["experimental"] == steer_run.EXPERIMENTAL  # marked in its schedule, tree, report
    assert "far extend of main:" in steer_run.format_tree(out) and "(experimental)" in \
        steer_run.format_tree(out)
    assert "extend (experimental)" in write_report(out).read_text()


def test_stop_then_resume_gives_the_bytes_of_a_whole_run(run, tmp_path):
    """run_edit stopped after its second subtask, then resumed, ends as the run did."""
    from jaxedit.edit.steer import ROOT  # noqa: F401
    from jaxedit.pipelines.edit_run import load_inputs
    from experiments.edit import recorded_settings, run_config
    from experiments.editors import make_editor
    from jaxedit.pipelines.edit_run import run_edit
    from jaxedit.edit.difficulty import default_distance

    args = cli.parse(["edit", *recorded_settings(run)])
    config = run_config(args)
    data, scene = load_inputs(config, args.data, args.scene)
    out = tmp_path / "stopped"
    asked = iter([False, True])

    def edit(**kw):
        return run_edit(make_editor(config.editor), PROMPT, data, scene, config=config.plan,
                        settings=config.train, seed=args.seed, run_dir=out, report=False,
                        distance=default_distance(config.distance, config.lpips_weights),
                        identity=config.identity, **kw)

    first = edit(stop=lambda: next(asked, False))
    assert first["stopped"] and not (out / "metrics.json").exists()
    assert len([r for r in schedule(out)["subtasks"] if r["snapshot"]]) == 2
    assert not edit(resume=True)["stopped"]
    for r in schedule(run)["subtasks"]:
        assert (out / r["snapshot"]).read_bytes() == (run / r["snapshot"]).read_bytes()


def test_stop_request_and_its_refusals(run, tmp_path, capfd):
    out = fresh_copy(run, tmp_path)
    fails(capfd, ["edit", "--out", out, "--stop"], "no edit is running", keep=out,
          snapshot=contents)
    with folder_lock(out):  # another process's running edit
        assert cli.main(["edit", "--out", str(out), "--stop"]) == 0
        assert steer_run.read_control(out) == {"stop": True}
        fails(capfd, ["edit", "--out", out, "--from", "1", "--refine"], "in use", keep=out,
              snapshot=contents)
    assert steer_run.stop_requested(out)() is True and steer_run.read_control(out) == {}


def test_bad_steering_inputs_change_nothing(run, tmp_path, capfd):
    out = fresh_copy(run, tmp_path)
    last = schedule(out)["subtasks"][-1]["index"]
    for argv, needle in (
            (["--from", "9", "--refine"], "no finished subtask main:9"),
            (["--from", "b7:0", "--refine"], "no branch 'b7'"),
            (["--from", "0", "--refine"], "only an edit step"),
            (["--from", str(last), "--refine"], "only an edit step"),
            (["--from", "2", "--refine", "--ratio", "0.99"], "--ratio"),
            (["--from", "1", "--extend", "0.5"], "--extend"),
            (["--from", "1"], "a branch changes something"),
            (["--ratio", "0.3", "--from", "2"], "--ratio"),
            (["--from", "1", "--refine", "--extend", "1.5"], "either --refine or --extend"),
            (["--branch", "b1"], "add --resume"),
            (["--branch", "b1", "--resume"], "no branch 'b1'"),
            (["--from", "1", "--prompt", "  "], "empty instruction"),
            (["--from", "1", "--seed", "3", "--name", "/abs"], "--name"),
            (["--from", "1", "--seed", "3", "--name", "../up"], "--name"),
            (["--from", "1", "--seed", "3", "--name", "main"], "reserved")):
        fails(capfd, ["edit", "--out", out, *argv, "--quiet"], needle, keep=out,
              snapshot=contents)
    (out / steer_run.CONTROL_NAME).write_text("{not json")
    fails(capfd, ["edit", "--out", out, "--from", "2", "--refine", "--quiet"], "control.json",
          keep=out, snapshot=contents)
    (out / steer_run.CONTROL_NAME).unlink()
    (out / steer_run.TREE_NAME).write_text('{"version": 1, "branches": [{"name": "x"}]}')
    fails(capfd, ["edit", "--out", out, "--from", "2", "--refine", "--quiet"], "tree.json",
          keep=out, snapshot=contents)
    entry = Branch("up", "branch", NodeRef(), NodeRef(), 0.0, "main").to_json()
    (out / steer_run.TREE_NAME).write_text(json.dumps({"version": 1, "branches": [
        dict(entry, name="../up")]}))
    fails(capfd, ["edit", "--out", out, "--tree"], "tree.json", keep=out, snapshot=contents)


def test_a_branch_scores_its_last_snapshot_with_clip(run, tmp_path, clip_dir):
    out = fresh_copy(run, tmp_path)
    assert cli.main(["edit", "--out", str(out), "--from", "2", "--seed", "4", "--quiet",
                     "--no-report", "--clip-weights", str(clip_dir), "--caption-orig", "a man",
                     "--caption-edit", "a bronze statue", "--ip2p-device", "cpu"]) == 0
    folder = out / "branches" / "b1"
    last = (folder / schedule(folder)["subtasks"][-1]["snapshot"]).parent
    saved = json.loads((last / "clip_metrics.json").read_text())
    clip = json.loads((folder / "metrics.json").read_text())["clip"]
    assert clip["direction_similarity"] == pytest.approx(saved["direction_similarity"])
    assert "clip" not in json.loads((out / "metrics.json").read_text())


class Tint:
    """A tiny editor that knows every instruction: a colour per text, added to the photo."""

    name = "tint"
    guidance = (7.5, 1.5)

    def __init__(self):
        self.seen = []

    def encode(self, text):
        import hashlib

        code = np.frombuffer(hashlib.sha256(text.encode()).digest()[:3], np.uint8)
        return (code.astype(np.float32) / 255.0 - 0.5) * (0.0 if text == "" else 0.6)

    def edit(self, image, original, embedding, key, *, timestep_range=(0.02, 0.98),
             guidance=None):
        self.seen.append(np.asarray(embedding, np.float32))
        return np.clip(0.5 * np.asarray(image) + 0.5 * (np.asarray(original) + embedding), 0, 1)


def test_a_new_instruction_branches_from_the_parents_embedding(run, tmp_path):
    from experiments.edit import recorded_settings, run_config
    from jaxedit.pipelines.edit_run import load_inputs

    out = fresh_copy(run, tmp_path)
    args = cli.parse(["edit", *recorded_settings(out)])
    config = run_config(args)
    data, scene = load_inputs(config, args.data, args.scene)
    editor = Tint()
    tree = steer_run.read_tree(out)
    branch = steer_run.plan_branch(out, tree, "branch", NodeRef("main", 2), prompt="make it gold",
                               seed=1)
    assert branch.path == "b1" and branch.from_ratio == 0.0
    done = steer_run.run_branch(editor, config, data, scene, out, branch)
    r_k = schedule(out)["subtasks"][2]["ratio"]
    e_from = r_k * editor.encode(PROMPT)
    first = schedule(out / "branches" / "b1")["subtasks"][0]
    want = first["ratio"] * editor.encode("make it gold") + (1 - first["ratio"]) * e_from
    assert any(np.allclose(e, want, atol=1e-6) for e in editor.seen)
    assert done["schedule"]["prompt"] == "make it gold"
    assert (out / "branches" / "b1" / "difficulty.npz").is_file()
    # its own refine reads the new path's memo: only the split's ratios are edited
    tree = steer_run.read_tree(out)
    k = next(r["index"] for r in done["schedule"]["subtasks"] if r["kind"] == "edit")
    refine = steer_run.plan_branch(out, tree, "refine", NodeRef("b1", k), seed=1)
    assert (refine.path, refine.start) == ("b1", NodeRef("main", 2) if k == 0 else NodeRef("b1", k - 1))
    again = steer_run.run_branch(editor, config, data, scene, out, refine)
    views = done["schedule"]["difficulty"]["num_views"]
    assert again["schedule"]["editor_calls_for_schedule"] <= 4 * views
