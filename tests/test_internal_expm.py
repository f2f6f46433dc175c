"""The exponential of small matrices (``_solvers.expm``: Taylor polynomial, scaling and squaring) against SciPy's
Padé, from tiny norms to stiff generators, and its derivatives against JAX's ``expm``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from nhsde._solvers import expm


def _generator(norm, size=5, seed=0):
    """A random matrix of 1-norm ``norm`` shifted to decay at rate ``norm`` (a stiff, stable generator)."""
    a = np.random.default_rng(seed).normal(size=(size, size))
    return a * norm / np.abs(a).sum(0).max() - norm * np.eye(size)


@pytest.mark.parametrize("norm", [1e-8, 0.3, 4.0, 60.0, 1e3, 1e6])
@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-12), (np.float32, 1e-5)])
def test_expm_matches_scipy_from_tiny_to_stiff_norms(norm, dtype, rtol):
    m = _generator(norm)
    exact = scipy.linalg.expm(m)
    got = np.asarray(jax.jit(expm)(jnp.asarray(m, dtype)), np.float64)
    assert got.dtype == np.float64 and np.all(np.isfinite(got))
    # relative to the largest entry: past a norm of ~40 every entry underflows towards 0
    scale = max(np.abs(exact).max(), np.finfo(dtype).tiny)
    np.testing.assert_allclose(got, exact, rtol=0, atol=rtol * scale * max(1.0, np.log2(max(norm, 1.0))))


def test_expm_derivatives_in_both_modes_match_jax():
    m = jnp.asarray(_generator(3.0, size=4, seed=1))
    direction = jnp.asarray(np.random.default_rng(2).normal(size=(4, 4)))

    def loss(f):
        return lambda x: jnp.sum(f(x) * direction)

    expected = jax.grad(loss(jax.scipy.linalg.expm))(m)
    np.testing.assert_allclose(jax.jit(jax.grad(loss(expm)))(m), expected, rtol=1e-11, atol=1e-13)
    forward = jax.jacfwd(loss(expm))(m)
    np.testing.assert_allclose(forward, expected, rtol=1e-11, atol=1e-13)
