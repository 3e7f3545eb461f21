"""An edit run's checkpoint: its whole :class:`EditState` in one npz, atomically,
bit-exact (:mod:`jaxedit.io.checkpoint`); :func:`check_resume` checks a resume before it
writes anything.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import typing
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..io.checkpoint import read_pytree, restore, save_pytree
from ..train.checkpoint import PRE_TRACED_EXTENT
from .buffer import Utilisation
from .state import HOST_FIELDS, DensityTally, DeviceState, EditState, HostState, LossTracker

KIND = "edit"


#: A host field's form in the checkpoint's JSON record: its type there, to JSON, from JSON.
_NUMBER = (int, float)
_JSON = {int: (int, int, int), float: (_NUMBER, float, float), tuple: (list, list, tuple),
         Utilisation: (dict, Utilisation.as_dict, lambda d: Utilisation(**d)),
         DensityTally: (dict, DensityTally._asdict, lambda d: DensityTally(**d))}
_HOST_TYPES = typing.get_type_hints(HostState)
#: :class:`HostState`'s fields stored in the JSON record (the others, arrays, in the npz).
JSON_FIELDS = tuple(k for k in HOST_FIELDS if _HOST_TYPES[k] in _JSON)
#: Its arrays, stored beside :class:`DeviceState`'s leaves.
ARRAY_FIELDS = tuple(k for k in HOST_FIELDS if k not in JSON_FIELDS)
#: Host fields an older version's checkpoint may lack (their default is the fresh state's).
ADDED_LATER = ("complete_at", "annealed_at", "density")
#: The layout before the tracker was stored whole: its recent losses as ``tracker_recent``,
#: its count, best and since_best as the record's ``tracker``.
_LEGACY_TRACKER = "tracker"


def save_checkpoint(path: str | os.PathLike, st: EditState, meta: dict) -> None:
    """Write the edit state to ``path`` (npz, atomic: a crash never leaves half a file):
    :class:`DeviceState` and the host arrays as leaves, the other host fields (by name),
    the trainer's ``max_intersections`` and ``meta`` in the JSON record."""
    tree = {**st.device._asdict(), **{k: np.asarray(getattr(st.host, k)) for k in ARRAY_FIELDS}}
    info = {k: _JSON[_HOST_TYPES[k]][1](getattr(st.host, k)) for k in JSON_FIELDS}
    info.update(max_intersections=getattr(st.train, "max_intersections", None), meta=meta)
    save_pytree(path, tree, kind=KIND, meta=info)


def record_schema(legacy: bool = False) -> dict:
    """The checkpoint's meta record: key -> (types, required), derived from
    :class:`HostState`; ``legacy``: that of the layout with a ``tracker`` list."""
    schema = {k: (_JSON[_HOST_TYPES[k]][0], not (legacy and k in ADDED_LATER))
              for k in JSON_FIELDS}
    schema.update(max_intersections=((int, type(None)), False), meta=(dict, True))
    if legacy:
        schema[_LEGACY_TRACKER] = (list, True)
    return schema


#: The run's own part of it (:func:`jaxedit.pipelines.edit_run.run_edit` writes it).
RUN_META = {"plan": (list, True), "header": (dict, True), "wall_time_s": (_NUMBER, False)}


def _check_keys(record, schema: dict, path, what: str) -> None:
    """Refuse a record that is not a dict, lacks a required key, has an unknown one, or
    holds a value of the wrong type (bools are not numbers here)."""
    if not isinstance(record, dict):
        raise DataError(path, f"{what} is a {type(record).__name__}, expected an object")
    missing = [k for k, (_, required) in schema.items() if required and k not in record]
    unknown = sorted(set(record) - set(schema))
    if missing or unknown:
        parts = ([f"lacks {', '.join(missing)}"] if missing else []) + (
            [f"has unknown {', '.join(unknown)}"] if unknown else [])
        raise DataError(path, f"{what} {' and '.join(parts)} (damaged, or written by "
                              f"another version); delete it to start the edit over")
    for key, (types, _) in schema.items():
        value, types = record.get(key), types if isinstance(types, tuple) else (types,)
        if key in record and (not isinstance(value, types)
                              or (isinstance(value, bool) and bool not in types)):
            raise DataError(path, f"{what}'s {key} is {json.dumps(value)[:40]}, of the "
                                  f"wrong type")


