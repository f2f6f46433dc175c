"""Multilevel randomised quasi-Monte Carlo (``nhsde.statistics.multilevel_quasi_monte_carlo``): unbiased within its
reported error and bias bound on the ball, agreement with multilevel Monte Carlo on the sleigh at less work, one
compiled solve for every level and point count, and the refusals naming the argument.

Tolerances come from the reported standard errors (from the spread of 16 independent scramblings per level) and
the reported bias estimate."""

import dataclasses
import logging
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.noise import CompoundPoisson, NormalJumps
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances
from nhsde.statistics import multilevel_monte_carlo, multilevel_quasi_monte_carlo

DELTA = 1 / 1.4
BALL = BallOnVibratingPlane(eps=1.0, nu=1.0)
Y0 = jnp.zeros(4)
SLEIGH = ChaplyginSleigh(drift=False)
ENERGY: dict[str, Any] = dict(t1=1.0, dt=0.25, statistic=("mean", "energy"), save=nhsde.Save(names=("energy",)))


class _Compiles(logging.Handler):
    def __init__(self):
        super().__init__()
        self.names: list[str] = []

    def emit(self, record):
        if record.getMessage().startswith("Compiling "):
            self.names.append(record.getMessage().split(" ")[1])


@pytest.fixture
def compiles():
    """The names of the XLA programs compiled while the test runs (``jax_log_compiles``)."""
    handler, logger = _Compiles(), logging.getLogger("jax")
    level, before = logger.level, jax.config.jax_log_compiles
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING)
    jax.config.update("jax_log_compiles", True)
    yield handler.names
    jax.config.update("jax_log_compiles", before)
    logger.removeHandler(handler)
    logger.setLevel(level)


def test_ball_covariance_within_its_errors_and_bias_bound():
    """K_xx(1) of the ball (S0 (3.1)) to 1% RMSE: within 4 reported SE plus the reported bias bound of the exact
    value; the reported fields are consistent (SE² = Σ V_ℓ/N_ℓ, cost = Σ N_ℓ C_ℓ, N_ℓ multiples of 16 × 64)."""
    exact = float(ball_covariances(jnp.float64(1.0), 1.0, 1.0, DELTA)[0])
    eps = 1e-2 * exact
    r = multilevel_quasi_monte_carlo(
        BALL.build(), Y0, jax.random.key(7), t1=1.0, dt=0.25, statistic=("cov", "x", "x"), rmse=eps
    )
    value, se = (float(x) for x in r.value())
    assert abs(value - exact) <= 4 * se + float(r.bias), (value, exact, se, float(r.bias))
    assert se <= eps / math.sqrt(2) * 1.0001 and float(r.bias) <= eps / math.sqrt(2), (se, float(r.bias), eps)
    counts = np.array(r.n_paths_per_level)
    assert np.all(counts % (16 * 64) == 0) and int(r.n_paths) == counts.sum(), counts
    np.testing.assert_allclose(np.sum(np.asarray(r.level_variances) / counts), se**2, rtol=1e-9)
    np.testing.assert_allclose(r.cost.path_steps, float(np.dot(counts, r.level_costs)))
    assert r.level_costs[:2] == (4.0, 12.0), r.level_costs
    np.testing.assert_allclose(float(np.sum(r.level_means)), value, rtol=1e-12)


