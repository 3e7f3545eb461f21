"""CLIP edit metrics: the arithmetic on constructed embeddings with known answers, and the
encoder on a tiny random CLIP model the test builds and saves in transformers' layout."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from jaxedit.clip_metrics import direction_metrics
from jaxedit.errors import DataError

# ----------------------------------------------------------------------------- arithmetic


def test_known_directions():
    n = 4
    orig = np.tile([1.0, 0.0, 0.0], (n, 1))
    edit = np.tile([0.0, 2.0, 0.0], (n, 1))  # scale is irrelevant: embeddings are normalised
    m = direction_metrics(orig, edit, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    assert m["direction_similarity"] == pytest.approx(1.0)
    assert m["direction_consistency"] == pytest.approx(1.0)
    assert m["image_similarity"] == pytest.approx(0.0)
    assert m["clip_score_edit"] == pytest.approx(1.0)
    assert m["views"] == n and len(m["per_pair_direction_consistency"]) == n - 1
    # Swapping the images' roles reverses the image direction: the sign flips.
    swapped = direction_metrics(edit, orig, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    assert swapped["direction_similarity"] == pytest.approx(-1.0)
    assert swapped["direction_consistency"] == pytest.approx(1.0)
    # Text direction orthogonal to the image direction -> 0.
    m = direction_metrics(orig, edit, np.array([0, 0, 1.0]), np.array([1.0, 0, 1.0]))
    # dI = (-1, 1, 0), dT = (1/sqrt2, 0, 1/sqrt2 - 1): cos = (-1/sqrt2) / (sqrt2 * |dT|)
    d_t = np.array([1, 0, 1]) / np.sqrt(2) - np.array([0, 0, 1])
    expect = (-1 / np.sqrt(2)) / (np.sqrt(2) * np.linalg.norm(d_t))
    assert m["direction_similarity"] == pytest.approx(expect)


def test_consistency_of_alternating_directions():
    # View k's edit goes one way, view k+1's the opposite way: consistency -1.
    e1, e2 = np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    orig = np.array([e1, e2, e1, e2])
    edit = np.array([e2, e1, e2, e1])
    m = direction_metrics(orig, edit, e1, e2)
    assert m["direction_consistency"] == pytest.approx(-1.0)
    assert m["per_view_direction_similarity"] == pytest.approx([1.0, -1.0, 1.0, -1.0])
    assert m["direction_similarity"] == pytest.approx(0.0)


def test_no_edit_is_undefined_not_a_number():
    orig = np.eye(3)
    m = direction_metrics(orig, orig.copy(), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    assert np.isnan(m["direction_similarity"]) and np.isnan(m["direction_consistency"])
    assert m["undefined"] == {"direction_similarity": 3, "direction_consistency": 2}
    # One unchanged view among edited ones is skipped, not averaged in as 0.
    edit = np.array([[0, 1.0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    m = direction_metrics(np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]]), edit,
                          np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    assert m["direction_similarity"] == pytest.approx(1.0)
    assert m["undefined"]["direction_similarity"] == 1


def test_shape_errors():
    with pytest.raises(DataError, match="images"):
        direction_metrics(np.ones((3, 4)), np.ones((2, 4)), np.ones(4), np.ones(4))
    with pytest.raises(DataError, match="captions"):
        direction_metrics(np.ones((3, 4)), np.ones((3, 4)), np.ones(5), np.ones(4))


vec = arrays(np.float64, (5, 6), elements=st.floats(-1, 1, allow_nan=False, width=32))
txt = arrays(np.float64, (6,), elements=st.floats(-1, 1, allow_nan=False, width=32))


@settings(max_examples=40, deadline=None)
@given(io=vec, ie=vec, to=txt, te=txt)
def test_symmetries(io, ie, to, te):
    io, ie, to, te = io + 0.05, ie - 0.05, to + 0.1, te - 0.1  # keep away from zero vectors
    m = direction_metrics(io, ie, to, te)
    both = direction_metrics(ie, io, te, to)   # swap both roles: unchanged
    imgs = direction_metrics(ie, io, to, te)   # swap the images only: sign flips
    for key in ("direction_similarity", "direction_consistency"):
        a, b = m[key], both[key]
        assert np.isnan(a) == np.isnan(b)
        if not np.isnan(a):
            assert -1 - 1e-9 <= a <= 1 + 1e-9
            assert b == pytest.approx(a, abs=1e-9)
    if not np.isnan(m["direction_similarity"]):
        assert imgs["direction_similarity"] == pytest.approx(-m["direction_similarity"], abs=1e-9)
    # Reversing the path order leaves both means unchanged.
    rev = direction_metrics(io[::-1], ie[::-1], to, te)
    assert rev["direction_similarity"] == pytest.approx(m["direction_similarity"], nan_ok=True)
    assert rev["direction_consistency"] == pytest.approx(m["direction_consistency"], nan_ok=True)


# ----------------------------------------------------------------------------- tiny CLIP

@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    torch = pytest.importorskip("torch")
    transformers = pytest.importorskip("transformers")
    root = tmp_path_factory.mktemp("clip") / "tiny-clip"
    torch.manual_seed(0)
    letters = "abcdefghijklmnopqrstuvwxyz"
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for token in list(letters) + [c + "</w>" for c in letters]:
        vocab[token] = len(vocab)
    config = transformers.CLIPConfig(
        text_config=dict(vocab_size=len(vocab), hidden_size=32, intermediate_size=37,
                         num_hidden_layers=2, num_attention_heads=4, max_position_embeddings=77,
                         bos_token_id=0, eos_token_id=1, pad_token_id=1),
        vision_config=dict(image_size=32, patch_size=8, hidden_size=32, intermediate_size=37,
                           num_hidden_layers=2, num_attention_heads=4),
        projection_dim=16)
    transformers.CLIPModel(config).save_pretrained(root)
    (root / "vocab.json").write_text(json.dumps(vocab))
    (root / "merges.txt").write_text("#version: 0.2\n")
    transformers.CLIPTokenizer(vocab=str(root / "vocab.json"), merges=str(root / "merges.txt"),
                               model_max_length=77).save_pretrained(root)
    (root / "preprocessor_config.json").write_text(json.dumps({
        "crop_size": {"height": 32, "width": 32}, "size": {"shortest_edge": 32},
        "image_mean": [0.48145466, 0.4578275, 0.40821073],
        "image_std": [0.26862954, 0.26130258, 0.27577711]}))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield root
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def encoder(clip_dir):
    from jaxedit.clip_metrics import ClipEncoder
    return ClipEncoder.from_pretrained(clip_dir, device="cpu")


def _views(seed, n=4, h=40, w=56):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 1, (n, h, w, 3)).astype(np.float32)


def test_encoder_shapes_and_norms(encoder):
    imgs = _views(0)
    f = encoder.encode_images(imgs)
    assert f.shape == (4, 16) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, rtol=1e-5)
    # Batching does not change embeddings.
    one_by_one = np.concatenate([encoder.encode_images(imgs[i:i + 1]) for i in range(4)])
    np.testing.assert_allclose(one_by_one, f, atol=1e-5)
    t = encoder.encode_texts(["a bear", "a panda bear"])
    assert t.shape == (2, 16)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0, rtol=1e-5)
    assert not np.allclose(t[0], t[1])


def test_identical_views_are_perfectly_consistent(encoder):
    orig = np.repeat(_views(1, n=1), 5, axis=0)
    edit = np.repeat(_views(2, n=1), 5, axis=0)
    m = encoder.edit_metrics(orig, edit, "a bear", "a panda")
    assert m["direction_consistency"] == pytest.approx(1.0, abs=1e-5)
    assert m["views"] == 5 and -1 <= m["direction_similarity"] <= 1
    swapped = encoder.edit_metrics(edit, orig, "a bear", "a panda")
    assert swapped["direction_similarity"] == pytest.approx(-m["direction_similarity"], abs=1e-5)
    both = encoder.edit_metrics(edit, orig, "a panda", "a bear")
    assert both["direction_similarity"] == pytest.approx(m["direction_similarity"], abs=1e-5)


def test_metrics_match_embeddings(encoder):
    orig, edit = _views(3), _views(4)
    m = encoder.edit_metrics(orig, edit, "a bear", "a panda")
    t = encoder.encode_texts(["a bear", "a panda"])
    ref = direction_metrics(encoder.encode_images(orig), encoder.encode_images(edit), t[0], t[1])
    assert m["direction_similarity"] == pytest.approx(ref["direction_similarity"], abs=1e-6)
    assert m["direction_consistency"] == pytest.approx(ref["direction_consistency"], abs=1e-6)
    json.dumps(m)  # the runner writes it as JSON
    with pytest.raises(DataError, match="3 original renders but 4"):
        encoder.edit_metrics(orig[:3], edit, "a", "b")


def test_missing_clip_weights(tmp_path, clip_dir):
    from jaxedit.clip_metrics import ClipEncoder, load_clip_metrics

    with pytest.raises(DataError, match="CLIP weights folder not found.*huggingface-cli download"):
        ClipEncoder.from_pretrained(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no config.json"):
        load_clip_metrics(tmp_path / "empty")
    with pytest.raises(DataError, match="not in the local Hugging Face cache"):
        load_clip_metrics("someone/not-cached-clip")
    assert callable(load_clip_metrics(clip_dir, device="cpu"))


def test_clip_metrics_command(clip_dir, tmp_path, capsys, monkeypatch):
    """The command on a run directory laid out as the edit command writes it."""
    import experiments.cli as cli
    from jaxedit.io import write_image

    run = tmp_path / "run"
    for folder, seed in [("original", 10), ("subtasks/00_r0.000", 11), ("subtasks/01_r1.000", 12)]:
        for k, img in enumerate(_views(seed, n=3, h=24, w=32)):
            write_image(run / folder / "renders" / f"view_{k:03d}.png", img)
    if "clip-metrics" not in cli.COMMANDS:  # until the lead registers the command
        monkeypatch.setattr(cli, "COMMANDS", cli.COMMANDS + ["clip-metrics"])
    args = ["clip-metrics", "--run", str(run), "--clip-weights", str(clip_dir),
            "--caption-orig", "a bear", "--caption-edit", "a panda", "--clip-device", "cpu"]
    assert cli.main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["views"] == 3 and out["snapshot"].endswith("01_r1.000")
    saved = json.loads((run / "subtasks/01_r1.000/clip_metrics.json").read_text())
    assert saved["direction_similarity"] == pytest.approx(out["direction_similarity"])
    # Missing weights: one line, status 2.
    assert cli.main(args[:4] + [str(tmp_path / "nope")] + args[5:]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "nope" in err and "--clip-weights" in err


def test_clip_metrics_of_a_node_of_the_tree(clip_dir, tmp_path, capsys, monkeypatch):
    """--select NODE: a main subtask or a branch's, as edit --select-only names it."""
    import experiments.cli as cli
    from jaxedit.io import write_image

    run = tmp_path / "run"
    folders = {"original": 10, "subtasks/00_r0.500": 11, "subtasks/01_r1.000": 12,
               "branches/b1/subtasks/00_r0.750": 13, "branches/b1/subtasks/01_r1.000": 14}
    for folder, seed in folders.items():
        for k, img in enumerate(_views(seed, n=3, h=24, w=32)):
            write_image(run / folder / "renders" / f"view_{k:03d}.png", img)
    for base, ratios in (("", (0.5, 1.0)), ("branches/b1/", (0.75, 1.0))):
        records = [{"index": i, "name": f"r{r}", "ratio": r,
                    "snapshot": f"subtasks/{i:02d}_r{r:.3f}/scene.ply"} for i, r in enumerate(ratios)]
        for r in records:
            (run / base / r["snapshot"]).write_bytes(b"ply")
        (run / base / "schedule.json").write_text(json.dumps({"subtasks": records}))
    if "clip-metrics" not in cli.COMMANDS:
        monkeypatch.setattr(cli, "COMMANDS", cli.COMMANDS + ["clip-metrics"])
    args = ["clip-metrics", "--run", str(run), "--clip-weights", str(clip_dir),
            "--caption-orig", "a bear", "--caption-edit", "a panda", "--clip-device", "cpu"]
    scores = {}
    for node, folder in (("b1:0", "branches/b1/subtasks/00_r0.750"), ("0", "subtasks/00_r0.500"),
                         ("b1:-1", "branches/b1/subtasks/01_r1.000")):
        assert cli.main(args + ["--select", node]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["snapshot"] == str(run / folder)
        assert (run / folder / "clip_metrics.json").is_file()
        scores[node] = out["direction_similarity"]
    assert len(set(scores.values())) == 3  # three snapshots, three scores
    for node, needle in (("b9:0", "no branch 'b9'"), ("b1:5", "no finished subtask"),
                         ("../x:0", "--select")):
        assert cli.main(args + ["--select", node]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and needle in err, err
    assert cli.main(args + ["--select", "0", "--snapshot", str(run / "original")]) == 2
    assert "either" in capsys.readouterr().err