def _fields(kind) -> set[str]:
    return set(getattr(kind, "_fields", ())) or {f.name for f in dataclasses.fields(kind)}


def read_record(path, info) -> dict:
    """The checkpoint's meta record ``info``, checked: every key of :func:`record_schema` and
    :data:`RUN_META`, their types and ranges, the counters' fields and each plan entry's.

    Raises:
      DataError naming ``path``.
    """
    from .plan import SubtaskSpec

    _check_keys(info, record_schema(isinstance(info, dict) and _LEGACY_TRACKER in info), path,
                "checkpoint record")
    _check_keys(info["meta"], RUN_META, path, "checkpoint record's meta")
    if info.get("max_intersections") is not None and info["max_intersections"] < 1:
        raise DataError(path, f"checkpoint record's max_intersections is "
                              f"{info['max_intersections']}, expected a positive size")
    if info["subtask"] < 0 or info["step"] < 0:
        raise DataError(path, f"checkpoint record is at subtask {info['subtask']}, step "
                              f"{info['step']}: negative")
    tracker = info.get(_LEGACY_TRACKER, [0, 0, 0])
    if len(tracker) != 3 or not all(isinstance(v, _NUMBER) and not isinstance(v, bool)
                                    for v in tracker):
        raise DataError(path, f"checkpoint record's tracker is {json.dumps(tracker)[:60]}, "
                              f"expected [count, best, since_best]")
    for key, kind in (("utilisation", Utilisation), ("density", DensityTally)):
        if key in info and not set(info[key]) <= _fields(kind):
            raise DataError(path, f"checkpoint record's {key} has unknown "
                                  f"{', '.join(sorted(set(info[key]) - _fields(kind)))}")
    spec_fields = _fields(SubtaskSpec)
    plan = info["meta"]["plan"]
    if not plan or not all(isinstance(p, dict) and set(p) == spec_fields for p in plan):
        raise DataError(path, f"checkpoint record's plan is not a list of subtasks with "
                              f"{', '.join(sorted(spec_fields))}")
    if info["subtask"] > len(plan):
        raise DataError(path, f"checkpoint record is at subtask {info['subtask']} of a plan "
                              f"of {len(plan)}")
    if not all(isinstance(r, dict) for r in info["records"]):
        raise DataError(path, "checkpoint record's records are not objects")
    return info


def load_checkpoint(path: str | os.PathLike, train_template) -> tuple[EditState, dict]:
    """Read a checkpoint written by :func:`save_checkpoint` (or by an older version) as
    (state, meta).

    ``train_template``: a trainer state of the same structure (shapes may differ); the
    meta record is checked by :func:`read_record` first. Raises DataError.
    """
    path = Path(path)
    arrays, info = read_pytree(path, kind=KIND)
    info = read_record(path, info)
    legacy = _LEGACY_TRACKER in info
    tracker = (np.zeros((0,), np.float32) if legacy else
               LossTracker(np.zeros((0,), np.float32), np.int32(0), np.float32(0), np.int32(0)))
    template = {**DeviceState(train_template, np.zeros((0,), np.float32), tracker)._asdict(),
                **{k: np.zeros((0,), bool) for k in ARRAY_FIELDS}}
    if legacy:
        template["tracker_recent"] = template.pop("tracker")
    # stored shapes win (capacity grows); a state without the traced extent takes the template's
    tree = restore(template, arrays, path, shapes=False, template_fills=PRE_TRACED_EXTENT)
    train = tree["train"]
    if info.get("max_intersections") is not None and hasattr(train, "max_intersections"):
        train = dataclasses.replace(train, max_intersections=int(info["max_intersections"]))
    if legacy:
        count, best, since = info[_LEGACY_TRACKER]
        tree["tracker"] = LossTracker(tree.pop("tracker_recent"), jnp.int32(count),
                                      jnp.float32(best), jnp.int32(since))
    host = {k: _JSON[_HOST_TYPES[k]][2](info[k]) for k in JSON_FIELDS if k in info}
    host.update({k: np.asarray(tree[k]) for k in ARRAY_FIELDS})
    st = EditState(DeviceState(train, tree["images"], tree["tracker"]), HostState(**host))
    return st, info["meta"]


