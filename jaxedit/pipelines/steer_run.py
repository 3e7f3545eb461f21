"""A steered edit run's files: its tree, its branches' folders, the stop request, and
:func:`run_branch`, which grows the tree by one operation (:mod:`jaxedit.edit.steer`).

    RUN/tree.json              the branches (absent: the main branch alone, as before)
    RUN/branches/NAME/         a branch: a run directory of its own (schedule.json,
                               subtasks/, checkpoint.npz, metrics.json)
    RUN/control.json           a request to the running edit ({"stop": true}), read
                               between subtasks and removed once obeyed
    RUN/difficulty.npz         the main path's difficulty edits, which branches reuse
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path
from typing import Callable

import numpy as np

from ..edit.context import EditData
from ..edit.steer import (ROOT, Branch, NodeRef, RunTree, check_name, extend_steps,
                          path_embeddings, refine_steps, resolve_index)
from ..errors import DataError
from ..io import load_scene
from ..io.files import LOCK_NAME, atomic_write_text
from .edit_run import ORACLE_NAME, EditRunConfig, EditStart, prepare_edit, run_edit
from .snapshots import BRANCHES, branch_folder as branch_dir

TREE_NAME = "tree.json"
#: What schedule.json's ``experimental`` says of an extension past r = 1.
EXPERIMENTAL = ("embeddings extrapolated past r = 1, where the editor was never trained")
CONTROL_NAME = "control.json"


def read_tree(run_dir) -> RunTree:
    """The run's tree (no ``tree.json``: the main branch alone)."""
    path = Path(run_dir) / TREE_NAME
    if not path.is_file():
        return RunTree()
    try:
        return RunTree.from_json(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError) as e:
        raise DataError(path, f"malformed run tree ({e})") from None


def write_tree(run_dir, tree: RunTree) -> None:
    atomic_write_text(Path(run_dir) / TREE_NAME, json.dumps(tree.to_json(), indent=2) + "\n")


def read_schedule(directory) -> dict:
    """A branch folder's schedule.json (DataError when there is none or it is garbled)."""
    path = Path(directory) / "schedule.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(path, "no schedule.json: not an edit run directory") from None
    except ValueError as e:
        raise DataError(path, f"malformed schedule ({e})") from None


def branch_status(run_dir, name: str) -> str:
    """done (metrics.json written), open (stopped or interrupted: ``--resume`` goes on) or
    planned (no schedule yet)."""
    folder = branch_dir(run_dir, name)
    if (folder / "metrics.json").is_file():
        return "done"
    return "open" if (folder / "schedule.json").is_file() else "planned"


def node_record(run_dir, ref: NodeRef, flag: str = "--from") -> tuple[NodeRef, dict, Path]:
    """(the node with its index resolved, its schedule.json record, its scene file)."""
    folder = branch_dir(run_dir, ref.branch)
    records = read_schedule(folder)["subtasks"]
    index = resolve_index(ref, records, flag)
    record = next(r for r in records if r["index"] == index)
    scene = folder / record["snapshot"]
    if not scene.is_file():
        raise DataError(scene, f"the snapshot of node {ref.branch}:{index} is missing")
    return NodeRef(ref.branch, index), record, scene


def start_scene(run_dir, start: NodeRef | None) -> tuple[object, dict | None]:
    """(the Gaussians of node ``start``, the parent's ``shapes`` there): the scene is grown
    to the capacity the parent trained on after that node, so its compiled programs (in the
    persistent cache) fit the branch; None shapes (the input scene, or a run recorded before
    shapes were): sized as a new run sizes them."""
    from ..gaussians import grow

    if start is None:
        return load_scene(Path(run_dir) / "original" / "scene.ply"), None
    _, record, path = node_record(run_dir, start)
    scene, shapes = load_scene(path), record.get("shapes")
    if not isinstance(shapes, dict) or not all(
            isinstance(shapes.get(k), int) and shapes[k] > 0
            for k in ("capacity", "max_intersections")):
        return scene, None
    if shapes["capacity"] > scene.capacity:
        scene = grow(scene, shapes["capacity"])
    return scene, {"capacity": max(shapes["capacity"], scene.capacity),
                   "max_intersections": shapes["max_intersections"]}


def _start_of(tree: RunTree, name: str) -> NodeRef | None:
    branch = tree.get(name)
    return None if branch is None else branch.start


