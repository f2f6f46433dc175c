"""The martingale (regression) control variate: unbiased for the discretisation whatever its basis, against theory.

Exact values for the ball on the vibrating plane (linear drift ``A``, additive noise ``b``) are those of the scheme
itself: Euler maps ``X ↦ (I + Ah)X + bΔW``, Platen's weak scheme ``X ↦ (I + Ah + ½A²h²)X + (I + ½Ah)bΔŴ``
(KP (15.1.4); three-point ``ΔŴ`` with ``E ΔŴΔŴᵀ = h I``), so the discrete means and covariances follow
``m ↦ Pm``, ``K ↦ PKPᵀ + h QQᵀ``.  The control removes most of the variance, so the comparison is with the
scheme's values (the continuous closed form, S0 (3.1), differs by the scheme's bias).  Tolerances: 4 standard
errors.
"""

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh
from nhsde.statistics import (
    Covariance,
    Mean,
    Multilevel,
    martingale_control_variate,
    multilevel_monte_carlo,
    to_accuracy,
)

BALL = BallOnVibratingPlane(eps=1.0, nu=1.0)
Y0 = jnp.array([0.0, 0.0, 0.5, -0.25])
H, T1 = 0.125, 1.0
NAMES = ("x", "u_x")


def discrete_moments(eps, nu, solver, h=H):
    """The scheme's exact mean and covariance of ``(x, u_x)`` at ``T1`` with step ``h`` (module)."""
    system = BALL.build().replace_params(eps=eps, nu=nu)
    a = system.linear_drift(system.params)
    b = system.diffusion(0.0, Y0, system.params)
    eye = jnp.eye(4, dtype=a.dtype)
    if solver == "euler":
        p, q = eye + a * h, b
    else:
        p, q = eye + a * h + 0.5 * (a @ a) * h**2, (eye + 0.5 * a * h) @ b
    m, k = Y0, jnp.zeros((4, 4), a.dtype)
    for _ in range(round(T1 / h)):
        m, k = p @ m, p @ k @ p.T + h * q @ q.T
    idx = jnp.array([0, 2])
    return m[idx], k[idx][:, idx]


def test_the_ball_has_the_linear_drift_the_exact_values_assume():
    system = BALL.build()
    y = jnp.array([0.3, -0.2, 0.7, 0.1])
    a = system.linear_drift(system.params)
    np.testing.assert_allclose(np.asarray(system.drift(0.0, y, system.params)), np.asarray(a @ y), atol=1e-15)


@pytest.fixture(scope="module")
def weak_ball():
    """Platen's weak scheme, three-point increments, with derivatives in ε and ν."""
    return martingale_control_variate(
        BALL.build(),
        Y0,
        jax.random.key(0),
        Covariance("x", "x"),
        n_paths=4096,
        n_pilot=2048,
        t1=T1,
        dt=H,
        solver="weak2",
        save=nhsde.Save(names=NAMES, n=2),
        wrt=("eps", "nu"),
    )


def test_the_ball_agrees_with_the_schemes_exact_moments_and_beats_plain_monte_carlo(weak_ball):
    """Means and covariances of (x, u_x) at t1 within 4 SE of the weak scheme's exact values; on the same paths the
    variance of K_xx is ≥ 100× below plain Monte Carlo's (measured 500–800×) and that of E x ≥ 1000× below."""
    est = weak_ball
    mean, cov = discrete_moments(1.0, 1.0, "weak2")
    z_mean = (np.asarray(est.mean[-1]) - np.asarray(mean)) / np.asarray(est.mean_se[-1])
    z_cov = (np.asarray(est.cov[-1]) - np.asarray(cov)) / np.asarray(est.cov_se[-1])
    assert np.all(np.abs(z_mean) <= 4) and np.all(np.abs(z_cov) <= 4), (z_mean, z_cov)
    value, se = est.value()
    plain_value, plain_se = est.plain.value()
    assert (plain_se / se) ** 2 >= 100, (plain_se, se)
    np.testing.assert_allclose(float(est.variance_reduction.cov[-1, 0, 0]), float((plain_se / se) ** 2), rtol=0.05)
    assert float(est.variance_reduction.mean[-1, 0]) >= 1000, est.variance_reduction.mean
    assert abs(float(plain_value - cov[0, 0])) <= 4 * float(plain_se)