# ----------------------------------------------------------------------------- resuming


def snapshot_fingerprint(path: str | os.PathLike) -> dict:
    """``{"snapshot_bytes", "snapshot_sha256"}`` of a snapshot's scene file, recorded in its
    subtask's record so that a resumed run can tell a truncated or replaced one."""
    data = Path(path).read_bytes()
    return {"snapshot_bytes": len(data), "snapshot_sha256": hashlib.sha256(data).hexdigest()}


def _named_snapshots(run_dir: Path, records) -> dict[str, dict]:
    """{snapshot path as recorded: its record} of the checkpoint's records and of
    ``schedule.json``'s finished subtasks (the checkpoint's win: they rewrite the file)."""
    named: dict[str, dict] = {}
    schedule = run_dir / "schedule.json"
    if schedule.is_file():
        try:
            subtasks = json.loads(schedule.read_text(encoding="utf-8")).get("subtasks", [])
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError) as e:
            raise DataError(schedule, f"unreadable run record ({type(e).__name__}); the run "
                                      f"cannot be resumed as it is") from None
        for r in subtasks if isinstance(subtasks, list) else []:
            if isinstance(r, dict) and isinstance(r.get("snapshot"), str):
                named[r["snapshot"]] = r
    for r in records:
        if isinstance(r.get("snapshot"), str):
            named[r["snapshot"]] = r
    return named


def verify_snapshots(run_dir: str | os.PathLike, records) -> None:
    """Refuse a resume whose finished subtasks' snapshots (named by ``records`` or
    ``schedule.json``) are missing, do not load, or differ from their recorded size and hash.

    Raises:
      DataError naming the snapshot.
    """
    from ..io import load_ply

    run_dir = Path(run_dir)
    for rel, record in _named_snapshots(run_dir, records).items():
        path = run_dir / rel
        if not path.is_file():
            raise DataError(path, "the snapshot of a finished subtask is missing; the run "
                                  "cannot be resumed (start it over, or --resume-from an "
                                  "intact snapshot)")
        size, digest = record.get("snapshot_bytes"), record.get("snapshot_sha256")
        if size is not None or digest is not None:
            found = snapshot_fingerprint(path)
            if (size is not None and found["snapshot_bytes"] != size) or (
                    digest is not None and found["snapshot_sha256"] != digest):
                raise DataError(path, f"the snapshot is not the one the run wrote "
                                      f"({found['snapshot_bytes']} bytes, recorded {size}); "
                                      f"it was truncated or replaced")
        load_ply(path)  # a DataError naming it when it does not load


def check_resume(path, st: EditState, images_shape: tuple, run_dir=None) -> None:
    """Before a resumed run writes anything: the checkpoint's training images must be of
    shape ``images_shape`` [N, H, W, 3], and every snapshot intact (:func:`verify_snapshots`).

    Raises:
      DataError naming the checkpoint ``path`` or the snapshot.
    """
    stored = tuple(np.shape(st.images))
    if stored != tuple(images_shape) or len(st.edited) != images_shape[0]:
        raise DataError(path, f"was written for {stored[0] if stored else 0} training views "
                              f"of {'x'.join(map(str, stored[1:3][::-1]))} px, the data has "
                              f"{images_shape[0]} of "
                              f"{'x'.join(map(str, tuple(images_shape)[1:3][::-1]))} px; "
                              f"resume with the run's own --data and --downscale")
    if run_dir is not None:
        verify_snapshots(run_dir, st.records)
