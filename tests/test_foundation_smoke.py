import subprocess
import sys

import numpy as np


def test_import_is_light():
    # In a fresh interpreter: other tests in this process may have imported torch already.
    code = ("import sys, jaxedit; heavy = [m for m in ('torch', 'diffusers', 'transformers', "
            "'matplotlib.pyplot') if m in sys.modules]; print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_gaussians_from_points_and_grow():
    from jaxedit import gaussians as G

    rng = np.random.default_rng(0)
    g = G.from_points(rng.normal(size=(20, 3)), rng.uniform(size=(20, 3)), capacity=24)
    assert g.capacity == 24 and int(g.num_alive()) == 20 and g.sh_degree == 3
    assert np.allclose(np.asarray(g.opacities()[:20]), 0.1, atol=1e-6)
    big = G.grow(g, 48)
    assert big.capacity == 48 and int(big.num_alive()) == 20


def test_quaternion_rotation_is_orthonormal_and_zero_quat_is_safe():
    import jax.numpy as jnp

    from jaxedit import gaussians as G

    q = jnp.array([[0.3, -1.2, 0.5, 2.0], [0.0, 0.0, 0.0, 0.0], [5.0, 0.0, 0.0, 0.0]])
    r = np.asarray(G.quat_to_rotmat(q))
    assert np.all(np.isfinite(r))
    for m in r:
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-5)
        assert np.linalg.det(m) > 0.99
    np.testing.assert_allclose(r[1], np.eye(3))
    cov = np.asarray(G.covariance(q[:1], jnp.log(jnp.array([[0.1, 0.2, 0.3]]))))[0]
    np.testing.assert_allclose(np.sort(np.linalg.eigvalsh(cov)), [0.01, 0.04, 0.09], rtol=1e-4)


def test_sh_degree_one_matches_inria_sign_convention():
    import jax.numpy as jnp

    from jaxedit import sh

    coeffs = np.zeros((4, 3), np.float32)
    coeffs[1] = 1.0  # the -C1 * y term
    rgb = np.asarray(sh.evaluate(jnp.asarray(coeffs), jnp.array([0.0, 1.0, 0.0])))
    np.testing.assert_allclose(rgb, 0.5 - sh.C1, atol=1e-6)
    dc = sh.rgb_to_dc(np.array([0.2, 0.5, 0.9]))
    np.testing.assert_allclose(sh.dc_to_rgb(dc), [0.2, 0.5, 0.9], atol=1e-12)
