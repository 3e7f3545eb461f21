"""Bad input to the surfaces of issue 50: one line naming the file or flag, exit 2, no
traceback, no hang, and nothing the user had changed.

The classes: ``train-editor`` (its run folder, absurd flags, ``--resume`` of nothing or of a
damaged dataset or checkpoint, a refused resume that must not rebuild the dataset), weights
folders (safetensors headers, fuzzed; network, scheduler and tokenizer configs; editor sizes),
masks that decode to more than the memory, prompts (not UTF-8, pages long), and the resume of
a damaged edit run directory (its checkpoint's record, data of another size, missing or
truncated snapshots). Multi-process disagreement is tested in ``test_distributed.py``.

Every case fails before JAX compiles anything: the CLI cases run in-process with stderr
captured at the descriptor level, the others call the one reader of the file.
"""

from __future__ import annotations

import json
import shutil
import struct
import types
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from cli_expect import contents, fails
from jaxedit import camera as camlib, gaussians as G
from jaxedit.errors import DataError, quoted
from jaxedit.io import save_nerfstudio, save_ply, write_image

PROMPT = "turn him into a bronze statue"


def _fails(capfd, argv, needle: str, keep: Path | None = None) -> str:
    """:func:`cli_expect.fails`, ``keep`` byte-identical afterwards."""
    return fails(capfd, argv, needle, keep=keep, snapshot=contents)


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> types.SimpleNamespace:
    """A 16 px, 4-view dataset (one held out), a scene, and the bundled editor's folder."""
    d = tmp_path_factory.mktemp("surfaces")
    rng = np.random.default_rng(0)
    cams = camlib.hemisphere(4, radius=2.2, width=16, height=16, fov_deg=50.0)
    images = rng.uniform(0.2, 0.8, size=(4, 16, 16, 3)).astype(np.float32)
    pts = rng.normal(scale=0.3, size=(30, 3)).astype(np.float32)
    data = save_nerfstudio(d / "data", images, cams, test_indices=np.array([1]), points=pts,
                           point_colors=rng.uniform(size=(30, 3)).astype(np.float32)).parent
    scene = d / "scene.ply"
    save_ply(scene, G.from_points(pts, rng.uniform(size=(30, 3)), sh_degree=0))
    return types.SimpleNamespace(dir=d, data=data, scene=scene)


# ----------------------------------------------------------------------------- train-editor

def _smoke_cfg():
    from jaxedit_lab.train_editor.tiny_ip2p import EditorTrainConfig

    return EditorTrainConfig.smoke()


def _vae_checkpoint(path: Path, *, config: dict | None = None, **meta) -> Path:
    """A ``checkpoints/vae.npz`` of the smoke config at step 0 with its record overridable
    (``_DROP`` removes a key). Its state is only the step counter: the record is read and
    refused before any state is restored (a real state's template takes a minute to build)."""
    from jaxedit.io.checkpoint import FORMAT_VERSION
    from jaxedit_lab.train_editor import _stage_record

    record = {"config": config or _stage_record(_smoke_cfg(), "editor-vae"), "step": 0,
              "losses": []}
    record = {k: v for k, v in {**record, **meta}.items() if v is not _DROP}
    path.parent.mkdir(parents=True, exist_ok=True)
    head = dict(version=FORMAT_VERSION, kind="editor-vae", paths=[".step"], keys=[],
                meta=record)
    with open(path, "wb") as f:
        np.savez(f, **{".step": np.int32(0), "__meta__": np.asarray(json.dumps(head))})
    return path


_DROP = object()  # a record key to leave out


