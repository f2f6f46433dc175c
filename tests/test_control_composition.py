"""The linearised system as a control variate inside multilevel Monte Carlo (``multilevel_monte_carlo(control=…)``,
``Multilevel(control=True)``) and inside (multilevel) randomised quasi-Monte Carlo
(``multilevel_quasi_monte_carlo(control=…)``, ``QuasiMonteCarlo(control=True)``).

Exact values: the ball's closed forms, S0 (3.1) (``ball_covariances``), and the sleigh's energy
``E[H](t) = H0 e^{−4εt} + ν(1 − e^{−4εt})/(4ε)`` (Itô, ``dE[H]/dt = −4εE[H] + ν``).  Every level telescopes
``P = Y − βC`` with one β, so the estimate is ``E Y_L − β(E C_L − E C)``: exact for a linear system (``Y ≡ C``
path by path), and for the sleigh within its Monte-Carlo error of the closed form.  Tolerances come from the
standard errors (4 SE, 99.99 %), or from rounding where the estimator is exact.
"""

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ChaplyginBall, ChaplyginSleigh, ball_covariances
from nhsde.statistics import (
    Mean,
    Multilevel,
    MultilevelQuasiMonteCarlo,
    QuasiMonteCarlo,
    multilevel_monte_carlo,
    multilevel_quasi_monte_carlo,
    to_accuracy,
)

DELTA = 1 / 1.4
BALL = BallOnVibratingPlane(eps=1.0, nu=1.0).build()
BALL_ARGS: dict[str, Any] = dict(t1=1.0, dt=0.25, statistic=("cov", "x", "x"), save=nhsde.Save(names=("x", "u_x"), n=3))

EPS, T1 = 0.5, 2.0
SLEIGH = ChaplyginSleigh(eps=EPS, nu=1.0, drift=False).build()
SLEIGH_Y0 = jnp.array([1.0, 0.5])  # v, ω; H0 = ½(m v² + J ω²) = 0.75 with J = 2
GAUSS = nhsde.PlatenWeak2(increments="gaussian")
SLEIGH_ARGS: dict[str, Any] = dict(t1=T1, dt=0.25, statistic=Mean("energy"), solver=GAUSS)
SLEIGH_COUNTS = (4096, 1024, 256, 256)


def sleigh_energy(eps, nu):
    decay = jnp.exp(-4 * eps * T1)
    return 0.75 * decay + nu * (1 - decay) / (4 * eps)


def ball_exact(ts):
    k_xx, k_xu, k_uu = (np.asarray(k) for k in ball_covariances(jnp.asarray(ts, jnp.float64), 1.0, 1.0, DELTA))
    return np.stack([np.stack([k_xx, k_xu], -1), np.stack([k_xu, k_uu], -1)], -2)


