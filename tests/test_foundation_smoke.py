import sys

import numpy as np


def test_import_is_light():
    import jaxedit  # noqa: F401

    assert "torch" not in sys.modules


def test_gaussians_from_points_and_grow():
    from jaxedit import gaussians as G

    rng = np.random.default_rng(0)
    g = G.from_points(rng.normal(size=(20, 3)), rng.uniform(size=(20, 3)), capacity=24)
    assert g.capacity == 24 and int(g.num_alive()) == 20 and g.sh_degree == 3
    assert np.allclose(np.asarray(g.opacities()[:20]), 0.1, atol=1e-6)
    big = G.grow(g, 48)
    assert big.capacity == 48 and int(big.num_alive()) == 20