def _run(tmp_path: Path) -> Path:
    """A run folder the user made earlier: a dataset and a note that must survive."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "dataset.npz").write_bytes(b"the user's dataset, whatever it holds")
    (run / "notes.txt").write_text("mine\n")
    return run


TE = ["train-editor", "--smoke", "--quiet"]


@pytest.mark.parametrize("name", ["checkpoints", "model", "model/tokenizer"])
def test_train_editor_refuses_a_run_folder_name_taken_by_a_file(tmp_path, capfd, name):
    run = tmp_path / "run"
    (run / name).parent.mkdir(parents=True, exist_ok=True)
    (run / name).write_text("a file where a folder goes\n")
    _fails(capfd, [*TE, "--out", run], name, keep=run)


@pytest.mark.parametrize("name", ["dataset.npz", "config.json"])
def test_train_editor_refuses_a_folder_where_its_files_go(tmp_path, capfd, name):
    run = tmp_path / "run"
    (run / name).mkdir(parents=True)
    _fails(capfd, [*TE, "--out", run], name, keep=run)


@pytest.mark.parametrize("flags, needle", [
    (["--lr", "0"], "--lr"), (["--vae-lr", "-0.001"], "--vae-lr"), (["--lr", "5"], "--lr"),
    (["--seed", str(2 ** 70)], "--seed"), (["--steps", "1000000000"], "--steps"),
    (["--vae-steps", str(10 ** 7)], "--vae-steps"), (["--size", "100000"], "--size"),
    (["--size", "40"], "--size"), (["--size", "48"], "--size"),
    (["--procedural-views", "99999999"], "--procedural-views"),
    (["--text-width", "33"], "--text-width"), (["--text-layers", "500"], "--text-layers"),
    (["--batch", "100000"], "--batch")])
def test_train_editor_refuses_absurd_settings_before_any_work(tmp_path, capfd, flags, needle):
    _fails(capfd, ["train-editor", "--quiet", "--out", tmp_path / "r", *flags], needle)
    assert not (tmp_path / "r").exists()


def test_train_editor_refuses_a_working_set_beyond_the_free_memory(tmp_path, capfd, monkeypatch):
    import jaxedit.memory

    monkeypatch.setattr(jaxedit.memory, "available_memory", lambda: 2 ** 20)
    line = _fails(capfd, ["train-editor", "--quiet", "--out", tmp_path / "r"], "--size")
    assert "memory" in line and not (tmp_path / "r").exists()


def test_train_editor_resume_of_nothing_is_refused(tmp_path, capfd):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    _fails(capfd, [*TE, "--out", run, "--resume"], "nothing to resume", keep=run)


def test_a_refused_resume_leaves_the_dataset_and_checkpoint_byte_identical(tmp_path, capfd):
    """The checkpoint was written with other settings: refused before the dataset is rebuilt
    (it used to be rebuilt and overwritten first, minutes of work, then refused)."""
    run = _run(tmp_path)
    other = dict(__import__("jaxedit_lab.train_editor", fromlist=["x"])._stage_record(
        _smoke_cfg(), "editor-vae"), size=64)
    _vae_checkpoint(run / "checkpoints" / "vae.npz", config=other)
    _fails(capfd, [*TE, "--out", run, "--resume"], "other settings", keep=run)


@pytest.mark.parametrize("meta, needle", [
    ({"step": _DROP}, "keys"), ({"extra": 1}, "keys"), ({"step": "0"}, "step"),
    ({"losses": {"a": 1}}, "losses"), ({"step": 5}, "inconsistent"),
    ({"step": 1, "losses": [float("nan")]}, "inconsistent"), ({"config": [1]}, "config")])
def test_train_editor_resume_of_a_damaged_checkpoint_record(tmp_path, capfd, meta, needle):
    run = _run(tmp_path)
    _vae_checkpoint(run / "checkpoints" / "vae.npz", **meta)
    line = _fails(capfd, [*TE, "--out", run, "--resume"], needle, keep=run)
    assert "vae.npz" in line


def _dataset_npz(path: Path, record: dict, **arrays) -> Path:
    from jaxedit_lab.train_editor import DATASET_ARRAYS

    n, size = 2, record.get("size", 32)
    full = {"inputs": np.zeros((n, size, size, 3), np.uint8), "scene": np.zeros(n, np.int32),
            "held_out": np.zeros(n, bool), "targets": np.zeros((n, size, size, 3), np.uint8),
            "target_view": np.arange(n, dtype=np.int32),
            "target_instruction": np.zeros(n, np.int32), "target_outcome": np.zeros(n, np.int32)}
    full.update(arrays)
    with open(path, "wb") as f:
        np.savez(f, meta=np.asarray(json.dumps(record)),
                 **{k: v for k, v in full.items() if v is not _DROP and k in
                    set(DATASET_ARRAYS) | set(arrays)})
    return path


def _smoke_record() -> dict:
    cfg = _smoke_cfg()
    return {"size": cfg.size, "procedural_views": cfg.procedural_views, "scenes": list(cfg.scenes)}


@pytest.mark.parametrize("damage, needle", [
    ("garbage", "cannot read"), ("no-meta", "settings record"),
    ("other-settings", "other settings"), ("not-a-bool", "settings record"),
    ("missing-array", "holds arrays"),
    ("wrong-dtype", "inputs"), ("wrong-size", "inputs are"), ("bad-index", "target_view")])
def test_train_editor_resume_of_a_damaged_dataset(tmp_path, capfd, damage, needle):
    run = tmp_path / "run"
    run.mkdir()
    path = run / "dataset.npz"
    record = _smoke_record()
    if damage == "garbage":
        path.write_bytes(b"PK\x03\x04" + bytes(range(256)))
    elif damage == "no-meta":
        np.savez(path, inputs=np.zeros(2))
    elif damage == "other-settings":
        _dataset_npz(path, dict(record, procedural_views=11))
    elif damage == "not-a-bool":
        _dataset_npz(path, dict(record, off_orbit_edits="no"))
    elif damage == "missing-array":
        _dataset_npz(path, record, targets=_DROP)
    elif damage == "wrong-dtype":
        _dataset_npz(path, record, inputs=np.zeros((2, 32, 32, 3), np.float32))
    elif damage == "wrong-size":
        _dataset_npz(path, record, inputs=np.zeros((2, 16, 16, 3), np.uint8))
    else:
        _dataset_npz(path, record, target_view=np.array([0, 7], np.int32))
    line = _fails(capfd, [*TE, "--out", run, "--resume"], needle, keep=run)
    assert "dataset.npz" in line


# ----------------------------------------------------------------------------- safetensors

def _safetensors(header: dict, body: bytes, *, hlen: int | None = None) -> bytes:
    raw = json.dumps(header).encode()
    return struct.pack("<Q", len(raw) if hlen is None else hlen) + raw + body


def _read(tmp_path: Path, data: bytes):
    from jaxedit.io.weights import read_safetensors

    path = tmp_path / "w.safetensors"
    path.write_bytes(data)
    return read_safetensors(path)


@pytest.mark.parametrize("header, body, needle", [
    ({"t": {"dtype": 5, "shape": [1], "data_offsets": [0, 4]}}, b"\0" * 4, "dtype"),
    ({"t": {"dtype": "F32", "shape": ["a"], "data_offsets": [0, 4]}}, b"\0" * 4, "shape"),
    ({"t": {"dtype": "F32", "shape": [-1], "data_offsets": [0, 4]}}, b"\0" * 4, "shape"),
    ({"t": {"dtype": "F32", "shape": [True], "data_offsets": [0, 4]}}, b"\0" * 4, "shape"),
    ({"t": {"dtype": "F32", "shape": [1], "data_offsets": [0]}}, b"\0" * 4, "data_offsets"),
    ({"t": {"dtype": "F32", "shape": [2], "data_offsets": [0, 4]}}, b"\0" * 4, "takes 8"),
    ({"t": {"dtype": "BF16", "shape": [1], "data_offsets": [0, 3]}}, b"\0" * 4, "takes 2"),
    ({"t": {"dtype": "F32", "shape": [1], "data_offsets": [0, 4], "x": 1}}, b"\0" * 4,
     "malformed"),
    ({"t": [1, 2]}, b"", "malformed"),
    ({"__metadata__": {"a": 1}}, b"", "__metadata__"),
    ({"__metadata__": [1]}, b"", "__metadata__"),
    ({"t": {"dtype": "F32", "shape": [10 ** 12], "data_offsets": [0, 4]}}, b"\0" * 4, "takes"),
])
def test_safetensors_headers_with_wrong_types_or_byte_counts(tmp_path, header, body, needle):
    with pytest.raises(DataError, match=needle):
        _read(tmp_path, _safetensors(header, body))


def test_safetensors_header_length_beyond_the_limit(tmp_path):
    with pytest.raises(DataError, match="header length"):
        _read(tmp_path, struct.pack("<Q", 2 ** 63) + b"{}")


_JSON = st.recursive(st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
                     | st.floats(allow_nan=False) | st.text(max_size=6),
                     lambda inner: st.lists(inner, max_size=4)
                     | st.dictionaries(st.text(max_size=6), inner, max_size=4), max_leaves=12)
_ENTRY = st.fixed_dictionaries({
    "dtype": st.sampled_from(["F32", "F16", "F64", "I64", "I32", "U8", "BF16", "Q4", ""]) | _JSON,
    "shape": st.lists(st.integers(-2, 5), max_size=3) | _JSON,
    "data_offsets": st.lists(st.integers(-4, 80), min_size=0, max_size=3) | _JSON},
    optional={"extra": _JSON})
FUZZ = settings(max_examples=150, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@FUZZ
@given(header=st.dictionaries(st.text(max_size=8), _ENTRY | _JSON, max_size=4),
       body=st.binary(max_size=80), slack=st.integers(-12, 12))
def test_fuzz_safetensors_reader_returns_what_the_header_says_or_a_data_error(
        tmp_path, header, body, slack):
    """Random headers (right and wrong types, byte counts that do and do not match the dtype)
    and header lengths: every file is read exactly as its header says or refused with a
    DataError, never anything else."""
    raw = json.dumps(header).encode()
    data = struct.pack("<Q", max(len(raw) + slack, 0)) + raw + body
    try:
        tensors, meta = _read(tmp_path, data)
    except DataError:
        return
    entries = {k: v for k, v in header.items() if k != "__metadata__"}
    assert set(tensors) == set(entries) and all(isinstance(v, str) for v in meta.values())
    for name, arr in tensors.items():
        lo, hi = entries[name]["data_offsets"]
        assert list(arr.shape) == entries[name]["shape"]
        assert arr.size * (2 if entries[name]["dtype"] == "BF16" else arr.itemsize) == hi - lo


@FUZZ
@given(data=st.binary(max_size=120))
def test_fuzz_safetensors_reader_on_random_bytes(tmp_path, data):
    try:
        _read(tmp_path, data)
    except DataError:
        pass


# ----------------------------------------------------------------------------- weights folders

@pytest.fixture()
def weights(tmp_path) -> Path:
    """A copy of the bundled editor's folder (weights linked, configs copied) to break."""
    from jaxedit.editors.bundled import bundled_editor

    src, dst = bundled_editor(), tmp_path / "ip2p"
    for p in src.rglob("*"):
        target = dst / p.relative_to(src)
        if p.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        elif p.suffix == ".safetensors":
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(p)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(p, target)
    return dst


