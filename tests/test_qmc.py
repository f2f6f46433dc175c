"""Randomised quasi-Monte Carlo (``nhsde.statistics.quasi_monte_carlo``): unbiasedness and honest errors on the
ball against the Euler chain's exact moments, the variance reduction against plain Monte Carlo, chunking
invariance, derivatives, and the refusals.  The generator and the driver: ``test_internal_qmc.py``."""

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.noise import CompoundPoisson, NormalJumps
from nhsde.scenes import ChaplyginSleigh, ball_covariances
from nhsde.statistics import quasi_monte_carlo

GAUSSIAN_WEAK2 = nhsde.PlatenWeak2(increments="gaussian")

T1, DT, N_PATHS, REPLICATES = 1.0, 1 / 16, 4096, 16


def euler_cov(eps, nu, delta, dt, n_steps):
    """Exact covariance of (x, u_x) of the Euler chain of the ball from rest: K ← A K Aᵀ + Q per step."""
    a = jnp.array([[1.0, dt], [0.0, 1.0 - 2.0 * eps * dt]])
    q = jnp.array([[0.0, 0.0], [0.0, nu * delta**2 * dt]])
    k = jnp.zeros((2, 2))
    for _ in range(n_steps):
        k = a @ k @ a.T + q
    return k


@pytest.fixture(scope="module")
def ball():
    scene = nhsde.scenes.BallOnVibratingPlane(eps=0.5, nu=1.0)
    return scene.build(), scene.initial_state()


@pytest.fixture(scope="module")
def ball_qmc(ball):
    system, y0 = ball
    return quasi_monte_carlo(system, y0, jax.random.key(0), n_paths=N_PATHS, t1=T1, dt=DT, replicates=REPLICATES)


def test_unbiased_with_honest_errors_and_far_smaller_than_monte_carlo(ball, ball_qmc):
    system, y0 = ball
    p = system.params
    exact = euler_cov(p.eps, p.nu, p.delta, DT, round(T1 / DT))
    r = ball_qmc
    assert r.names == ("x", "y", "u_x", "u_y") and int(r.n_paths) == N_PATHS * REPLICATES
    for axis in ((0, 2), (1, 3)):  # (x, u_x) and (y, u_y): the same law
        cov = np.asarray(r.cov[-1])[np.ix_(axis, axis)]
        se = np.asarray(r.cov_se[-1])[np.ix_(axis, axis)]
        np.testing.assert_array_less(np.abs(cov - exact), 4 * se)
    np.testing.assert_array_less(np.abs(r.mean[-1]), 4 * r.mean_se[-1])  # E = 0 exactly
    mc = nhsde.simulate(system, y0, jax.random.key(1), n_paths=N_PATHS * REPLICATES, t1=T1, dt=DT)
    # measured: the covariances' standard errors are 24–49× smaller than plain Monte Carlo's at the same paths
    gain = np.asarray(mc.cov_se[-1] / r.cov_se[-1])
    assert gain[0, 0] > 10 and gain[1, 1] > 10, gain


def test_the_same_key_gives_bitwise_the_same_estimate_whatever_the_chunking(ball, ball_qmc):
    system, y0 = ball
    r = quasi_monte_carlo(
        system,
        y0,
        jax.random.key(0),
        n_paths=N_PATHS,
        t1=T1,
        dt=DT,
        replicates=REPLICATES,
        batching=nhsde.Batching(chunk_size=1024),
    )
    for name in ("mean", "cov", "mean_se", "cov_se"):
        np.testing.assert_array_equal(getattr(r, name), getattr(ball_qmc, name))


