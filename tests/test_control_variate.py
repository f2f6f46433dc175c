"""Control variates from the linearised system (nhsde.statistics.control_variate).

Exact values: the ball's closed forms, S0 (3.1) (``ball_covariances``), and the
sleigh's energy, ``dE[H]/dt = −4εE[H] + ν`` (Itô), so
``E[H](t) = H0 e^{−4εt} + ν(1 − e^{−4εt})/(4ε)``.  Tolerances come from the
Monte-Carlo standard errors at the stated confidence, or from rounding where the
estimator is exact.
"""

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.noise import CompoundPoisson, NormalJumps, driver_intensity
from nhsde.scenes import BallOnVibratingPlane, BodyOnVibratingPlane, ChaplyginSleigh, ball_covariances
from nhsde.statistics import control_variate

DELTA = 1 / 1.4
BALL = BallOnVibratingPlane(eps=1.0, nu=1.0)
Y0 = jnp.zeros(4)
BALL_ARGS: dict[str, Any] = dict(n_paths=256, t1=1.0, dt=1 / 16, save=nhsde.Save(names=("x", "u_x"), n=3))


def ball_exact(ts, eps=1.0, nu=1.0):
    """``(n, 2, 2)`` covariances of ``(x, u_x)`` at ``ts``, S0 (3.1)."""
    k_xx, k_xu, k_uu = (np.asarray(k) for k in ball_covariances(jnp.asarray(ts, jnp.float64), eps, nu, DELTA))
    return np.stack([np.stack([k_xx, k_xu], -1), np.stack([k_xu, k_uu], -1)], -2)


@pytest.fixture(scope="module")
def ball_estimate():
    return control_variate(BALL.build(), Y0, jax.random.key(0), **BALL_ARGS)


