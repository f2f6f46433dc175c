"""∂k_xx(t)/∂ε and ∂k_xx(t)/∂ν through simulate: reverse, forward, finite differences, analytic."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ball_covariances

KEY = jax.random.key(7)
T1, DT, N = 2.0, 0.004, 4096


def ensemble(eps, nu, dtype, paths=False):
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    return nhsde.simulate(
        scene.build(),
        scene.initial_state().astype(dtype),
        KEY,
        n_paths=N,
        t1=T1,
        dt=DT,
        save=nhsde.Save(names=("x",), n=3, paths=paths),
    )


def k_xx(eps, nu, dtype):
    return ensemble(eps, nu, dtype).cov[:, 0, 0]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_gradient_matches_analytic_within_monte_carlo_error(dtype):
    eps, nu = jnp.asarray(1.0, dtype), jnp.asarray(1.5, dtype)
    delta = 1 / 1.4
    rev = jax.jacrev(k_xx, argnums=(0, 1))(eps, nu, dtype)
    fwd = jax.jacfwd(k_xx, argnums=(0, 1))(eps, nu, dtype)
    rtol = 1e-4 if dtype == jnp.float32 else 1e-10
    for r, f in zip(rev, fwd):
        np.testing.assert_allclose(r, f, rtol=rtol, atol=rtol * 1e-3)

    # Per-path tangents give the Monte-Carlo error of the pathwise gradient estimator:
    # d k̂/dθ = 2/(n−1) Σ (x_i − x̄)(ẋ_i − mean ẋ).
    ts = jnp.linspace(0.0, T1, 3).astype(jnp.float64)
    exact_grad = jax.jacfwd(lambda e, n: ball_covariances(ts, e, n, delta)[0], argnums=(0, 1))(1.0, 1.5)
    for arg, (grad, exact) in enumerate(zip(rev, exact_grad)):
        tangent = (1.0, 0.0) if arg == 0 else (0.0, 1.0)
        x, xdot = jax.jvp(
            lambda e, n: ensemble(e, n, dtype, paths=True).paths[:, :, 0],
            (eps, nu),
            tuple(jnp.asarray(v, dtype) for v in tangent),
        )
        x, xdot = np.asarray(x, np.float64), np.asarray(xdot, np.float64)
        xc, xdc = x - x.mean(0), xdot - xdot.mean(0)
        g = 2 * xc * xdc * N / (N - 1)
        np.testing.assert_allclose(g.mean(0), grad, rtol=1e-3 if dtype == jnp.float32 else 1e-9, atol=1e-6)
        se = g.std(0) / np.sqrt(N)
        err = np.abs(np.asarray(grad, np.float64) - np.asarray(exact))
        assert np.all(err[1:] <= 4 * se[1:]), (arg, grad, exact, se)


def test_gradient_matches_central_finite_difference():
    """Same key ⇒ common random numbers: the FD of the estimator is its derivative to O(h²)."""
    eps, nu, h = 0.7, 1.2, 1e-4
    grad = jax.grad(lambda e: k_xx(e, nu, jnp.float64)[-1])(jnp.float64(eps))
    fd = (k_xx(eps + h, nu, jnp.float64)[-1] - k_xx(eps - h, nu, jnp.float64)[-1]) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)
    grad_nu = jax.grad(lambda n: k_xx(eps, n, jnp.float64)[-1])(jnp.float64(nu))
    # k_xx is exactly linear in ν on every path, so ∂k̂/∂ν = k̂/ν
    np.testing.assert_allclose(grad_nu, k_xx(eps, nu, jnp.float64)[-1] / nu, rtol=1e-10)


def test_gradient_under_jit_and_value_and_grad():
    f = jax.jit(jax.value_and_grad(lambda e, n: k_xx(e, n, jnp.float32)[-1], argnums=(0, 1)))
    value, (ge, gn) = f(jnp.float32(1.0), jnp.float32(1.0))
    assert np.isfinite(value) and np.isfinite(ge) and np.isfinite(gn)
    assert ge < 0 < gn  # more friction, less spread; more noise, more spread