def test_derivatives_match_the_euler_chain(ball):
    system, y0 = ball
    p = system.params
    r = quasi_monte_carlo(system, y0, jax.random.key(3), n_paths=1024, t1=T1, dt=DT, replicates=8, wrt=("eps", "nu"))
    assert r.derivatives is not None and r.derivatives.wrt == ("eps", "nu")
    exact = jax.jacfwd(lambda eps, nu: euler_cov(eps, nu, p.delta, DT, round(T1 / DT))[0, 0], argnums=(0, 1))(
        p.eps, p.nu
    )
    d, se = np.asarray(r.derivatives.d_cov[:, -1, 0, 0]), np.asarray(r.derivatives.d_cov_se[:, -1, 0, 0])
    np.testing.assert_array_less(np.abs(d - np.asarray(exact)), 4 * se)
    assert np.all(se < 0.01 * np.abs(d))


def weak2_cov(system, y0, dt, n_steps):
    """Exact covariance of PlatenWeak2's chain on a linear system with additive noise: a step is
    ``X₊ = (I + Ah + A²h²/2) X + (I + Ah/2) b ΔW``, so ``K ← M K Mᵀ + h N b bᵀ Nᵀ``."""
    a = jax.jacfwd(lambda y: system.drift(0.0, y, system.params))(y0)
    b = system.diffusion(0.0, y0, system.params)
    eye = jnp.eye(y0.size)
    m, n = eye + a * dt + a @ a * dt**2 / 2, (eye + a * dt / 2) @ b
    k = jnp.zeros((y0.size, y0.size))
    for _ in range(n_steps):
        k = m @ k @ m.T + dt * n @ n.T
    return k


def test_gaussian_weak2_on_the_ball_is_unbiased_for_its_chain_and_near_the_closed_form(ball):
    """PlatenWeak2(increments='gaussian') under QMC: the covariances of (x, u_x) within 4 SE of the closed form
    (S0 (3.1)) plus the scheme's bias, computed exactly from its linear chain; the error of the scheme is O(h²), far
    below Euler's at the same step."""
    system, y0 = ball
    p = system.params
    r = quasi_monte_carlo(system, y0, jax.random.key(5), n_paths=1024, t1=T1, dt=DT, solver=GAUSSIAN_WEAK2)
    k_xx, k_xu, k_uu = ball_covariances(jnp.float64(T1), p.eps, p.nu, p.delta)
    closed = np.array([[k_xx, k_xu], [k_xu, k_uu]])
    chain = np.asarray(weak2_cov(system, y0, DT, round(T1 / DT)))[np.ix_((0, 2), (0, 2))]
    euler = np.asarray(euler_cov(p.eps, p.nu, p.delta, DT, round(T1 / DT)))
    assert np.all(np.abs(chain - closed) < 0.2 * np.abs(euler - closed))  # weak order 2: a far smaller bias
    cov = np.asarray(r.cov[-1])[np.ix_((0, 2), (0, 2))]
    se = np.asarray(r.cov_se[-1])[np.ix_((0, 2), (0, 2))]
    np.testing.assert_array_less(np.abs((cov - closed) - (chain - closed)), 4 * se)


def test_gaussian_weak2_on_the_sleigh_has_weak_order_two_and_keeps_the_variance_reduction():
    """The sleigh's E[H](2) = H0 e^{−4ε t} + ν(1 − e^{−4ε t})/(4ε): the Richardson combination (4 E_{h/2} − E_h)/3
    of QMC weak2 at h = 1/4 and 1/8 removes an O(h²) bias, within 4 of its SE of the closed form (an O(h) bias
    would leave a third of E_h's error, about 6 SE); and the SE is far below plain Monte Carlo's, same scheme,
    same step, same paths."""
    eps, nu, t1 = 0.5, 1.0, 2.0
    system, y0 = ChaplyginSleigh(eps=eps, nu=nu, drift=False).build(), jnp.array([1.0, 0.5])
    exact = 0.75 * math.exp(-4 * eps * t1) + nu * (1 - math.exp(-4 * eps * t1)) / (4 * eps)
    save = nhsde.Save(names=("energy",), n=2)
    coarse, fine = (
        quasi_monte_carlo(system, y0, jax.random.key(6), n_paths=1024, t1=t1, dt=dt, solver=GAUSSIAN_WEAK2, save=save)
        for dt in (0.25, 0.125)
    )
    (e_h, s_h), (e_f, s_f) = ((float(r.mean[-1, 0]), float(r.mean_se[-1, 0])) for r in (coarse, fine))
    assert abs(e_h - exact) > 8 * s_h  # the bias at h = 1/4 is resolved
    assert abs((4 * e_f - e_h) / 3 - exact) < 4 * math.hypot(4 * s_f, s_h) / 3
    mc = nhsde.simulate(
        system, y0, jax.random.key(7), n_paths=16 * 1024, t1=t1, dt=0.125, solver=GAUSSIAN_WEAK2, save=save
    )
    assert float(mc.mean_se[-1, 0]) > 5 * s_f, (float(mc.mean_se[-1, 0]), s_f)  # variance ÷ 25 at least


