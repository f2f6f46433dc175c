"""The ball on the vibrating plane, S0 (3.1): closed forms and the ensemble against them."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ball_covariances
from nhsde.statistics import drift_statistics, effective_diffusion, stationary_moments


def lyapunov_covariance(t, eps, nu, delta):
    """Independent route: integrate dK/dt = AK + KAᵀ + GGᵀ (one axis, state (x, u)) to 1e-13."""
    a = jnp.array([[0.0, 1.0], [0.0, -2.0 * eps]])
    q = jnp.array([[0.0, 0.0], [0.0, nu * delta**2]])
    sol = dfx.diffeqsolve(
        dfx.ODETerm(lambda t, k, args: a @ k + k @ a.T + q),
        dfx.Dopri8(),
        0.0,
        t,
        1e-3,
        jnp.zeros((2, 2)),
        stepsize_controller=dfx.PIDController(rtol=1e-13, atol=1e-15),
        max_steps=100_000,
    )
    return sol.ys[-1]


@pytest.mark.parametrize("eps", [0.3, 1.0, 2.5])
def test_closed_form_matches_lyapunov_equation(eps):
    nu, delta = 1.7, 5 / 7
    for t in [0.01, 0.3, 1.0, 4.0]:
        k = lyapunov_covariance(t, eps, nu, delta)
        k_xx, k_xu, k_uu = ball_covariances(jnp.float64(t), eps, nu, delta)
        np.testing.assert_allclose([k_xx, k_xu, k_uu], [k[0, 0], k[0, 1], k[1, 1]], rtol=1e-10, atol=1e-14)


def test_closed_form_limits_are_s0_asymptotics():
    eps, nu, delta = 0.8, 2.0, 5 / 7
    g = nu * delta**2
    t = jnp.float64(60.0)
    k_xx, k_xu, k_uu = ball_covariances(t, eps, nu, delta)
    np.testing.assert_allclose(k_uu, g / (4 * eps), rtol=1e-12)
    np.testing.assert_allclose(k_xu, g / (8 * eps**2), rtol=1e-12)
    # k_xx = g t/(4ε²) − 3g/(16 ε³) + O(e^{−2εt})
    np.testing.assert_allclose(k_xx, g * t / (4 * eps**2) - 3 * g / (16 * eps**3), rtol=1e-12)
    t = jnp.float64(1e-4)
    k_xx, k_xu, k_uu = ball_covariances(t, eps, nu, delta)
    np.testing.assert_allclose(k_uu, g * t, rtol=1e-3)
    assert k_xx < 1e-10 and k_xu < 1e-7


def test_closed_form_at_zero_friction_is_brownian_velocity():
    nu, delta, t = 1.3, 5 / 7, jnp.float64(2.0)
    g = nu * delta**2
    for eps in [0.0, 1e-9]:
        k_xx, k_xu, k_uu = ball_covariances(t, jnp.float64(eps), nu, delta)
        np.testing.assert_allclose([k_xx, k_xu, k_uu], [g * t**3 / 3, g * t**2 / 2, g * t], rtol=1e-8)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_ensemble_covariances_match_closed_form(dtype):
    eps, nu = 1.0, 2.0
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    ens = nhsde.simulate(
        scene.build(),
        scene.initial_state().astype(dtype),
        jax.random.key(1),
        n_paths=8192,
        t1=3.0,
        dt=0.002,
        save=nhsde.Save(n=7),
    )
    assert ens.mean.dtype == dtype
    k_xx, k_xu, k_uu = ball_covariances(ens.ts.astype(jnp.float64), eps, nu, scene.params.delta.astype(jnp.float64))
    # Euler–Maruyama's bias here is O(ε dt) = 0.2 % of each covariance, far below
    # the Monte-Carlo error (√(2/8192) ≈ 1.6 %).
    for (i, j), exact in [((0, 0), k_xx), ((0, 2), k_xu), ((2, 2), k_uu), ((1, 1), k_xx), ((3, 3), k_uu)]:
        err = np.abs(np.asarray(ens.cov[:, i, j], np.float64) - np.asarray(exact))
        assert np.all(err[1:] <= 4 * np.asarray(ens.cov_se[1:, i, j])), (i, j, err, ens.cov_se[:, i, j])
    assert float(jnp.max(jnp.abs(ens.cov[0]))) == 0.0
    # independent axes: cross-covariances vanish within error
    assert np.all(np.abs(ens.cov[1:, 0, 1]) <= 4 * ens.cov_se[1:, 0, 1])
    # no drift of the mean from rest
    assert np.all(np.abs(ens.mean[1:]) <= 4 * ens.mean_se[1:])


def test_effective_diffusion_and_stationary_moments():
    eps, nu = 2.0, 1.0
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    ens = nhsde.simulate(
        scene.build(),
        scene.initial_state().astype(jnp.float64),
        jax.random.key(2),
        n_paths=8192,
        t1=8.0,
        dt=0.004,
        save=nhsde.Save(n=9),
        solver="sra1",
    )
    g = nu * float(scene.params.delta) ** 2
    # over t ∈ [4, 8], K_xx grows at rate g/(4ε²) up to e^{−2εt} ≈ 1e-7
    d = effective_diffusion(ens, t_from=4.0)
    stats = drift_statistics(ens)
    se = float(jnp.max(stats.fluctuation_se[-1, 0, 0])) / 4.0  # slope error ≲ K's error over the span
    np.testing.assert_allclose(d[0, 0], g / (8 * eps**2), atol=4 * se)
    stat = stationary_moments(ens, t_from=4.0)
    assert stat.names == ("u_x", "u_y")
    np.testing.assert_allclose(stat.cov[0, 0], g / (4 * eps), atol=4 * float(ens.cov_se[-1, 2, 2]))