def _start_ratio_of(tree: RunTree, name: str) -> float:
    branch = tree.get(name)
    return 0.0 if branch is None else branch.from_ratio


def _path_of(tree: RunTree, name: str) -> str:
    branch = tree.get(name)
    return ROOT if branch is None else branch.path


def plan_branch(run_dir, tree: RunTree, op: str, node: NodeRef, *, name: str | None = None,
                prompt: str | None = None, seed: int = 0, settings: dict | None = None) -> Branch:
    """The tree entry of operation ``op`` on ``node`` (checked against the run's files)."""
    settings = dict(settings or {})
    tree.get(node.branch)  # an unknown branch is refused here
    node, record, _ = node_record(run_dir, node)
    name = tree.next_name() if name is None else check_name(name)
    if name in tree.names():
        raise DataError("--name", f"the run already has a branch {name!r}")
    path = _path_of(tree, node.branch)
    path_prompt = (read_schedule(run_dir)["prompt"] if path == ROOT else tree.get(path).prompt)
    if op == "refine":
        if record["kind"] != "edit":
            raise DataError("--from", f"node {node} is a {record['kind']} subtask; only an edit "
                                      f"step (kind edit) can be refined")
        records = read_schedule(branch_dir(run_dir, node.branch))["subtasks"]
        before = [r for r in records if r["index"] < node.index and r.get("snapshot")]
        start = (NodeRef(node.branch, before[-1]["index"]) if before
                 else _start_of(tree, node.branch))
        r_prev = before[-1]["ratio"] if before else _start_ratio_of(tree, node.branch)
        return Branch(name, op, node, start, float(r_prev), path, None, seed, settings)
    if op == "extend":
        return Branch(name, op, node, node, float(record["ratio"]), path, None, seed, settings)
    if prompt is not None and prompt != path_prompt:  # a new instruction: a path of its own
        if not str(prompt).strip():
            raise DataError("--prompt", "empty instruction")
        return Branch(name, op, node, node, 0.0, name, str(prompt), seed, settings)
    return Branch(name, op, node, node, float(record["ratio"]), path, None, seed, settings)


def _branch_config(config: EditRunConfig, branch: Branch) -> EditRunConfig:
    s = branch.settings
    changes = {k: s[k] for k in ("threshold", "target_subtasks") if s.get(k) is not None}
    if s.get("guidance") is not None:
        changes["guidance"] = tuple(s["guidance"])
    if changes.get("threshold") is not None:
        changes.setdefault("target_subtasks", None)
    return dataclasses.replace(config, plan=dataclasses.replace(config.plan, **changes))


def _steps(run_dir, tree: RunTree, branch: Branch, config: EditRunConfig):
    """The branch's own ``steps(oracle)`` (None: the config's schedule from its start)."""
    parent = read_schedule(branch_dir(run_dir, branch.parent.branch))
    threshold = config.plan.threshold if config.plan.threshold is not None else parent.get("threshold")
    if branch.op == "refine":
        r_k = next(r["ratio"] for r in parent["subtasks"] if r["index"] == branch.parent.index)
        later = [r["ratio"] for r in parent["subtasks"]
                 if r["index"] > branch.parent.index and r["kind"] == "edit"]
        return refine_steps(branch.from_ratio, r_k, later, threshold,
                            ratio=branch.settings.get("ratio"), max_depth=config.plan.max_depth)
    if branch.op == "extend":
        return extend_steps(branch.from_ratio, float(branch.settings["r_max"]), threshold,
                            max_depth=config.plan.max_depth)
    return None


def _path_inputs(run_dir, tree: RunTree, path: str, data: EditData, input_scene, seed: int,
                 renderer, scenes: dict) -> tuple[EditData, object, int, Path]:
    """(the views, the oracle's scene, its seed, its memo file) of embedding path ``path``:
    the main path edits the photos; a new instruction's path edits the renders of its start
    (``scenes``: the start scenes loaded already, by node)."""
    if path == ROOT:
        return data, input_scene, int(read_schedule(run_dir).get("seed", seed)), \
            Path(run_dir) / ORACLE_NAME
    owner = tree.get(path)
    if owner.start not in scenes:
        scenes[owner.start] = start_scene(run_dir, owner.start)[0]
    scene = scenes[owner.start]
    renders = renderer.views(scene, data.train_cameras)[0]
    views = EditData(renders, data.train_cameras, data.test_images, data.test_cameras)
    return views, scene, owner.seed, branch_dir(run_dir, path) / ORACLE_NAME


