"""Steering an edit: the run as a tree of branches, and the pure operations that grow it.

The main branch is the run's own plan; any finished subtask's snapshot can start a branch
(paper 3.4: preview, "adjust the subtasks on the fly", select). Each branch follows an
embedding path e(r) = r E_to + (1 - r) E_from: the main path is (E(p), E("")); a branch with
a new instruction p' from a node at ratio r on its parent's path starts a path of its own,
(E(p'), e_parent(r)), so its first step continues from where the parent stood. Operations:

- ``refine`` node k: redo step k from snapshot k-1, split at r' with d(r_{k-1}, r') ~
  d(r', r_k) (:func:`refine_steps`), then the parent's later steps;
- ``branch`` node k: from snapshot k, another instruction, or the same path with another
  seed, threshold, target subtask count or guidance;
- ``extend`` node k: past the path's end, r in (r_k, r_max] (:func:`extend_steps`),
  experimental: e(r) extrapolates beyond the instruction.

Nothing here reads or writes a file (:mod:`jaxedit.pipelines.steer_run` does).
"""

from __future__ import annotations

import dataclasses
import re
from typing import Callable, Sequence

import numpy as np

from ..errors import DataError
from .schedule import MAX_DEPTH, decompose_interval, split_ratio

#: The run's own plan.
ROOT = "main"
OPS = ("refine", "branch", "extend")
TREE_VERSION = 1
#: A branch name: its folder's name under ``RUN/branches`` (letters, digits, _ and -).
NAME_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
#: Names a branch cannot take (the main branch; a snapshot's folder of the run).
RESERVED = (ROOT, "original")


