"""The ``reconstruct`` command end to end on a tiny built-in dataset: outputs, resume, errors."""

import json

import numpy as np
import pytest

from experiments import cli
from jaxedit import scenes
from jaxedit.io import load_ply


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("face16")
    scenes.make_scene("face", root, size=16, views=4, test_views=1, num_points=200,
                      supersample=1)
    return root


def test_reconstruct_writes_ply_renders_metrics_and_resumes(dataset, tmp_path):
    out = tmp_path / "run"
    flags = ["--data", str(dataset), "--out", str(out), "--warmup", "100", "--quiet",
             "--checkpoint-every", "2", "--iters", "6"]
    assert cli.main(["reconstruct", *flags]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("test_psnr", "test_ssim", "num_gaussians", "wall_time_s", "steps_per_s"):
        assert isinstance(metrics[key], (int, float)) and np.isfinite(metrics[key]), key
    assert metrics["iterations"] == 6 and metrics["eval_split"] == "test"
    assert 0 < metrics["test_ssim"] <= 1 and metrics["test_psnr"] > 5
    g = load_ply(out / "scene.ply")
    assert g.capacity == metrics["num_gaussians"] == 200
    assert len(list((out / "test").glob("*.png"))) == 1
    assert (out / "test_compare.png").exists()
    assert [p.name for p in sorted((out / "checkpoints").glob("*.npz"))] == [
        "ckpt_00000004.npz", "ckpt_00000006.npz"]
    lines = (out / "train_log.jsonl").read_text().splitlines()
    assert json.loads(lines[-1])["step"] == 6
    # A run killed after step 4 (its last checkpoint) and resumed ends with the same bytes.
    ply = (out / "scene.ply").read_bytes()
    (out / "checkpoints" / "ckpt_00000006.npz").unlink()
    assert cli.main(["reconstruct", *flags, "--resume"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["resumed_from"] == 4 and metrics["iterations"] == 6
    assert metrics["steps_run"] == 2
    assert (out / "scene.ply").read_bytes() == ply


def test_reconstruct_reports_bad_input_in_one_line(tmp_path, capsys):
    assert cli.main(["reconstruct", "--data", str(tmp_path / "nope"), "--out",
                     str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:")
    assert cli.main(["reconstruct", "--data", str(tmp_path), "--out", str(tmp_path / "o"),
                     "--sh-degree", "5", "--quiet"]) == 2


def test_reconstruct_camera_opt_writes_the_corrected_dataset_and_resumes(dataset, tmp_path):
    """--camera-opt: the learned corrections move the training cameras of RUN/dataset (a
    nerfstudio dataset of the images as trained) and leave the test cameras; a resumed run
    ends with the same bytes."""
    from jaxedit.io import load_nerfstudio

    out = tmp_path / "run"
    flags = ["--data", str(dataset), "--out", str(out), "--warmup", "100", "--quiet",
             "--checkpoint-every", "4", "--iters", "6", "--camera-opt",
             "--camera-opt-from", "0", "--camera-lr", "0.01"]
    assert cli.main(["reconstruct", *flags]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    corr = metrics["camera_corrections"]
    assert metrics["config"]["camera_opt"] and 0 < corr["median_rotation_deg"] < 5
    original, learned = load_nerfstudio(dataset), load_nerfstudio(out / "dataset")
    assert learned.filenames == original.filenames
    np.testing.assert_array_equal(learned.train_indices, original.train_indices)
    np.testing.assert_array_equal(learned.test_indices, original.test_indices)
    np.testing.assert_allclose(learned.images, original.images, atol=1 / 255)
    w2c_orig = np.asarray(original.cameras.world_to_camera)
    w2c_new = np.asarray(learned.cameras.world_to_camera)
    test, train = original.test_indices, original.train_indices
    np.testing.assert_allclose(w2c_new[test], w2c_orig[test], atol=1e-5)
    moved = np.abs(w2c_new[train] - w2c_orig[train]).max(axis=(1, 2))
    assert (moved > 1e-4).all() and (moved < 0.5).all()
    ply = (out / "scene.ply").read_bytes()
    transforms = (out / "dataset" / "transforms.json").read_bytes()
    (out / "checkpoints" / "ckpt_00000006.npz").unlink()
    assert cli.main(["reconstruct", *flags, "--resume"]) == 0
    assert json.loads((out / "metrics.json").read_text())["resumed_from"] == 4
    assert (out / "scene.ply").read_bytes() == ply
    assert (out / "dataset" / "transforms.json").read_bytes() == transforms