def branch_inputs(editor, config: EditRunConfig, data: EditData, input_scene, run_dir,
                  tree: RunTree, branch: Branch,
                  log: Callable[[str], None] = lambda m: None) -> tuple:
    """(config, views, prompt, :class:`EditStart`) of ``branch`` in ``tree``, read from the
    run's files; writes nothing."""
    from ..edit.outputs import Renderer

    config = _branch_config(config, branch)
    renderer = Renderer(config.plan.background)
    scene, shapes = start_scene(run_dir, branch.start)
    views, path_scene, path_seed, memo = _path_inputs(run_dir, tree, branch.path, data,
                                                      input_scene, branch.seed, renderer,
                                                      {branch.start: scene})
    main_prompt = read_schedule(run_dir)["prompt"]

    def ratio_of(ref: NodeRef) -> float:
        return float(node_record(run_dir, ref)[1]["ratio"])

    cache: dict = {}

    def encode(text: str):
        if text not in cache:
            cache[text] = np.asarray(editor.encode(text))
        return cache[text]

    embeddings = path_embeddings(tree, branch.name, ratio_of, encode, main_prompt)
    prompt = main_prompt if branch.path == ROOT else tree.get(branch.path).prompt
    notes = {"experimental": EXPERIMENTAL} if branch.op == "extend" else None
    if notes:
        log(f"experimental: {EXPERIMENTAL}")
    start = EditStart(scene, branch.from_ratio, str(branch.start or "main:original"),
                      embeddings, _steps(run_dir, tree, branch, config), path_scene, path_seed,
                      memo, shapes, notes,
                      images=views.train_images if path_scene is scene else None)
    return config, views, prompt, start


def run_branch(editor, config: EditRunConfig, data: EditData, input_scene, run_dir,
               branch: Branch, *, distance=None, resume: bool = False,
               stop: Callable[[], bool] | None = None, progress=None,
               log: Callable[[str], None] = lambda m: None) -> dict:
    """Run ``branch`` (new: added to the tree first; ``resume``: from its checkpoint) in
    ``RUN/branches/NAME``; returns :func:`jaxedit.pipelines.edit_run.run_edit`'s summary.

    Nothing of the parent is recomputed: the branch starts from the parent's snapshot, and
    its path's difficulty edits are read from the memo. A DataError before training leaves
    the run as it was (the branch's folder and tree entry removed).
    """
    run_dir = Path(run_dir)
    tree = read_tree(run_dir)
    folder = branch_dir(run_dir, branch.name)
    if not resume:
        tree = tree.add(branch)
        if folder.exists():
            raise DataError(folder, "exists already: choose another --name")
    config, views, prompt, start = branch_inputs(editor, config, data, input_scene, run_dir,
                                                 tree, branch, log)
    if not resume:
        old = (run_dir / TREE_NAME).read_bytes() if (run_dir / TREE_NAME).is_file() else None
        write_tree(run_dir, tree)
    try:
        return run_edit(editor, prompt, views, input_scene, config=config.plan,
                        settings=config.train, seed=branch.seed, run_dir=folder, resume=resume,
                        distance=distance, identity=None, start=start, stop=stop,
                        progress=progress, log=log, report=False)
    except DataError:
        if not resume:  # refused before training: the run as it was
            shutil.rmtree(folder, ignore_errors=True)
            if old is None:
                (run_dir / TREE_NAME).unlink(missing_ok=True)
            else:
                atomic_write_text(run_dir / TREE_NAME, old.decode())
        raise


def warm_up(editor, config: EditRunConfig, data: EditData, input_scene, run_dir, *,
            distance=None) -> bool:
    """Prepare a refine of the run's last edit step in memory, writing nothing, so that this
    process holds what an operation on the run compiles, reads and renders (the viewer's
    warm worker); False when the run has no edit step to refine."""
    tree = read_tree(run_dir)
    steps = [r for r in read_schedule(run_dir)["subtasks"]
             if r["kind"] == "edit" and r.get("snapshot")]
    if not steps:
        return False
    branch = plan_branch(run_dir, tree, "refine", NodeRef(ROOT, steps[-1]["index"]))
    tree = tree.add(branch)
    config, views, prompt, start = branch_inputs(editor, config, data, input_scene, run_dir,
                                                 tree, branch)
    prepare_edit(editor, prompt, views, input_scene, config=config.plan, settings=config.train,
                 seed=branch.seed, distance=distance, identity=None, start=start,
                 memo=start.memo)
    return True