def _set(folder: Path, name: str, **values) -> Path:
    path = folder / name
    config = json.loads(path.read_text())
    config.update(values)
    path.write_text(json.dumps(config))
    return path


@pytest.mark.parametrize("file, values, needle", [
    ("unet/config.json", {"block_out_channels": "abc"}, "block_out_channels"),
    ("unet/config.json", {"layers_per_block": 10 ** 6}, "layers_per_block"),
    ("unet/config.json", {"block_out_channels": [10 ** 6, 10 ** 6, 10 ** 6]},
     "block_out_channels"),
    ("unet/config.json", {"norm_num_groups": 7}, "norm_num_groups"),
    ("unet/config.json", {"cross_attention_dim": [1, 2]}, "cross_attention_dim"),
    ("vae/config.json", {"latent_channels": "4"}, "latent_channels"),
    ("vae/config.json", {"scaling_factor": -1}, "scaling_factor"),
    ("text_encoder/config.json", {"num_hidden_layers": 10 ** 5}, "num_hidden_layers"),
    ("text_encoder/config.json", {"hidden_size": 33}, "hidden_size"),
    ("text_encoder/config.json", {"max_position_embeddings": 10}, "position_embedding"),
    ("scheduler/scheduler_config.json", {"num_train_timesteps": 10 ** 12},
     "num_train_timesteps"),
    ("scheduler/scheduler_config.json", {"beta_start": "x"}, "beta_start"),
    ("scheduler/scheduler_config.json", {"beta_start": 0.5, "beta_end": 0.1}, "beta_start"),
    ("scheduler/scheduler_config.json", {"trained_betas": [0.1, 0.2]}, "trained_betas"),
    ("scheduler/scheduler_config.json", {"clip_sample": "yes"}, "clip_sample"),
    ("tokenizer/tokenizer_config.json", {"model_max_length": 5000}, "model_max_length"),
])
def test_weights_folder_configs_are_schema_checked(weights, file, values, needle):
    from jaxedit.models import load_ip2p

    path = _set(weights, file, **values)
    with pytest.raises(DataError) as e:
        load_ip2p(weights)
    assert str(path.parent) in str(e.value) and needle in str(e.value), str(e.value)