@pytest.mark.parametrize("antithetic", [False, True])
def test_on_a_linear_system_every_level_is_exact(antithetic):
    """A linear system is its own linearisation: ``Y ≡ C`` on every level's fine and coarse solve, β = 1, each level
    term is rounding and the sum is ``E C``, the continuous covariance, although Euler at h₀ = 1/4 is biased.  The
    control doubles every level's path-steps."""
    counts = (256, 128, 64)
    est = multilevel_monte_carlo(
        BALL, jnp.zeros(4), jax.random.key(0), n_paths=counts, control="mean", antithetic=antithetic, **BALL_ARGS
    )
    np.testing.assert_allclose(np.asarray(est.cov), ball_exact(np.asarray(est.ts)), rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(np.asarray(est.mean), 0.0, atol=1e-15)
    assert est.coefficient is not None
    np.testing.assert_allclose(np.asarray(est.coefficient.cov[1:]), 1.0, rtol=1e-8)
    assert np.all(np.asarray(est.level_variances) < 1e-20 * float(est.value()[0]) ** 2)
    plain = multilevel_monte_carlo(
        BALL, jnp.zeros(4), jax.random.key(0), n_paths=counts, antithetic=antithetic, **BALL_ARGS
    )
    assert est.level_costs == tuple(2 * c for c in plain.level_costs)
    assert est.cost.path_steps == 2 * plain.cost.path_steps
    assert plain.coefficient is None


@pytest.fixture(scope="module")
def sleigh_pair():
    """The controlled and the plain estimate on the same levels' paths, derivatives in (ε, ν) included."""
    key, wrt = jax.random.key(3), ("eps", "nu")
    controlled = multilevel_monte_carlo(
        SLEIGH, SLEIGH_Y0, key, n_paths=SLEIGH_COUNTS, control="mean", wrt=wrt, **SLEIGH_ARGS
    )
    plain = multilevel_monte_carlo(SLEIGH, SLEIGH_Y0, key, n_paths=SLEIGH_COUNTS, **SLEIGH_ARGS)
    return controlled, plain


def test_the_sleigh_energy_agrees_and_every_level_variance_falls(sleigh_pair):
    """E[H](t1) of the nonlinear sleigh within 4 SE of the closed form (weak order 2 down to h = 1/32: bias
    ``bias(Y_L) − β bias(C_L)`` far below the SE ≈ 2e-3).  The control explains most of level 0 (``H(Z) − H(C) =
    O(ν)`` against ``O(√ν)``; ``control_variate``'s own test: a reduction > 4 at ν = 1; measured 25) and, the
    coupled fine and coarse controls moving with the system's, each finer level's difference too (measured 4–7)."""
    controlled, plain = sleigh_pair
    value, se = (float(x) for x in controlled.value())
    assert abs(value - float(sleigh_energy(EPS, 1.0))) <= 4 * se, (value, se)
    v_cv, v_plain = np.asarray(controlled.level_variances), np.asarray(plain.level_variances)
    assert v_plain[0] > 4 * v_cv[0], (v_plain, v_cv)
    assert np.all(v_plain > v_cv), (v_plain, v_cv)
    # the control doubles the path-steps: it pays where Σ √(V_ℓ C_ℓ) (Giles' cost at a fixed RMSE) falls
    work = [np.sum(np.sqrt(e.level_variances * np.asarray(e.level_costs))) ** 2 for e in (controlled, plain)]
    assert work[0] < work[1] / 2, work


def test_derivatives_are_jacfwd_of_the_estimate_and_agree_with_the_closed_form(sleigh_pair):
    """``wrt=('eps', 'nu')``: the per-path tangents of both solves on every level, plus ``β ∂E C``, are
    ``jax.jacfwd`` of the estimate (β held fixed) up to rounding (two small levels), and within 4 of their SEs of
    ``∂E[H](t1)``."""
    counts, key = (128, 64), jax.random.key(4)

    def value(theta):
        system = SLEIGH.replace_params(eps=theta[0], nu=theta[1])
        return multilevel_monte_carlo(system, SLEIGH_Y0, key, n_paths=counts, control="mean", **SLEIGH_ARGS).value()[0]

    theta = jnp.array([EPS, 1.0])
    small = multilevel_monte_carlo(
        SLEIGH, SLEIGH_Y0, key, n_paths=counts, control="mean", wrt=("eps", "nu"), **SLEIGH_ARGS
    )
    np.testing.assert_allclose(np.asarray(small.derivative()[0]), np.asarray(jax.jacfwd(value)(theta)), rtol=1e-9)
    d, d_se = (np.asarray(x) for x in sleigh_pair[0].derivative())
    exact = np.asarray(jax.grad(lambda t: sleigh_energy(t[0], t[1]))(theta))
    assert np.all(np.abs(d - exact) <= 4 * d_se), (d, exact, d_se)


def test_adaptive_levels_reach_the_target_with_less_work():
    """``rmse=…``: levels and samples chosen from the controlled level terms; the error is within 3 rmse (a
    3σ bound: the MSE is ≤ rmse²) and the work below plain multilevel's on the same keys (measured 2.6× less)."""
    rmse = 3e-3
    runs = [
        multilevel_monte_carlo(SLEIGH, SLEIGH_Y0, jax.random.key(0), rmse=rmse, control=control, **SLEIGH_ARGS)
        for control in ("mean", None)
    ]
    controlled, plain = runs
    assert abs(float(controlled.value()[0]) - float(sleigh_energy(EPS, 1.0))) <= 3 * rmse
    assert controlled.cost.path_steps < plain.cost.path_steps, (controlled.cost, plain.cost)


def test_bad_controls_are_refused_naming_the_argument():
    with pytest.raises(ValueError, match=r"control='median'; allowed: 'mean'"):
        multilevel_monte_carlo(SLEIGH, SLEIGH_Y0, jax.random.key(0), n_paths=(64,), control="median", **SLEIGH_ARGS)
    with pytest.raises(ValueError, match=r"control has shape \(3,\)"):
        multilevel_monte_carlo(SLEIGH, SLEIGH_Y0, jax.random.key(0), n_paths=(64,), control=jnp.zeros(3), **SLEIGH_ARGS)
    jumps = nhsde.noise.CompoundPoisson(law=nhsde.noise.NormalJumps(std=0.5), intensity=2.0)
    with pytest.raises(ValueError, match="control is not Gaussian"):
        multilevel_monte_carlo(
            dataclasses.replace(BALL, noise=jumps),
            jnp.zeros(4),
            jax.random.key(0),
            n_paths=(64,),
            control="mean",
            t1=1.0,
            dt=0.25,
            statistic=Mean("energy"),
        )


def test_the_fitted_coefficient_is_one_per_saved_entry():
    """β is fitted per saved mean and covariance entry on level 0 and reported; at t0 (no variance) it is 1."""
    est = multilevel_monte_carlo(
        SLEIGH,
        SLEIGH_Y0,
        jax.random.key(1),
        n_paths=(256, 64),
        control="mean",
        save=nhsde.Save(names=("energy", "v"), n=3),
        **SLEIGH_ARGS,
    )
    assert est.coefficient is not None
    assert est.coefficient.mean.shape == (3, 2) and est.coefficient.cov.shape == (3, 2, 2)
    np.testing.assert_array_equal(np.asarray(est.coefficient.mean[0]), 1.0)
    assert math.isfinite(float(est.value()[0]))


# ----------------------------------------------------------------------------- inside quasi-Monte Carlo


def test_inside_qmc_a_linear_system_is_exact():
    """On the same scrambled points the linear ball is its own control: every level's term is rounding, the
    estimate the continuous covariance, its standard error zero; β fitted on level 0's scramblings is 1."""
    est = multilevel_quasi_monte_carlo(
        BALL, jnp.zeros(4), jax.random.key(0), n_points=(64, 64), control="mean", **BALL_ARGS
    )
    np.testing.assert_allclose(np.asarray(est.cov), ball_exact(np.asarray(est.ts)), rtol=1e-10, atol=1e-15)
    assert np.all(np.asarray(est.cov_se[-1]) < 1e-10 * float(est.value()[0]))
    assert est.coefficient is not None
    np.testing.assert_allclose(np.asarray(est.coefficient.cov[1:]), 1.0, rtol=1e-8)


def test_inside_qmc_the_sleigh_energy_and_its_derivatives_agree():
    """One level of 16 × 1024 points at h = 1/16 (weak order 2): E[H](t1) and ∂E[H]/∂(ε, ν) within 4 SE of the
    closed form (the SE over 14 degrees of freedom: β is fitted on the 16 scramblings), and the control divides
    the scramblings' variance (measured ÷3.3 at h = 1/8, β ≈ 1; asked: > 2)."""
    args: dict[str, Any] = dict(SLEIGH_ARGS, dt=1 / 16)
    key = jax.random.key(2)
    est = multilevel_quasi_monte_carlo(
        SLEIGH, SLEIGH_Y0, key, n_points=(1024,), control="mean", wrt=("eps", "nu"), **args
    )
    plain = multilevel_quasi_monte_carlo(SLEIGH, SLEIGH_Y0, key, n_points=(1024,), **args)
    value, se = (float(x) for x in est.value())
    assert abs(value - float(sleigh_energy(EPS, 1.0))) <= 4 * se, (value, se)
    assert float(plain.value()[1]) > math.sqrt(2) * se, (float(plain.value()[1]), se)
    d, d_se = (np.asarray(x) for x in est.derivative())
    exact = np.asarray(jax.grad(lambda t: sleigh_energy(t[0], t[1]))(jnp.array([EPS, 1.0])))
    assert np.all(np.abs(d - exact) <= 4 * d_se), (d, exact, d_se)
    assert est.cost.path_steps == 2 * plain.cost.path_steps


@pytest.mark.parametrize("kind", [Multilevel, QuasiMonteCarlo, MultilevelQuasiMonteCarlo])
def test_to_accuracy_prices_each_estimator_with_the_control(kind):
    """``Multilevel``, ``QuasiMonteCarlo`` and ``MultilevelQuasiMonteCarlo`` with ``control=True`` price from the
    controlled pilot (shared on ``Pricing``, its work counted) and meet a target."""
    rmse = 0.02 * float(sleigh_energy(EPS, 1.0))
    res = to_accuracy(
        SLEIGH,
        SLEIGH_Y0,
        jax.random.key(7),
        t1=T1,
        statistic=Mean("energy"),
        rmse=rmse,
        save=nhsde.Save(names=("energy",), n=2),
        estimators=(kind(GAUSS, control=True),),
    )
    chosen = res.alternatives[0]
    assert chosen.name.endswith("weak2-gaussian, control variate") and chosen.applies, res.report()
    assert chosen.pilot_work > 0 and res.pilot_cost.path_steps >= chosen.pilot_work
    assert abs(float(res.value()[0]) - float(sleigh_energy(EPS, 1.0))) <= 4 * rmse


def test_a_run_far_beyond_its_plan_is_never_returned():
    """Chaplygin's ball at h₀ = 1/4 (key 1017, relative RMSE 1e-2): the controlled multilevel run's standard error
    came out 4.6e17× the target, every value finite (its paths went far beyond the pilot's).  ``to_accuracy``
    refuses such a run (standard error above 2× the target): from its own coarsest step it prices everything
    again from half the step and meets the target there; from a given step it raises, naming the ratio."""
    scene = ChaplyginBall(eps=1.0, nu=2.0)
    system, y0 = scene.build(), scene.initial_state().astype(jnp.float64)
    args: dict[str, Any] = dict(
        t1=4.0,
        statistic=Mean("energy"),
        rmse=0.0075,
        save=nhsde.Save(names=("energy",), n=2),
        estimators=(Multilevel(GAUSS, control=True),),
    )
    res = to_accuracy(system, y0, jax.random.key(1017), **args)
    assert "standard error of" in res.reason and "priced again from dt=0.125" in res.reason, res.reason
    value, se = (float(x) for x in res.value())
    assert se <= 0.0075 and abs(value - 0.75) <= 4 * se  # E[H] = 3ν/(8ε), stationary (S0 Statement 1)
    with pytest.raises(ValueError, match=r"dt=0.25: .* standard error of .*× the target .* pass a smaller dt"):
        to_accuracy(system, y0, jax.random.key(1017), dt=0.25, **args)