def test_derivatives_in_eps_and_nu_are_those_of_the_finest_euler_chain():
    """``wrt=('eps', 'nu')`` with fixed points on three levels: the levels telescope to the finest step, so the
    derivatives of K_xx(1) and K_uu(1) are those of the Euler chain at h = 1/16 (``K ← A K Aᵀ + Q``, by
    ``jax.jacfwd``), within 4 reported SE (scramblings' spread, levels' variances added); the values are those of
    the same call without ``wrt``."""
    args: dict[str, Any] = dict(
        t1=1.0, dt=0.25, statistic=("cov", "x", "x"), n_points=(256, 128, 64), save=nhsde.Save(names=("x", "u_x"), n=2)
    )
    r = multilevel_quasi_monte_carlo(BALL.build(), Y0, jax.random.key(3), wrt=("eps", "nu"), **args)
    plain = multilevel_quasi_monte_carlo(BALL.build(), Y0, jax.random.key(3), **args)
    np.testing.assert_allclose(np.asarray(r.cov), np.asarray(plain.cov), rtol=1e-12)

    def chain(theta):
        dt, n = 1 / 16, 16
        a = jnp.array([[1.0, dt], [0.0, 1.0 - 2.0 * theta[0] * dt]])
        q = jnp.array([[0.0, 0.0], [0.0, theta[1] * DELTA**2 * dt]])
        k = jnp.zeros((2, 2))
        for _ in range(n):
            k = a @ k @ a.T + q
        return jnp.stack([k[0, 0], k[1, 1]])

    exact = np.asarray(jax.jacfwd(chain)(jnp.array([1.0, 1.0])))  # (K_xx, K_uu) × (eps, nu)
    assert r.derivatives is not None and r.derivatives.wrt == ("eps", "nu")
    names = r.names
    ix, iu = names.index("x"), names.index("u_x")
    d = np.asarray(r.derivatives.d_cov)[:, -1]
    se = np.asarray(r.derivatives.d_cov_se)[:, -1]
    got = np.stack([d[:, ix, ix], d[:, iu, iu]])
    err = np.stack([se[:, ix, ix], se[:, iu, iu]])
    assert np.all(err > 0) and np.all(np.abs(got - exact) <= 4 * err), (got, exact, err)


def test_gaussian_weak2_ball_covariance_within_its_errors_and_bias_bound():
    """PlatenWeak2(increments='gaussian') on every level (ΔW from the points, V pseudo-random): K_xx(1) of the ball
    to 1% RMSE within 4 reported SE plus the reported bias bound (weak order 2) of the exact value."""
    exact = float(ball_covariances(jnp.float64(1.0), 1.0, 1.0, DELTA)[0])
    solver = nhsde.PlatenWeak2(increments="gaussian")
    r = multilevel_quasi_monte_carlo(
        BALL.build(),
        Y0,
        jax.random.key(8),
        t1=1.0,
        dt=0.25,
        statistic=("cov", "x", "x"),
        rmse=1e-2 * exact,
        solver=solver,
    )
    value, se = (float(x) for x in r.value())
    assert abs(value - exact) <= 4 * se + float(r.bias), (value, exact, se, float(r.bias))


def test_sleigh_energy_agrees_with_multilevel_monte_carlo_with_less_work_and_one_program(compiles):
    """E[H](1) on the sleigh: within 4 combined SE of multilevel Monte Carlo's; halving the RMSE (2e-2 → 1e-2)
    multiplies the work by less than 4 (cost exponent above −2) and compiles no new program although it adds a
    level and doubles points."""
    system, y0 = SLEIGH.build(), SLEIGH.initial_state()
    coarse = multilevel_quasi_monte_carlo(system, y0, jax.random.key(1), rmse=2e-2, **ENERGY)
    del compiles[:]
    fine = multilevel_quasi_monte_carlo(system, y0, jax.random.key(2), rmse=1e-2, **ENERGY)
    assert compiles == [], compiles
    assert (
        len(fine.n_paths_per_level) > len(coarse.n_paths_per_level)
        or fine.n_paths_per_level[0] > (coarse.n_paths_per_level[0])
    )
    mc = multilevel_monte_carlo(system, y0, jax.random.key(3), rmse=1e-2, **ENERGY)
    (q, q_se), (m, m_se) = ((float(x) for x in e.value()) for e in (fine, mc))
    assert abs(q - m) <= 4 * math.hypot(q_se, m_se) + float(fine.bias) + float(mc.bias), (q, q_se, m, m_se)
    exponent = math.log(fine.cost.path_steps / coarse.cost.path_steps) / math.log(1e-2 / 2e-2)
    assert exponent > -2, f"cost ∝ rmse^{exponent:.2f} ({coarse.cost.path_steps} → {fine.cost.path_steps})"
    assert fine.cost.path_steps < mc.cost.path_steps, (fine.cost.path_steps, mc.cost.path_steps)