def test_weights_whose_config_cannot_fit_are_refused_before_any_network(weights, monkeypatch):
    import jaxedit.memory
    from jaxedit.models import load_ip2p

    monkeypatch.setattr(jaxedit.memory, "available_memory", lambda: 1024)
    with pytest.raises(DataError, match="unet/config.json: .*memory"):
        load_ip2p(weights)


def test_tokenizer_vocabulary_with_absurd_ids(weights):
    from jaxedit.models import CLIPTokenizer

    vocab = weights / "tokenizer" / "vocab.json"
    if not vocab.exists():
        pytest.skip("the bundled tokenizer has no vocab.json")
    ids = json.loads(vocab.read_text())
    first = next(iter(ids))
    for bad in ("x", 10 ** 12, -1):
        vocab.write_text(json.dumps(dict(ids, **{first: bad})))
        (weights / "tokenizer" / "tokenizer.json").unlink(missing_ok=True)
        with pytest.raises(DataError, match="vocab.json"):
            CLIPTokenizer.from_folder(weights / "tokenizer")


def test_ip2p_weights_with_a_broken_config_through_the_cli(corpus, weights, tmp_path, capfd):
    _set(weights, "unet/config.json", layers_per_block=10 ** 6)
    _fails(capfd, ["edit", "--data", corpus.data, "--scene", corpus.scene, "--prompt", PROMPT,
                   "--editor", "ip2p", "--ip2p-weights", weights, "--out", tmp_path / "o",
                   "--quiet"], "layers_per_block")
    assert not (tmp_path / "o").exists()


