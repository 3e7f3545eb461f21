"""Pytrees to and from one ``.npz`` file (leaves under their keystr paths, plus a JSON
record of version, ``kind`` and ``meta``): the checkpoint format of every jaxedit loop."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ..errors import DataError
from .files import atomic_path, read_npz

#: Bumped when the file layout changes (not when a pytree gains a leaf).
FORMAT_VERSION = 2
_META = "__meta__"


def _is_key(x) -> bool:
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def leaf_paths(tree) -> list[str]:
    """The pytree paths of ``tree``'s leaves, in flattening order."""
    return [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(tree)[0]]


def save_pytree(path, tree, *, kind: str, meta: dict | None = None) -> Path:
    """Write ``tree``'s leaves and JSON-serialisable ``meta`` to ``path`` atomically;
    ``kind`` is checked again on reading."""
    path = Path(path)
    flat = jax.tree_util.tree_flatten_with_path(jax.device_get(tree))[0]
    arrays, keys = {}, []
    for p, leaf in flat:
        name = jax.tree_util.keystr(p)
        if _is_key(leaf):
            keys.append(name)
            leaf = jax.random.key_data(leaf)
        arrays[name] = np.asarray(leaf)
    record = dict(version=FORMAT_VERSION, kind=kind, paths=list(arrays), keys=keys,
                  meta=meta or {})
    arrays[_META] = np.asarray(json.dumps(record))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
    return path


def read_pytree(path, *, kind: str) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays by leaf path, the caller's meta) of a file written by :func:`save_pytree`.

    Raises:
      DataError naming ``path``: unreadable, another format version, or another kind.
    """
    path = Path(path)
    arrays = read_npz(path)
    if _META not in arrays:
        raise DataError(path, "not a jaxedit checkpoint (no meta record)")
    try:
        record = json.loads(str(arrays.pop(_META)))
    except json.JSONDecodeError as e:
        raise DataError(path, f"corrupt checkpoint metadata ({e})") from None
    if not isinstance(record, dict) or record.get("version") != FORMAT_VERSION:
        version = record.get("version") if isinstance(record, dict) else None
        raise DataError(path, f"checkpoint format version {version} is not {FORMAT_VERSION} "
                              f"(written by another jaxedit version)")
    if record.get("kind") != kind:
        raise DataError(path, f"a {record.get('kind')!r} checkpoint, not a {kind!r} one")
    return arrays, record.get("meta", {})


def restore(template, arrays: dict[str, np.ndarray], where, *, shapes: bool = True,
            template_fills: tuple[str, ...] = ()) -> Any:
    """``template`` with every leaf replaced by the array stored under its path.

    Args:
      template: a pytree of the structure that was saved.
      arrays: from :func:`read_pytree`.
      where: what a DataError names (the file).
      shapes: also require the template's shapes (False: only dtypes, for growing states).
      template_fills: path endings whose missing leaves keep the template's value.
    """
    flat, treedef = jax.tree_util.tree_flatten_with_path(template)
    leaves = []
    for p, ref in flat:
        name = jax.tree_util.keystr(p)
        a = arrays.get(name)
        if a is None and name.endswith(template_fills):  # () matches nothing
            leaves.append(ref)
            continue
        if a is None:
            raise DataError(where, f"checkpoint lacks {name} (saved by another version?)")
        if _is_key(ref):
            leaves.append(jax.random.wrap_key_data(np.asarray(a)))
            continue
        ref_dtype = np.dtype(getattr(ref, "dtype", np.asarray(ref).dtype))
        ref_shape = tuple(np.shape(ref))
        if np.dtype(a.dtype) != ref_dtype or (shapes and tuple(a.shape) != ref_shape):
            raise DataError(where, f"checkpoint leaf {name} is {a.dtype} {tuple(a.shape)}, "
                                   f"expected {ref_dtype} {ref_shape}")
        leaves.append(jax.device_put(np.asarray(a)))
    return jax.tree_util.tree_unflatten(treedef, leaves)
