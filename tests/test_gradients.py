"""∂k_xx(t)/∂ε and ∂k_xx(t)/∂ν through simulate: reverse, forward, finite differences, analytic."""

from typing import Any

import diffrax
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


@pytest.mark.parametrize(
    "solver",
    [*nhsde.SOLVERS, diffrax.Heun(scan_kind="lax"), diffrax.ShARK()],
    ids=lambda s: s if isinstance(s, str) else repr(s),
)
def test_every_solver_differentiates_in_reverse_mode_as_in_forward_mode(solver):
    """``jax.grad`` of K_xx(t1) through fixed steps equals ``jax.jacfwd`` for every alias of ``nhsde.SOLVERS`` and
    for diffrax's explicit and stochastic Runge–Kutta objects whatever their ``scan_kind`` (Heun's ``'lax'`` is a while
    loop, which has no reverse mode; ShARK's default ``'checkpointed'`` has no forward mode): their stages run as
    scans of the stage count."""
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)

    def k_xx_end(eps):
        system = scene.build().replace_params(eps=eps)
        ens = nhsde.simulate(
            system,
            scene.initial_state().astype(jnp.float64),
            KEY,
            n_paths=64,
            t1=0.25,
            dt=0.0625,
            solver=solver,
            save=nhsde.Save(names=("x",), n=2),
        )
        return ens.cov[-1, 0, 0]

    eps = jnp.float64(1.0)
    rev, fwd = jax.grad(k_xx_end)(eps), jax.jacfwd(k_xx_end)(eps)
    assert np.isfinite(rev) and rev != 0.0
    np.testing.assert_allclose(rev, fwd, rtol=1e-12)


def test_reverse_mode_through_excluded_paths_that_overflow_is_finite_and_equals_forward_mode():
    """``dx = a x² dt + 0.1 dW``, half the paths from x = 0.1 and half from x = 10, ``on_failure='exclude'``: the
    latter overflow (≈ 10^{2^k} after k steps of 0.1), and ``∂x₁/∂a = h x²`` overflows in their last finite step,
    whose value is discarded.  Reverse mode gave nan (0·∞ in that step's cotangent); now it equals forward mode, and
    the derivative is that of the surviving half alone."""

    def system(a):
        return nhsde.StochasticSystem(
            drift_fn=lambda t, y, p: p * y**2,
            diffusion_fn=lambda t, y, p: 0.1 * jnp.ones((1, 1), y.dtype),
            params=a,
            layout=nhsde.StateLayout(("x",), ("independent_coordinate",)),
            noise_dim=1,
            additive_noise=True,
        )

    n = 128
    y0 = jnp.concatenate([jnp.full((n // 2, 1), 0.1), jnp.full((n // 2, 1), 10.0)])
    run: dict[str, Any] = dict(n_paths=n, t1=2.0, dt=0.1, save=nhsde.Save(n=2), on_failure="exclude")

    def statistic(a, start=y0, n_paths=n):
        ens = nhsde.simulate(system(a), start, KEY, **(run | dict(n_paths=n_paths)))
        return ens.mean[-1, 0] + ens.cov[-1, 0, 0]

    a = jnp.float64(1.0)
    assert int(nhsde.simulate(system(a), y0, KEY, **run).n_failed) == n // 2
    rev, fwd = jax.grad(statistic)(a), jax.jacfwd(statistic)(a)
    assert np.isfinite(rev), rev
    np.testing.assert_allclose(rev, fwd, rtol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.grad(statistic))(a), fwd, rtol=1e-12)
    # the surviving paths alone (the same noise: paths 0 … 63 of the key), no failure at all
    alone = jax.grad(lambda a: statistic(a, y0[: n // 2], n // 2))(a)
    np.testing.assert_allclose(rev, alone, rtol=1e-12)