def test_linear_system_is_its_own_control_and_the_estimate_is_exact(ball_estimate):
    """For a linear system ``a(p) + ∂a(p)(C − p) = a(C)``: the control is the system, ``Z ≡ C`` path by path
    (same increments, same scheme), β = 1 and ``Ŷ − (Ĉ − E C) = E C``: the exact continuous covariances up to
    rounding, although Euler at h = 1/16 is biased (bias(Y) − β·bias(C) = 0)."""
    est = ball_estimate
    exact = ball_exact(np.asarray(est.ts))
    np.testing.assert_allclose(np.asarray(est.cov), exact, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(np.asarray(est.control.cov), exact, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(np.asarray(est.mean), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(est.coefficient.cov[1:]), 1.0, rtol=1e-8)
    # the residual Y − C is rounding: its SE, from Var Y − 2β Cov + β² Var C, is at most √(rounding) of the plain one
    assert np.all(np.asarray(est.cov_se[1:]) <= 1e-6 * np.asarray(est.plain.cov_se[1:]))
    assert np.all(np.asarray(est.variance_reduction.cov[1:]) > 1e12)
    assert est.cost.path_steps == 2 * est.plain.cost.path_steps == 2 * 256 * 16


def test_reference_linearisation_of_a_linear_system_is_exact():
    """Linearised about any fixed state a linear system is itself: the same exact covariances."""
    ref = jnp.array([0.3, -0.2, 1.0, 0.5])
    est = control_variate(BALL.build(), Y0, jax.random.key(0), linearisation=ref, **BALL_ARGS)
    np.testing.assert_allclose(np.asarray(est.cov), ball_exact(np.asarray(est.ts)), rtol=1e-10, atol=1e-15)


def test_the_estimate_is_continuous_as_the_noise_vanishes():
    """At ν = 0 every path is the noiseless Euler motion (exact binary fractions from (0, 0, 1, 1) at h = 1/16), the
    control has no variance and β is its limit 1: the means are the noiseless motion ``x = u₀(1 − e^{−2εt})/(2ε)``,
    ``u_x = u₀ e^{−2εt}`` (not Euler's, 7 % off), as at ν = 10⁻¹² and 10⁻⁸ (exact for the linear ball, up to
    rounding)."""
    y0 = jnp.array([0.0, 0.0, 1.0, 1.0])
    runs = [
        control_variate(BALL.build().replace_params(nu=nu), y0, jax.random.key(0), **BALL_ARGS)
        for nu in (0.0, 1e-12, 1e-8)
    ]
    ts = np.asarray(runs[0].ts)
    exact = np.stack([(1 - np.exp(-2 * ts)) / 2, np.exp(-2 * ts)], -1)
    for est in runs:
        np.testing.assert_allclose(np.asarray(est.mean), exact, rtol=1e-10)
        np.testing.assert_allclose(np.asarray(est.coefficient.mean), 1.0, rtol=1e-6)
    assert abs(float(runs[0].plain.mean[-1, 1]) / exact[-1, 1] - 1) > 0.05  # Euler's bias, removed
    np.testing.assert_array_equal(np.asarray(runs[0].cov), 0.0)


@pytest.mark.slow
@pytest.mark.parametrize(
    "solver", ["milstein", "heun", "heun2", "sra1", "exponential", "weak2", nhsde.PlatenWeak2("gaussian")]
)
def test_every_scheme_keeps_the_linear_system_exact(solver):
    """Every scheme steps the control like the system (same increments, drift ``a(C)``): exact on the ball."""
    args: dict[str, Any] = dict(BALL_ARGS, n_paths=64, dt=1 / 8)
    est = control_variate(BALL.build(), Y0, jax.random.key(5), solver=solver, **args)
    np.testing.assert_allclose(np.asarray(est.cov), ball_exact(np.asarray(est.ts)), rtol=1e-10, atol=1e-15)


def test_gradient_of_the_cv_estimate_is_the_exact_derivative():
    """jacfwd in (ε, ν) of the CV estimate of K_xx(1) equals ∂ of the closed form (jax.jacfwd of
    ``ball_covariances``) up to rounding.  Why exact: β is held fixed (stop_gradient), so
    ``∂Ŷ_cv = ∂Ŷ − β(∂Ĉ − ∂E C)``; on the linear ball the tangent paths also coincide, ``∂Y ≡ ∂C``, and β = 1,
    leaving ``∂E C``, the derivative of the exact moment equations."""
    system = BALL.build()

    def k_xx_cv(theta):
        s = system.replace_params(eps=theta[0], nu=theta[1])
        return control_variate(s, Y0, jax.random.key(3), **BALL_ARGS).cov[-1, 0, 0]

    theta = jnp.array([0.8, 1.3])
    grad = jax.jacfwd(k_xx_cv)(theta)
    exact = jax.jacfwd(lambda th: ball_covariances(jnp.float64(1.0), th[0], th[1], DELTA)[0])(theta)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(exact), rtol=1e-9)
    # wrt=: the same derivatives, with standard errors of the residual tangents ∂Y − β∂C, rounding here
    est = control_variate(system.replace_params(eps=0.8, nu=1.3), Y0, jax.random.key(3), wrt=("eps", "nu"), **BALL_ARGS)
    d = est.derivatives
    assert d is not None and d.wrt == ("eps", "nu")
    np.testing.assert_allclose(np.asarray(d.d_cov[:, -1, 0, 0]), np.asarray(exact), rtol=1e-9)
    assert np.all(np.asarray(d.d_cov_se) <= 1e-9) and np.all(np.asarray(d.d_mean_se) <= 1e-9)


@pytest.mark.slow
def test_jump_driver_enters_through_its_intensity():
    """Centred compound Poisson jumps on the ball: the moment equations carry the intensity λE[c²] (S0 (1.4)),
    the same jumps drive both solves, and the linear system stays exact."""
    jumps = CompoundPoisson(law=NormalJumps(std=0.5), intensity=2.0)
    system = dataclasses.replace(BALL.build(), noise=jumps)
    est = control_variate(system, Y0, jax.random.key(2), n_paths=128, t1=1.0, dt=1 / 8, save=nhsde.Save(("x",), n=2))
    nu = float(driver_intensity(jumps, 2, jnp.float64)[0])
    exact = ball_exact(np.asarray(est.ts), nu=nu)[:, :1, :1]
    np.testing.assert_allclose(np.asarray(est.cov), exact, rtol=1e-10, atol=1e-15)


# ----------------------------------------------------------------------------- a nonlinear system: the sleigh

SLEIGH_EPS, SLEIGH_T1 = 0.5, 2.0
SLEIGH_Y0 = jnp.array([1.0, 0.5])  # v, ω; H0 = ½(m v² + J ω²) with J = I + m a² = 2
SLEIGH_ARGS: dict[str, Any] = dict(
    n_paths=4096, t1=SLEIGH_T1, dt=1 / 16, solver="sra1", save=nhsde.Save(names=("energy",), n=2)
)


def sleigh_energy(nu):
    decay = math.exp(-4 * SLEIGH_EPS * SLEIGH_T1)
    return 0.75 * decay + nu * (1 - decay) / (4 * SLEIGH_EPS)


def test_sleigh_energy_agrees_and_the_variance_falls_like_the_noise():
    """E[H](t1) of the nonlinear sleigh: the CV estimate is within 4 SE of the closed form (99.99 %; SRA1 at
    h = 1/16 is weak order 2: the CV estimate's bias, measured with 2^18 paths, is (−1.3 ± 2.1)e-4, below a
    quarter of the SE ≈ 1.7e-3 of 4096 paths), and the variance reduction grows like
    1/ν.  Small-noise expansion about the noiseless motion: ``Z = z̄ + √ν Z₁ + ν Z₂ + …`` and the control is
    ``C = z̄ + √ν Z₁``, so ``H(Z) − H(C) = O(ν)`` while ``H(Z) − E H = O(√ν)`` (the sleigh still moves at t1,
    ∇H(z̄) ≠ 0): ``Var(Y − βC)/Var Y = O(ν)``.  Quartering ν should multiply the reduction by → 4; the test asks
    for more than 2 (the margin covers the O(ν) corrections and the ≈ 3 % sampling error of each factor), and
    for a reduction > 4 at ν = 1."""
    system = ChaplyginSleigh(eps=SLEIGH_EPS, nu=1.0, drift=False).build()
    reductions = []
    for nu in (1.0, 0.25):
        est = control_variate(system.replace_params(nu=nu), SLEIGH_Y0, jax.random.key(1), **SLEIGH_ARGS)
        z = (float(est.mean[-1, 0]) - sleigh_energy(nu)) / float(est.mean_se[-1, 0])
        assert abs(z) <= 4, (nu, z)
        reductions.append(float(est.variance_reduction.mean[-1, 0]))
        se_ratio = float(est.plain.mean_se[-1, 0] / est.mean_se[-1, 0])
        np.testing.assert_allclose(se_ratio**2, reductions[-1], rtol=1e-8)
    assert reductions[0] > 4, reductions
    assert reductions[1] > 2 * reductions[0], reductions


def test_derivatives_are_jacfwd_of_the_estimate_on_the_sleigh():
    """``wrt=``: the derivatives (β fixed) are ``jax.jacfwd`` of ``.mean`` and ``.cov`` in (ε, ν) up to rounding,
    on a nonlinear system with an observable and a state component saved at three times (β ≠ 1, varying)."""
    system = ChaplyginSleigh(eps=SLEIGH_EPS, nu=1.0, drift=False).build()
    args: dict[str, Any] = dict(n_paths=32, t1=1.0, dt=1 / 8, save=nhsde.Save(names=("energy", "v"), n=3))

    def moments(theta):
        est = control_variate(system.replace_params(eps=theta[0], nu=theta[1]), SLEIGH_Y0, jax.random.key(4), **args)
        return est.mean, est.cov

    d_mean, d_cov = (jnp.moveaxis(j, -1, 0) for j in jax.jacfwd(moments)(jnp.array([SLEIGH_EPS, 1.0])))
    d = control_variate(system, SLEIGH_Y0, jax.random.key(4), wrt=("eps", "nu"), **args).derivatives
    assert d is not None
    for got, want in ((d.d_mean, d_mean), (d.d_cov, d_cov)):
        np.testing.assert_allclose(
            np.asarray(got), np.asarray(want), rtol=1e-9, atol=1e-12 * float(jnp.abs(want).max())
        )
    assert np.all(np.asarray(d.d_mean_se[:, 1:]) > 0) and np.all(np.asarray(d.d_cov_se[:, 1:]) > 0)


def test_derivative_of_the_sleigh_energy_agrees_with_plain_sensitivities():
    """∂E[H](t1)/∂(ε, ν) by the control variate and by an independent plain pathwise estimate
    (``moment_sensitivities``, another key) agree within 4 combined SEs (99.99 %), and both are within 4 of their
    own SEs of the closed form's derivative (SRA1 at h = 1/16: bias well below the SEs, as for the value).  The
    control removes most of the tangents' variance too: the CV's SEs are below half the plain ones (measured
    3.5× below in ε, 3.2× in ν)."""
    system = ChaplyginSleigh(eps=SLEIGH_EPS, nu=1.0, drift=False).build()
    wrt = ("eps", "nu")
    d = control_variate(system, SLEIGH_Y0, jax.random.key(1), wrt=wrt, **SLEIGH_ARGS).derivatives
    plain = nhsde.statistics.moment_sensitivities(system, SLEIGH_Y0, jax.random.key(2), wrt=wrt, **SLEIGH_ARGS)
    assert d is not None
    cv, cv_se = np.asarray(d.d_mean[:, -1, 0]), np.asarray(d.d_mean_se[:, -1, 0])
    pl, pl_se = np.asarray(plain.d_mean[:, -1, 0]), np.asarray(plain.d_mean_se[:, -1, 0])
    assert np.all(np.abs(cv - pl) <= 4 * np.hypot(cv_se, pl_se)), (cv, cv_se, pl, pl_se)
    assert np.all(cv_se < 0.5 * pl_se), (cv_se, pl_se)

    def energy(theta):  # E[H](t1) = H0 e^{−4εt} + ν(1 − e^{−4εt})/(4ε)
        decay = jnp.exp(-4 * theta[0] * SLEIGH_T1)
        return 0.75 * decay + theta[1] * (1 - decay) / (4 * theta[0])

    exact = np.asarray(jax.grad(energy)(jnp.array([SLEIGH_EPS, 1.0])))
    assert np.all(np.abs(cv - exact) <= 4 * cv_se), (cv, cv_se, exact)
    assert np.all(np.abs(pl - exact) <= 4 * pl_se), (pl, pl_se, exact)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(n_paths=2), "n_paths=2"),
        (dict(n_paths=10.5), "n_paths"),
        (dict(save=nhsde.Save(names=("z",))), "unknown name 'z'"),
        (dict(linearisation="median"), "linearisation='median'"),
        (dict(linearisation=jnp.zeros(3)), "linearisation has shape"),
        (dict(dt=None), "needs a step"),
        (dict(dt=None, steps=nhsde.AdaptiveSteps(dt=0.1)), "steps="),
        (dict(dt=0.3), "dt"),
        (dict(solver="rk4"), "solver='rk4'"),
        (dict(t1=0.0), "t1=0.0"),
        (dict(wrt=("delta_x",)), "wrt="),
        (dict(wrt=("eps", "eps")), "wrt="),
    ],
)
def test_bad_input_names_the_argument(kwargs, match):
    args: dict[str, Any] = dict(n_paths=64, t1=1.0, dt=0.25) | kwargs
    with pytest.raises((ValueError, TypeError), match=match):
        control_variate(BALL.build(), Y0, jax.random.key(0), **args)


def test_bad_systems_and_solvers_are_refused():
    with pytest.raises(TypeError, match="system="):
        control_variate(BALL, Y0, jax.random.key(0), n_paths=64, t1=1.0, dt=0.25)
    body = BodyOnVibratingPlane().build()
    with pytest.raises(ValueError, match="solver='sra1'"):
        control_variate(
            body, BodyOnVibratingPlane().initial_state(), jax.random.key(0), n_paths=64, t1=1.0, dt=0.25, solver="sra1"
        )
    jumps = dataclasses.replace(
        BallOnVibratingPlane(angular_velocity=True).build(), noise=CompoundPoisson(law=NormalJumps(), intensity=1.0)
    )
    with pytest.raises(ValueError, match="save state components only"):
        control_variate(jumps, Y0, jax.random.key(0), n_paths=64, t1=1.0, dt=0.25, save=nhsde.Save(("omega_x",)))
    with pytest.raises(ValueError, match="solver='heun'"):
        control_variate(jumps, Y0, jax.random.key(0), n_paths=64, t1=1.0, dt=0.25, solver="heun")