def test_derivatives_in_eps_and_nu_agree_with_the_schemes_exact_derivatives(weak_ball):
    """∂/∂(ε, ν) of E x and K_xx at t1 (β fixed) within 4 SE of jax.jacfwd of the scheme's exact moments."""
    d_mean, d_cov = jax.jacfwd(lambda p: discrete_moments(p[0], p[1], "weak2"))(jnp.array([1.0, 1.0]))
    d = weak_ball.derivatives
    assert d is not None and d.wrt == ("eps", "nu")
    z_mean = (np.asarray(d.d_mean[:, -1, 0]) - np.asarray(d_mean[0])) / np.asarray(d.d_mean_se[:, -1, 0])
    z_cov = (np.asarray(d.d_cov[:, -1, 0, 0]) - np.asarray(d_cov[0, 0])) / np.asarray(d.d_cov_se[:, -1, 0, 0])
    assert np.all(np.abs(z_mean) <= 4) and np.all(np.abs(z_cov) <= 4), (z_mean, z_cov)
    derivative, se = weak_ball.derivative()
    assert np.all(np.asarray(se) < 0.05 * np.abs(np.asarray(derivative))), (derivative, se)


def _poor(t, x, params):
    """A basis unrelated to the ball's value function: oscillating in the state and time, one row per channel."""
    return jnp.stack([jnp.sin(7.0 * x[0] + 3.0 * t) * jnp.ones(2, x.dtype), jnp.cos(5.0 * x[2] * x[3]) * x[1:3]])


def test_a_poor_basis_fitted_on_few_paths_costs_variance_not_bias():
    """Euler, a deliberately poor basis whose coefficients are fitted on 16 pilot paths: the estimates stay within
    4 SE of Euler's exact moments on 2¹⁴ paths."""
    est = martingale_control_variate(
        BALL.build(),
        Y0,
        jax.random.key(5),
        Mean("x"),
        n_paths=2**14,
        n_pilot=16,
        t1=T1,
        dt=H,
        basis=_poor,
        time_degree=1,
        save=nhsde.Save(names=NAMES, n=2),
    )
    mean, cov = discrete_moments(1.0, 1.0, "euler")
    z_mean = (np.asarray(est.mean[-1]) - np.asarray(mean)) / np.asarray(est.mean_se[-1])
    z_cov = (np.asarray(est.cov[-1]) - np.asarray(cov)) / np.asarray(est.cov_se[-1])
    assert np.all(np.abs(z_mean) <= 4) and np.all(np.abs(z_cov) <= 4), (z_mean, z_cov)


def _r2(t, y, p):
    """The sleigh's squared distance from the start, x² + y²."""
    return y[0] ** 2 + y[1] ** 2


def test_the_sleighs_mean_square_displacement_agrees_with_plain_monte_carlo_at_far_less_variance():
    """E[x² + y²](2) of the Chaplygin sleigh (no closed form: the moment equations do not close): the controlled
    estimate on 4096 paths agrees with plain Monte Carlo of the same scheme on 2¹⁵ independent paths within 4
    combined SE, and its variance at equal paths is ≥ 50× lower (measured ≈ 370×, weak scheme, h = 1/8)."""
    scene = ChaplyginSleigh()
    system = scene.build()
    system = dataclasses.replace(system, observables=system.observables + (("r2", _r2),))
    args: dict[str, Any] = dict(t1=2.0, dt=0.125, solver="weak2")
    est = martingale_control_variate(system, scene.initial_state(), jax.random.key(1), Mean("r2"), n_paths=4096, **args)
    plain = nhsde.simulate(
        system, scene.initial_state(), jax.random.key(2), n_paths=2**15, save=nhsde.Save(names=("r2",), n=2), **args
    )
    value, se = est.value()
    ref, ref_se = plain.mean[-1, 0], plain.mean_se[-1, 0]
    assert abs(float(value - ref)) <= 4 * float(jnp.hypot(se, ref_se)), (value, se, ref, ref_se)
    reduction = float(est.variance_reduction.mean[-1, 0])
    assert reduction >= 50, reduction


def _x2(t, y, p):
    """The ball's squared displacement x² (no mean with variance zero: E x alone is deterministic here)."""
    return y[0] ** 2


GAUSS = nhsde.PlatenWeak2(increments="gaussian")
BALL_X2 = dataclasses.replace(BALL.build(), observables=BALL.build().observables + (("x2", _x2),))


def _exact_x2(eps, nu, h):
    """E x² = K_xx + (E x)² of the weak scheme at step ``h`` (Gaussian increments: the same first two moments)."""
    mean, cov = discrete_moments(eps, nu, "weak2", h)
    return cov[0, 0] + mean[0] ** 2