def test_fixed_points_replay_the_same_estimate():
    """n_points=(N_0, …) of an adaptive run's points per scrambling gives bitwise the same estimate."""
    system, y0 = SLEIGH.build(), SLEIGH.initial_state()
    r = multilevel_quasi_monte_carlo(system, y0, jax.random.key(4), rmse=4e-2, **ENERGY)
    points = tuple(n // 16 for n in r.n_paths_per_level)
    again = multilevel_quasi_monte_carlo(system, y0, jax.random.key(4), n_points=points, **ENERGY)
    np.testing.assert_array_equal(np.asarray(again.mean), np.asarray(r.mean))
    np.testing.assert_array_equal(np.asarray(again.cov_se), np.asarray(r.cov_se))


def test_refuses_what_it_cannot_do_naming_the_argument():
    system, key = BALL.build(), jax.random.key(0)
    base: dict[str, Any] = dict(t1=1.0, statistic=("cov", "x", "x"), rmse=1e-2)
    with pytest.raises(ValueError, match=r"dt=0\.3333.*power of two"):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=1 / 3, **base)
    jumps = dataclasses.replace(system, noise=CompoundPoisson(law=NormalJumps(), intensity=1.0))
    with pytest.raises(ValueError, match="system.noise=CompoundPoisson has jumps.*Wiener"):
        multilevel_quasi_monte_carlo(jumps, Y0, key, dt=0.25, **base)
    with pytest.raises(ValueError, match="solver='weak2' needs ThreePointIncrement"):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=0.25, solver="weak2", **base)
    with pytest.raises(ValueError, match="solver='sra1' needs SpaceTimeLevyArea.*allowed: euler"):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=0.25, solver="sra1", **base)
    with pytest.raises(TypeError, match="dt=FixedSteps"):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=nhsde.FixedSteps(0.25), **base)
    with pytest.raises(ValueError, match="replicates=1"):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=0.25, replicates=1, **base)
    with pytest.raises(ValueError, match=r"n_points=\(64, 96\).*power of two"):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=0.25, t1=1.0, statistic=("cov", "x", "x"), n_points=(64, 96))
    with pytest.raises(TypeError, match="exactly one of rmse"):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=0.25, n_points=(64,), **base)
    with pytest.raises(ValueError, match="statistic="):
        multilevel_quasi_monte_carlo(system, Y0, key, dt=0.25, t1=1.0, statistic=("median", "x"), rmse=1e-2)


def test_antithetic_points_on_every_level_make_odd_means_exact_and_the_covariance_within_its_errors():
    """Antithetic pairs inside multilevel QMC: on the ball from rest ``x(−W) = −x(W)`` on every level, so the
    mean of x is exact; K_xx(1) (S0 (3.1)) is within 4 reported SE plus the bias bound, at twice the level costs."""
    exact = float(ball_covariances(jnp.float64(1.0), 1.0, 1.0, DELTA)[0])
    eps = 2e-2 * exact
    args: dict[str, Any] = dict(t1=1.0, dt=0.25, save=nhsde.Save(names=("x",)), antithetic=True)
    r = multilevel_quasi_monte_carlo(BALL.build(), Y0, jax.random.key(8), statistic=("cov", "x", "x"), rmse=eps, **args)
    value, se = (float(x) for x in r.value())
    assert abs(value - exact) <= 4 * se + float(r.bias), (value, exact, se, float(r.bias))
    assert r.level_costs[:2] == (8.0, 24.0), r.level_costs
    assert abs(float(r.mean[-1, 0])) < 1e-12