@pytest.mark.parametrize(
    "change, named",
    [
        (dict(n_paths=1000), "n_paths=1000"),
        (dict(n_paths=32), "n_paths=32"),
        (dict(replicates=1), "replicates=1"),
        (dict(dt=0.01), "dt=0.01: (t1 − t0)/dt = 100"),
        (dict(dt=2.0**-12, t1=8.0), "dt=0.000244140625, t1=8.0"),
        (dict(solver="sra1"), "solver='sra1'"),
        (dict(solver="weak2"), "solver='weak2' needs ThreePointIncrement"),
        (dict(n_paths=2**30, replicates=4), "replicates=4, n_paths=1073741824"),
        (dict(dt=nhsde.AdaptiveSteps(dt=0.1)), "dt=AdaptiveSteps"),
    ],
)
def test_bad_input_is_refused_naming_the_argument(ball, change, named):
    system, y0 = ball
    kwargs: dict[str, Any] = dict(n_paths=64, t1=T1, dt=DT) | change
    with pytest.raises((ValueError, TypeError), match=named.replace("(", r"\(").replace(")", r"\)")):
        quasi_monte_carlo(system, y0, jax.random.key(0), **kwargs)


def test_jumps_are_refused(ball):
    system, y0 = ball
    jumping = dataclasses.replace(system, noise=CompoundPoisson(law=NormalJumps(), intensity=1.0))
    with pytest.raises(ValueError, match="system.noise=CompoundPoisson has jumps"):
        quasi_monte_carlo(jumping, y0, jax.random.key(0), n_paths=64, t1=T1, dt=DT)


def test_antithetic_points_make_odd_means_exact_and_keep_the_covariance_unbiased(ball):
    """Each point also solved with ``W → −W`` (the point set ``1 − u``): the ball from rest is linear, ``x(−W) =
    −x(W)``, so every pair averages to 0 and the means are exact; the covariances (averaged outer products of
    the two paths, not of their average) are unbiased for the Euler chain's closed form, within 4 SE, and the
    work is twice the path-steps."""
    system, y0 = ball
    p = system.params
    exact = euler_cov(p.eps, p.nu, p.delta, DT, round(T1 / DT))
    n = N_PATHS // 4
    r = quasi_monte_carlo(system, y0, jax.random.key(2), n_paths=n, t1=T1, dt=DT, antithetic=True)
    np.testing.assert_array_less(np.abs(r.mean[-1]), 1e-12)
    cov, se = (np.asarray(c[-1])[np.ix_((0, 2), (0, 2))] for c in (r.cov, r.cov_se))
    np.testing.assert_array_less(np.abs(cov - exact), 4 * se)
    assert r.cost.path_steps == 2 * n * REPLICATES * round(T1 / DT)
    with pytest.raises(TypeError, match="antithetic=1"):
        quasi_monte_carlo(system, y0, jax.random.key(2), n_paths=n, t1=T1, dt=DT, antithetic=1)