def check_name(name, flag: str = "--name") -> str:
    """``name`` if it can name a branch (:data:`NAME_PATTERN`, not :data:`RESERVED`), else a
    DataError naming ``flag``: a name is a folder, so nothing outside the run is reachable."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise DataError(flag, f"a branch name is 1 to 64 letters, digits, _ or -, got "
                              f"{str(name)[:80]!r}")
    if name in RESERVED:
        raise DataError(flag, f"{name!r} is reserved; choose another branch name")
    return name


@dataclasses.dataclass(frozen=True)
class NodeRef:
    """Subtask ``index`` of branch ``branch`` (negative: counted from the branch's end)."""

    branch: str = ROOT
    index: int = -1

    def __str__(self) -> str:
        return f"{self.branch}:{self.index}"


def parse_node(text: str, flag: str = "--from") -> NodeRef:
    """``"2"`` (the main branch's subtask 2), ``"b1:3"`` or ``"b1:-1"`` (b1's last)."""
    branch, _, index = str(text).rpartition(":")
    try:
        return NodeRef(branch or ROOT, int(index))
    except ValueError:
        raise DataError(flag, f"expected a node as INDEX or BRANCH:INDEX (e.g. 2, b1:-1), "
                              f"got {text!r}") from None


@dataclasses.dataclass(frozen=True)
class Branch:
    """One branch of a run (``tree.json``'s entry; the main branch has none).

    Attributes:
      name: its name, also its folder ``RUN/branches/NAME``.
      op: "refine", "branch" or "extend".
      parent: the node it was made from (index resolved, >= 0).
      start: the snapshot it trains from (refine: the parent's node k-1); None: the
        parent branch's own start (refining a branch's first step).
      from_ratio: the start's ratio on the parent's path.
      path: the branch whose beginning starts this branch's embedding path (itself when
        it has a new ``prompt``, else its parent's path).
      prompt: its new instruction (None: the parent path's).
      seed: its seed (every draw of its subtasks).
      settings: what it changes: ``threshold``, ``target_subtasks``, ``guidance``, ``ratio``
        (refine's split), ``r_max`` (extend), with the command line it came from.
    """

    name: str
    op: str
    parent: NodeRef
    start: NodeRef | None
    from_ratio: float
    path: str
    prompt: str | None = None
    seed: int = 0
    settings: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        return {"name": self.name, "op": self.op, "parent": str(self.parent),
                "start": None if self.start is None else str(self.start),
                "from_ratio": self.from_ratio, "path": self.path, "prompt": self.prompt,
                "seed": self.seed, "settings": self.settings}

    @staticmethod
    def from_json(d: dict) -> "Branch":
        """The entry ``d`` of ``tree.json``; ValueError / KeyError / TypeError naming the
        field that is missing or of the wrong type."""
        if not isinstance(d, dict):
            raise TypeError(f"a branch entry is an object, got {type(d).__name__}")

        def field(key, *types, optional=False):
            value = d.get(key) if optional else d[key]
            if value is None and optional:
                return None
            if isinstance(value, bool) or not isinstance(value, types):
                raise TypeError(f"{key!r} of branch {str(d.get('name'))[:40]!r} is "
                                f"{type(value).__name__}, not {'/'.join(t.__name__ for t in types)}")
            return value

        name, op, path = field("name", str), field("op", str), field("path", str)
        try:
            check_name(name, "tree.json")
        except DataError as e:
            raise ValueError(e.problem) from None
        if path != ROOT:
            try:
                check_name(path, "tree.json")
            except DataError as e:
                raise ValueError(f"path: {e.problem}") from None
        if op not in OPS:
            raise ValueError(f"unknown op {op!r}")
        start = field("start", str, optional=True)
        branch = Branch(name, op, parse_node(field("parent", str), "tree.json"),
                        None if start is None else parse_node(start, "tree.json"),
                        float(field("from_ratio", int, float)), path,
                        field("prompt", str, optional=True), int(field("seed", int)),
                        dict(field("settings", dict, optional=True) or {}))
        return branch


@dataclasses.dataclass(frozen=True)
class RunTree:
    """The branches of a run (the main branch implicit), in the order they were made."""

    branches: tuple[Branch, ...] = ()

    def names(self) -> tuple[str, ...]:
        return (ROOT,) + tuple(b.name for b in self.branches)

    def get(self, name: str) -> Branch | None:
        """The branch ``name`` (None for the main branch); DataError if there is none."""
        if name == ROOT:
            return None
        for b in self.branches:
            if b.name == name:
                return b
        raise DataError("--from", f"no branch {name!r}; the run has {', '.join(self.names())}")

    def children(self, name: str) -> tuple[Branch, ...]:
        return tuple(b for b in self.branches if b.parent.branch == name)

    def add(self, branch: Branch) -> "RunTree":
        check_name(branch.name)
        if branch.name in self.names():
            raise DataError("--name", f"the run already has a branch {branch.name!r}")
        return RunTree(self.branches + (branch,))

    def next_name(self) -> str:
        taken, i = set(self.names()), 1
        while f"b{i}" in taken:
            i += 1
        return f"b{i}"

    def to_json(self) -> dict:
        return {"version": TREE_VERSION, "branches": [b.to_json() for b in self.branches]}

    @staticmethod
    def from_json(d) -> "RunTree":
        """The tree of ``tree.json``'s contents; ValueError / KeyError / TypeError when
        malformed."""
        if not isinstance(d, dict) or d.get("version") != TREE_VERSION:
            raise ValueError(f"not a version-{TREE_VERSION} run tree")
        if not isinstance(d["branches"], list):
            raise TypeError("'branches' is not a list")
        tree = RunTree()
        for entry in d["branches"]:
            branch = Branch.from_json(entry)
            if branch.parent.branch not in tree.names():
                raise ValueError(f"branch {branch.name!r} has an unknown parent {branch.parent}")
            if branch.start is not None and branch.start.branch not in tree.names():
                raise ValueError(f"branch {branch.name!r} has an unknown start {branch.start}")
            if branch.path not in tree.names() + (branch.name,):
                raise ValueError(f"branch {branch.name!r} has an unknown path {branch.path!r}")
            tree = tree.add(branch)
        return tree


def resolve_index(ref: NodeRef, records: Sequence[dict], flag: str = "--from") -> int:
    """``ref.index`` as an index of the branch's finished subtasks ``records``."""
    done = [r["index"] for r in records if r.get("snapshot")]
    index = ref.index if ref.index >= 0 else (done[ref.index] if -len(done) <= ref.index
                                              else None)
    if index not in done:
        raise DataError(flag, f"no finished subtask {ref} (branch {ref.branch} has "
                              f"{done or 'none'})")
    return int(index)


def path_embeddings(tree: RunTree, name: str, ratio_of: Callable[[NodeRef], float],
                    encode: Callable[[str], np.ndarray], main_prompt: str):
    """(E_to, E_from) of branch ``name``'s embedding path; ``ratio_of(node)`` is a node's
    ratio, ``encode(text)`` the editor's embedding."""
    branch = tree.get(name)
    if branch is None:
        return np.asarray(encode(main_prompt)), np.asarray(encode(""))
    if branch.path != branch.name:
        return path_embeddings(tree, branch.path, ratio_of, encode, main_prompt)
    e_to, e_from = path_embeddings(tree, branch.parent.branch, ratio_of, encode, main_prompt)
    r = ratio_of(branch.parent)
    return np.asarray(encode(branch.prompt)), r * e_to + (1.0 - r) * e_from


def steps_fields(method: str, threshold, evaluations: int, limit_hit: bool = False) -> dict:
    """schedule.json's scheduler fields of a branch's own steps."""
    return {"threshold": threshold, "target_subtasks": None, "schedule_method": method,
            "depth_limit_hit": limit_hit, "difficulty_evaluations": evaluations}


def refine_steps(r_prev: float, r_k: float, later: Sequence[float], threshold: float | None, *,
                 ratio: float | None = None, max_depth: int = MAX_DEPTH):
    """``steps(oracle)`` of refining the step r_prev -> r_k, then the parent's ``later``
    ratios: split at ``ratio`` (None: where the two halves' difficulties meet,
    :func:`jaxedit.edit.schedule.split_ratio`); a half still over ``threshold`` is
    bisected as the scheduler would (:func:`jaxedit.edit.schedule.decompose_interval`)."""
    if ratio is not None and not r_prev < ratio < r_k:
        raise DataError("--ratio", f"a refined step's ratio must lie in ({r_prev:g}, {r_k:g}), "
                                   f"got {ratio:g}")

    def steps(oracle):
        if oracle is None:
            raise DataError("--refine", "needs the difficulty (not in IN2N mode)")
        if ratio is None:
            x, d1, d2 = split_ratio(oracle, r_prev, r_k)
        else:
            x, d1, d2 = ratio, oracle(r_prev, ratio), oracle(ratio, r_k)
        ratios, diffs = [r_prev], []
        for (a, b), d in (((r_prev, x), d1), ((x, r_k), d2)):
            if threshold is not None and d > threshold:
                rs, ds = decompose_interval(oracle, a, b, threshold=threshold,
                                            max_depth=max_depth)
                ratios, diffs = ratios + list(rs[1:]), diffs + list(ds)
            else:
                ratios, diffs = ratios + [b], diffs + [d]
        for r in later:
            diffs.append(oracle(ratios[-1], r))
            ratios.append(float(r))
        return (steps_fields("refine", threshold, getattr(oracle, "evaluations", 0),
                             any(threshold is not None and d > threshold for d in diffs[:2])),
                ratios, diffs)

    return steps


def extend_steps(r_k: float, r_max: float, threshold: float | None, *,
                 max_depth: int = MAX_DEPTH):
    """``steps(oracle)`` of going on past r_k to ``r_max`` (> 1: extrapolated embeddings),
    bisected to the ``threshold`` (None: one step)."""
    if not r_max > max(r_k, 1.0):
        raise DataError("--extend", f"r_max must exceed the node's ratio {r_k:g} and 1, "
                                    f"got {r_max:g}")

    def steps(oracle):
        if oracle is None:
            raise DataError("--extend", "needs the difficulty (not in IN2N mode)")
        if threshold is None:
            return steps_fields("extend", None, 0), [r_k, r_max], [oracle(r_k, r_max)]
        ratios, diffs = decompose_interval(oracle, r_k, r_max, threshold=threshold,
                                           max_depth=max_depth)
        return (steps_fields("extend", threshold, getattr(oracle, "evaluations", 0),
                             any(d > threshold for d in diffs)), list(ratios), list(diffs))

    return steps


__all__ = ["Branch", "NAME_PATTERN", "NodeRef", "OPS", "RESERVED", "ROOT", "RunTree",
           "check_name", "extend_steps", "parse_node",
           "path_embeddings", "refine_steps", "resolve_index", "steps_fields"]
