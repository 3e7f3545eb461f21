"""jaxedit.io.checkpoint: the one pytree <-> npz format of the trainer and the edit driver."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxedit import DataError
from jaxedit.io import checkpoint as C


def tree():
    return {"a": jnp.arange(6, dtype=jnp.float32).reshape(2, 3) / 7.0,
            "flags": jnp.asarray([True, False]), "n": jnp.int32(5),
            "key": jax.random.key(3), "nested": (jnp.ones((4,), jnp.uint32),)}


def test_round_trip_is_bit_exact_and_keeps_meta_and_typed_keys(tmp_path):
    path = C.save_pytree(tmp_path / "x.npz", tree(), kind="test", meta={"step": 7})
    arrays, meta = C.read_pytree(path, kind="test")
    assert meta == {"step": 7}
    back = C.restore(tree(), arrays, path)
    for a, b in zip(jax.tree_util.tree_leaves(tree()), jax.tree_util.tree_leaves(back)):
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert np.asarray(a).dtype == np.asarray(b).dtype
    assert not list(tmp_path.glob("*.tmp*"))  # nothing left beside the file


def test_wrong_kind_version_shape_or_bytes_name_the_file(tmp_path):
    path = C.save_pytree(tmp_path / "x.npz", tree(), kind="train")
    with pytest.raises(DataError, match="'train' checkpoint, not a 'edit'"):
        C.read_pytree(path, kind="edit")
    arrays, _ = C.read_pytree(path, kind="train")
    bigger = dict(tree(), a=jnp.zeros((3, 3), jnp.float32))
    with pytest.raises(DataError, match=r"\['a'\]"):
        C.restore(bigger, arrays, path)
    assert C.restore(bigger, arrays, path, shapes=False)["a"].shape == (2, 3)  # growth allowed
    with pytest.raises(DataError, match="lacks"):
        C.restore(dict(tree(), extra=jnp.zeros(1)), arrays, path)
    old = tmp_path / "old.npz"
    np.savez(old, __meta__=np.asarray(json.dumps({"version": 1, "kind": "train"})))
    with pytest.raises(DataError, match="version 1"):
        C.read_pytree(old, kind="train")
    for bad in (b"", b"not a zip"):
        (tmp_path / "bad.npz").write_bytes(bad)
        with pytest.raises(DataError, match="cannot read checkpoint") as e:
            C.read_pytree(tmp_path / "bad.npz", kind="train")
        assert "bad.npz" in str(e.value)


def test_a_failed_write_leaves_the_previous_checkpoint(tmp_path, monkeypatch):
    path = C.save_pytree(tmp_path / "x.npz", tree(), kind="test", meta={"v": 1})
    before = path.read_bytes()

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", fail)
    with pytest.raises(OSError):
        C.save_pytree(path, tree(), kind="test", meta={"v": 2})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["x.npz"]