def test_editor_step_tables_and_sizes_are_checked_before_any_edit(monkeypatch):
    import jaxedit.memory
    from jaxedit.editors.jax_ip2p import check_edit_sizes

    with pytest.raises(DataError, match="--ip2p-steps: .* 1000 timesteps"):
        check_edit_sizes(64, 5000, 1, 1000, 4, 32, 4)
    check_edit_sizes(64, 20, 1, 1000, 4, 32, 4)
    monkeypatch.setattr(jaxedit.memory, "available_memory", lambda: 2 ** 20)
    with pytest.raises(DataError, match="--ip2p-size.*memory"):
        check_edit_sizes(512, 20, 4, 1000, 8, 320, 4)


# ----------------------------------------------------------------------------- masks

def _huge_png(path: Path, width: int, height: int) -> Path:
    """A grey PNG whose header says ``width`` x ``height`` and whose data holds four rows:
    a few hundred bytes on disk, gigabytes once decoded."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
                     + chunk(b"IDAT", zlib.compress(b"\0" * (width + 1) * 4))
                     + chunk(b"IEND", b""))
    return path


def test_a_mask_that_decodes_beyond_the_free_memory_is_refused_from_its_header(
        tmp_path, monkeypatch):
    import jaxedit.memory
    from jaxedit.editors.masks import check_mask_file

    mask = tmp_path / "frame.png"
    write_image(mask, np.ones((64, 64, 3), np.float32))  # 4x its view's size: a valid mask
    assert check_mask_file(mask, (16, 16)) == (64, 64)
    monkeypatch.setattr(jaxedit.memory, "available_memory", lambda: 64 * 64)
    with pytest.raises(DataError, match="frame.png: decoding a 64x64 px mask .* memory"):
        check_mask_file(mask, (16, 16))


def test_a_mask_of_another_size_is_refused_before_decoding(tmp_path):
    from jaxedit.editors.masks import check_mask_file

    with pytest.raises(DataError, match="mask is 50x50 px"):
        check_mask_file(_huge_png(tmp_path / "m.png", 50, 50), (16, 16))
    write_image(tmp_path / "ok.png", np.ones((32, 32, 3), np.float32))
    assert check_mask_file(tmp_path / "ok.png", (16, 16)) == (32, 32)


def test_huge_masks_through_the_cli(corpus, tmp_path, capfd):
    masks = tmp_path / "masks"
    masks.mkdir()
    for i in range(4):
        _huge_png(masks / f"frame_{i:05d}.png", 16 * 6000, 16 * 6000)
    _fails(capfd, ["edit", "--data", corpus.data, "--scene", corpus.scene, "--prompt", PROMPT,
                   "--masks", masks, "--out", tmp_path / "o", "--quiet"], "frame_0000")
    assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- prompts

def test_a_prompt_that_is_not_utf8_is_one_line():
    from jaxedit.editors.jax_ip2p import check_prompt

    assert check_prompt("make it blue") == "make it blue"
    with pytest.raises(DataError, match=r"prompt: is not valid UTF-8 .*b'\\xff' at character 1"):
        check_prompt("a\udcffb")


def test_error_lines_quote_a_long_prompt_in_part(corpus, tmp_path, capfd):
    assert quoted("short") == "'short'"
    assert quoted("z" * 10_000).endswith("... (10000 characters)")
    line = _fails(capfd, ["edit", "--data", corpus.data, "--scene", corpus.scene, "--prompt",
                          "z" * 10_000, "--out", tmp_path / "o", "--quiet"], "--prompt")
    assert len(line) < 1000 and "10000 characters" in line


# ----------------------------------------------------------------------------- edit --resume

def _edit_run(corpus, tmp_path: Path, *, size: int = 16, views: int = 3, finished=(),
              **record) -> Path:
    """A run folder whose checkpoint.npz is a fresh edit state (``views`` images of ``size``
    px) with its record overridden by ``record`` (``_DROP`` removes a key)."""
    from jaxedit.edit.checkpoint import KIND, save_checkpoint
    from jaxedit.edit.state import EditState, LossTracker
    from jaxedit.edit.trainer import SubtaskTrainer, EditTrainConfig
    from jaxedit.io import load_ply
    from jaxedit.io.checkpoint import read_pytree

    run = tmp_path / "run"
    run.mkdir(exist_ok=True)
    g = load_ply(corpus.scene)
    train = SubtaskTrainer(EditTrainConfig(scene_extent=1.0), int(g.num_alive())).init(g)
    st = EditState.create(subtask=0, step=0, train=train,
                          images=np.zeros((views, size, size, 3), np.float32),
                          edited=np.zeros(views, bool), tracker=LossTracker.init(10),
                          records=tuple(finished))
    plan = [{"index": 0, "name": "r1", "ratio": 1.0, "difficulty": None, "kind": "edit"}]
    ckpt = run / "checkpoint.npz"
    save_checkpoint(ckpt, st, {"plan": plan, "header": {}, "wall_time_s": 1.0})
    # The trainer's intersection buffer as a run sizes it from its cameras (unsized here).
    arrays, info = read_pytree(ckpt, kind=KIND)
    info = {k: v for k, v in {**info, "max_intersections": 4096, **record}.items()
            if v is not _DROP}
    _write_raw(ckpt, arrays, info)
    (run / "config.json").write_text('{"the": "record"}\n')
    return run


def _write_raw(path: Path, arrays: dict, info: dict) -> None:
    """Write ``arrays`` (by leaf path) and the meta record ``info`` as save_pytree would."""
    from jaxedit.io.checkpoint import FORMAT_VERSION

    record = dict(version=FORMAT_VERSION, kind="edit", paths=list(arrays), keys=[], meta=info)
    with open(path, "wb") as f:
        np.savez(f, __meta__=np.asarray(json.dumps(record)), **arrays)


def _resume(corpus, run: Path) -> list:
    return ["edit", "--data", corpus.data, "--scene", corpus.scene, "--prompt", PROMPT,
            "--out", run, "--resume", "--quiet"]


@pytest.mark.parametrize("record, needle", [
    ({"seconds": _DROP}, "lacks seconds"), ({"subtask": _DROP}, "lacks subtask"),
    ({"surprise": 1}, "unknown surprise"), ({"step": "3"}, "step"),
    ({"step": True}, "step"), ({"records": {}}, "records"), ({"tracker": [1, 2]}, "tracker"),
    ({"utilisation": {"bogus": 1}}, "utilisation"), ({"subtask": -1}, "negative"),
    ({"meta": {"plan": [{"index": 0}], "header": {}}}, "plan"),
    ({"meta": {"header": {}}}, "lacks plan"), ({"max_intersections": 0}, "max_intersections")])
def test_edit_resume_with_damaged_checkpoint_metadata(corpus, tmp_path, capfd, record, needle):
    run = _edit_run(corpus, tmp_path, **record)
    line = _fails(capfd, _resume(corpus, run), needle, keep=run)
    assert "checkpoint.npz" in line


def test_edit_resume_on_data_of_another_size_rewrites_nothing(corpus, tmp_path, capfd):
    """It used to rewrite the checkpoint, fail with a traceback, and leave config.json
    naming the other dataset."""
    run = _edit_run(corpus, tmp_path, size=8)
    _fails(capfd, _resume(corpus, run), "8x8 px, the data has 3 of 16x16", keep=run)


def _scene_snapshot(run: Path, corpus, name: str = "00_r1.000") -> tuple[str, dict]:
    from jaxedit.edit.checkpoint import snapshot_fingerprint

    rel = f"subtasks/{name}/scene.ply"
    (run / rel).parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(corpus.scene, run / rel)
    return rel, {"index": 0, "name": "r1", "snapshot": rel, **snapshot_fingerprint(run / rel)}


@pytest.mark.parametrize("damage, needle", [("deleted", "missing"),
                                            ("truncated", "truncated or replaced"),
                                            ("replaced", "truncated or replaced"),
                                            ("garbage-no-hash", "scene.ply")])
def test_edit_resume_verifies_every_recorded_snapshot(corpus, tmp_path, capfd, damage, needle):
    run = tmp_path / "run"
    run.mkdir()
    rel, record = _scene_snapshot(run, corpus)
    if damage == "garbage-no-hash":  # a record of an older run: no size or hash to compare
        record = {k: v for k, v in record.items() if not k.startswith("snapshot_")}
    run = _edit_run(corpus, tmp_path, finished=[record])
    (run / "schedule.json").write_text(json.dumps({"subtasks": [record]}))
    snap = run / rel
    if damage == "deleted":
        snap.unlink()
    elif damage == "truncated":
        snap.write_bytes(snap.read_bytes()[:100])
    elif damage == "replaced":
        data = snap.read_bytes()
        snap.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))  # one bit of the last byte
    else:
        snap.write_bytes(b"ply\nnot a scene\n")
    line = _fails(capfd, _resume(corpus, run), needle, keep=run)
    assert rel in line


def test_snapshots_named_only_by_schedule_json_are_verified_too(corpus, tmp_path):
    from jaxedit.edit.checkpoint import verify_snapshots

    run = tmp_path / "run"
    run.mkdir()
    rel, record = _scene_snapshot(run, corpus)
    (run / "schedule.json").write_text(json.dumps({"subtasks": [record]}))
    verify_snapshots(run, [])  # intact
    (run / rel).unlink()
    with pytest.raises(DataError, match="00_r1.000/scene.ply: the snapshot .* is missing"):
        verify_snapshots(run, [])


# ----------------------------------------------------------------------------- multi-process

@pytest.mark.parametrize("script, expected", [
    # The worker's own line comes after the runtime's fatal log began: it is still shown.
    ("import sys; sys.stderr.write('F1127 11:00:00.000000   1 client.cc:1] lost it\\n"
     "error: --out: the processes disagree\\n'); sys.exit(2)",
     "error: --out: the processes disagree"),
    # Status 2 and no line at all: the supervisor says so, in one line.
    ("import sys; sys.exit(2)", "error: process 0 of 2 stopped: exited with status 2")])
def test_a_supervised_worker_ends_with_exactly_one_line(tmp_path, script, expected):
    import io
    import sys

    from jaxedit.parallel.distributed import DistributedConfig, supervise

    err = io.StringIO()
    code = supervise([sys.executable, "-c", script], DistributedConfig("h:1", 2, 0), stderr=err)
    assert code == 2 and err.getvalue().strip().splitlines() == [expected], err.getvalue()