def test_multilevel_with_the_martingale_control_on_every_level_is_unbiased_and_cuts_the_level_variances():
    """Multilevel Monte Carlo (weak order 2, h₀ = 1/4, three levels) with ``control='martingale'``: E x²(1) within
    4 SE of the scheme's exact value at the finest step (the control has mean zero on every level, so the levels
    telescope to the finest level's mean), its derivatives in ε and ν within 4 SE of ``jax.jacfwd`` of that value,
    and on the same key the level-0 variance ≥ 20× below the plain multilevel's (measured ≈ 400×); the fit's pilot
    paths are counted in the cost."""
    args: dict[str, Any] = dict(statistic=Mean("x2"), n_paths=(2048, 512, 256), t1=T1, dt=0.25, solver=GAUSS)
    est = multilevel_monte_carlo(BALL_X2, Y0, jax.random.key(7), control="martingale", wrt=("eps", "nu"), **args)
    plain = multilevel_monte_carlo(BALL_X2, Y0, jax.random.key(7), **args)
    exact = _exact_x2(1.0, 1.0, 0.0625)
    value, se = est.value()
    assert abs(float(value - exact)) <= 4 * float(se), (value, se, exact)
    d_exact = jax.jacfwd(lambda q: _exact_x2(q[0], q[1], 0.0625))(jnp.array([1.0, 1.0]))
    derivative, d_se = est.derivative()
    z = (np.asarray(derivative) - np.asarray(d_exact)) / np.asarray(d_se)
    assert np.all(np.abs(z) <= 4), (derivative, d_se, d_exact)
    reduction = float(plain.level_variances[0] / est.level_variances[0])
    assert reduction >= 20, (plain.level_variances, est.level_variances)
    assert est.cost.path_steps > 2 * plain.cost.path_steps  # the control's components counted, and its pilot
    assert est.coefficient is not None and est.coefficient.mean.shape[:2] == (2, 1)


def test_to_accuracy_prices_and_runs_multilevel_with_the_martingale_control():
    """``Multilevel(..., control='martingale')`` in ``to_accuracy``: priced from its own controlled pilot (κ measured),
    chosen when given alone, and within 4× the requested RMSE of the scheme's exact value at the finest step
    it ran (bias bounded below the target)."""
    res = to_accuracy(
        BALL_X2,
        Y0,
        jax.random.key(8),
        statistic=Mean("x2"),
        t1=T1,
        rmse=2e-3,
        dt=0.25,
        estimators=[Multilevel(GAUSS, control="martingale")],
    )
    assert res.choice == "multilevel, weak2-gaussian, martingale control", res.choice
    (chosen,) = [a for a in res.alternatives if a.applies]
    # κ measured: a ratio of seconds per path-step (the machine's load sets its size, so it is not bounded here)
    assert 0 < chosen.kappa < math.inf and f"κ = {chosen.kappa:.3g}" in chosen.note
    finest = 0.25 / 2 ** (len(res.estimate.n_paths_per_level) - 1)
    value, se = res.value()
    assert abs(float(value) - float(_exact_x2(1.0, 1.0, finest))) <= 4 * 2e-3, (value, se, finest)
    with pytest.raises(ValueError, match="control='mean'; allowed: False, True"):
        Multilevel(GAUSS, control="mean")


def test_bad_input_raises_naming_the_argument():
    system, args = BALL.build(), dict(n_paths=64, t1=T1, dt=H)
    key, stat = jax.random.key(0), Mean("x")
    with pytest.raises(ValueError, match="solver='heun2'; allowed: 'euler', 'weak2'"):
        martingale_control_variate(system, Y0, key, stat, solver="heun2", **args)
    with pytest.raises(ValueError, match="basis='quartic'; allowed"):
        martingale_control_variate(system, Y0, key, stat, basis="quartic", **args)
    with pytest.raises(ValueError, match=r"basis=.* returns shape \(3,\)"):
        martingale_control_variate(system, Y0, key, stat, basis=lambda t, x, p: x[:3], **args)
    with pytest.raises(ValueError, match="n_pilot=8; the fit of 27 coefficients"):
        martingale_control_variate(system, Y0, key, stat, n_pilot=8, **args)
    with pytest.raises(ValueError, match="time_degree=7; allowed: 0 … 4"):
        martingale_control_variate(system, Y0, key, stat, time_degree=7, **args)
    with pytest.raises(ValueError, match="statistic='x'"):
        martingale_control_variate(system, Y0, key, "x", **args)
    with pytest.raises(ValueError, match="names \\['u_y'\\], which are not saved"):
        martingale_control_variate(system, Y0, key, Mean("u_y"), save=nhsde.Save(names=("x",)), **args)
    with pytest.raises(ValueError, match="n_paths=2; must be ≥ 4"):
        martingale_control_variate(system, Y0, key, stat, n_paths=2, t1=T1, dt=H)
    with pytest.raises(ValueError, match="control='martingal'; allowed: 'mean' .* or 'martingale'"):
        multilevel_monte_carlo(system, Y0, key, statistic=stat, n_paths=(64,), control="martingal", t1=T1, dt=H)
    with pytest.raises(ValueError, match="solver='heun2'; allowed: 'euler', 'weak2'"):
        multilevel_monte_carlo(
            system, Y0, key, statistic=stat, n_paths=(64,), solver="heun2", control="martingale", t1=T1, dt=H
        )