# Requests to a running edit


def _locked(run_dir) -> bool:
    """Whether a jaxedit process holds the run directory's lock now."""
    import fcntl

    path = Path(run_dir) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


def request_stop(run_dir) -> Path:
    """Ask the edit running in ``run_dir`` to stop after its current subtask."""
    run_dir = Path(run_dir)
    read_schedule(run_dir)
    if not _locked(run_dir):
        raise DataError("--stop", f"no edit is running in {run_dir}")
    path = run_dir / CONTROL_NAME
    atomic_write_text(path, json.dumps({"stop": True}) + "\n")
    return path


def read_control(run_dir) -> dict:
    """The pending request ({} when none); DataError naming the file when garbled."""
    path = Path(run_dir) / CONTROL_NAME
    if not path.is_file():
        return {}
    try:
        control = json.loads(path.read_text())
        if not isinstance(control, dict) or not isinstance(control.get("stop", False), bool):
            raise ValueError("expected {\"stop\": true}")
        return control
    except ValueError as e:
        raise DataError(path, f"garbled control file ({e}); delete it") from None


def stop_requested(run_dir, log: Callable[[str], None] = lambda m: None) -> Callable[[], bool]:
    """``stop()`` for :func:`jaxedit.pipelines.edit_run.run_edit`: True once ``--stop`` asked
    (the request is then removed); a garbled request is logged and ignored mid-run."""
    path = Path(run_dir) / CONTROL_NAME

    def stop() -> bool:
        try:
            asked = bool(read_control(run_dir).get("stop"))
        except DataError as e:
            log(f"WARNING: {e}")
            return False
        if asked:
            path.unlink(missing_ok=True)
        return asked

    return stop


def tree_rows(run_dir) -> list[dict]:
    """Each branch with its op, parent, instruction, status and finished nodes (for
    ``edit --tree``, the report and the viewer)."""
    run_dir = Path(run_dir)
    tree = read_tree(run_dir)
    rows = []
    for name in tree.names():
        branch = tree.get(name)
        folder = branch_dir(run_dir, name)
        schedule = read_schedule(folder) if (folder / "schedule.json").is_file() else {}
        nodes = [{"index": r["index"], "name": r["name"], "kind": r["kind"],
                  "ratio": r["ratio"], "difficulty": r.get("difficulty"),
                  "snapshot": None if not r.get("snapshot") else str(folder / r["snapshot"]),
                  "psnr_vs_input": (r.get("metrics") or {}).get("psnr_vs_input")}
                 for r in schedule.get("subtasks", [])]
        rows.append({"name": name, "op": "root" if branch is None else branch.op,
                     "parent": None if branch is None else str(branch.parent),
                     "prompt": schedule.get("prompt") if branch is None or branch.prompt is None
                     else branch.prompt,
                     "path": ROOT if branch is None else branch.path,
                     "seed": schedule.get("seed") if branch is None else branch.seed,
                     "threshold": schedule.get("threshold"),
                     "experimental": bool(schedule.get("experimental")),
                     "status": branch_status(run_dir, name), "dir": str(folder), "nodes": nodes})
    return rows


def format_tree(run_dir) -> str:
    """The tree as text: a line per branch, then a line per subtask."""
    lines = []
    for row in tree_rows(run_dir):
        origin = "" if row["parent"] is None else f" {row['op']} of {row['parent']}"
        origin += " (experimental)" if row["experimental"] else ""
        lines.append(f"{row['name']}{origin}: {row['prompt']!r} [{row['status']}]")
        for n in row["nodes"]:
            moved = ("" if n["psnr_vs_input"] is None
                     else f", {n['psnr_vs_input']:.1f} dB from the input")
            diff = "" if n["difficulty"] is None else f", d {n['difficulty']:.4g}"
            done = "done" if n["snapshot"] else "pending"
            lines.append(f"  {row['name']}:{n['index']} {n['kind']} r = {n['ratio']:.3f}"
                         f"{diff}{moved} ({done})")
    return "\n".join(lines)


__all__ = ["BRANCHES", "CONTROL_NAME", "TREE_NAME", "branch_dir", "branch_status",
           "format_tree", "node_record", "plan_branch", "read_control", "read_schedule",
           "read_tree", "request_stop", "run_branch", "stop_requested", "tree_rows",
           "write_tree"]
