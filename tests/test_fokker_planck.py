"""Fokker–Planck grid solver (S0 (2.2)): a third route to stationary and transient densities."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_stationary_density import (
    conformal,
    conformal_measure,
    oscillator_hamiltonian,
    relativistic,
    relativistic_hamiltonian,
)

import nhsde
from nhsde import StateLayout, StochasticSystem
from nhsde.noise import CompoundPoisson, NormalJumps
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh
from nhsde.statistics import fokker_planck, stationary_density, stationary_fokker_planck, stationary_moments


def test_one_dimensional_stationary_density_three_routes():
    """Relativistic momentum (Jüttner law): the grid density equals stationary_density to second order in the
    cell size, and the Monte-Carlo histogram within its binomial error."""
    system = relativistic(eps=0.5, nu=1.0)
    exact = stationary_density(system, relativistic_hamiltonian)
    errors = []
    for n in (200, 400):
        grid = stationary_fokker_planck(system, [(-10.0, 10.0)], n)
        errors.append(float(jnp.max(jnp.abs(grid.values - exact.pdf(grid.axes[0][:, None])))))
        np.testing.assert_allclose(jnp.sum(grid.values) * grid.cell_volume, 1.0, rtol=1e-12)
    assert errors[1] < 2e-4 * float(jnp.max(grid.values)), errors
    assert 3.0 < errors[0] / errors[1] < 5.0, errors  # O(h²)

    n_paths = 4096
    ens = nhsde.simulate(
        system,
        jnp.zeros(1),
        jax.random.key(8),
        n_paths=n_paths,
        t1=10.0,
        dt=0.01,
        solver="sra1",
        save=nhsde.Save(n=2, paths=True),
    )
    p = np.asarray(ens.paths[:, -1, 0])
    edges = np.linspace(-3.0, 3.0, 13)
    prob = np.asarray(grid.cell_probabilities(edges))
    counts = np.histogram(p, edges)[0] / n_paths
    se = np.sqrt(prob * (1 - prob) / n_paths)
    assert np.all(np.abs(counts - prob) <= 4 * se), (counts, prob, se)


def test_ball_transient_and_stationary_densities():
    """u̇ = −2εu + √ν δ V from a Gaussian: mean m₀e^{−2εt}, variance s₀²e^{−4εt} + νδ²(1 − e^{−4εt})/(4ε)."""
    eps, nu, s0, m0 = 0.7, 1.3, 0.2, np.array([1.0, -0.5])
    scene = BallOnVibratingPlane(eps=eps, nu=nu, drift=False)
    g = nu * float(scene.params.delta) ** 2

    def initial(x):
        return jnp.exp(-jnp.sum((x - m0) ** 2, -1) / (2 * s0**2)) / (2 * np.pi * s0**2)

    grid = fokker_planck(scene.build(), initial, [(-3, 3), (-3, 3)], [120, 120], t1=1.0, dt=0.01, save_n=3)
    ts = np.asarray(grid.ts)
    mean = m0 * np.exp(-2 * eps * ts)[:, None]
    var = s0**2 * np.exp(-4 * eps * ts) + g * (1 - np.exp(-4 * eps * ts)) / (4 * eps)
    np.testing.assert_allclose(grid.mean(), mean, atol=1e-3)
    np.testing.assert_allclose(jnp.diagonal(grid.cov(), axis1=1, axis2=2), np.stack([var, var], -1), atol=3e-4)
    np.testing.assert_allclose(grid.cov()[:, 0, 1], 0.0, atol=1e-5)  # implicit steps couple the axes at O(dt²)
    np.testing.assert_allclose(jnp.sum(grid.values, axis=(1, 2)) * grid.cell_volume, 1.0, rtol=1e-10)
    errors = [
        np.abs(stationary_fokker_planck(scene.build(), [(-3, 3), (-3, 3)], [n, n]).cov() - g / (4 * eps) * np.eye(2))
        for n in (80, 160)
    ]
    assert np.max(errors[1]) < 1e-3 * g / (4 * eps) and 3.0 < np.max(errors[0]) / np.max(errors[1]) < 4.5, errors


def test_statement_2_density_with_noise_on_one_component():
    """Degenerate diffusion (noise on p only; q is advected): the grid density → N e^{−αH} at second order."""
    system = conformal(eps=0.5, nu=1.0)
    exact = stationary_density(system, oscillator_hamiltonian, invariant_density=conformal_measure)
    errors = []
    for n in (60, 120):
        grid = stationary_fokker_planck(system, [(-5, 5), (-5, 5)], [n, n])
        x = jnp.stack(jnp.meshgrid(*grid.axes, indexing="ij"), -1)
        errors.append(float(jnp.max(jnp.abs(grid.values - exact.pdf(x)))))
    assert errors[1] < 2e-3 * float(jnp.max(grid.values)), errors
    assert 3.0 < errors[0] / errors[1] < 5.5, errors  # O(h²)
    np.testing.assert_allclose(grid.cov(), exact.cov, atol=2e-3)


def test_sleigh_velocities_stationary_density_against_monte_carlo():
    """Nonlinear, no closed form (no invariant measure): the grid's stationary moments of (v, ω) against Monte Carlo."""
    scene = ChaplyginSleigh(eps=0.5, nu=1.0, drift=False)
    grid = stationary_fokker_planck(scene.build(), [(-3.0, 5.0), (-3.0, 3.0)], [100, 80]).moments()
    ens = nhsde.simulate(
        scene.build(),
        scene.initial_state().astype(jnp.float64),
        jax.random.key(9),
        n_paths=2048,
        t1=10.0,
        dt=0.02,
        solver="sra1",
        save=nhsde.Save(n=6),
    )
    mc = stationary_moments(ens, t_from=6.0)
    assert np.all(np.abs(np.asarray(grid.mean - mc.mean)) <= 4 * np.asarray(ens.mean_se[-1])), (grid.mean, mc.mean)
    assert np.all(np.abs(np.asarray(grid.cov - mc.cov)) <= 4 * np.asarray(ens.cov_se[-1])), (grid.cov, mc.cov)
    assert float(grid.mean[0]) > 10 * float(ens.mean_se[-1, 0])  # the noise drives the sleigh forward on average


def test_bad_input_is_refused():
    sleigh = ChaplyginSleigh().build()
    with pytest.raises(ValueError, match=r"1- and 2-dimensional systems; this one has 5 components"):
        stationary_fokker_planck(sleigh, [(-1, 1)] * 5, [10] * 5)
    ball = BallOnVibratingPlane(drift=False).build()
    poisson = dataclasses.replace(ball, noise=CompoundPoisson(law=NormalJumps(), intensity=1.0))
    with pytest.raises(ValueError, match=r"for Wiener noise; this system is driven by CompoundPoisson"):
        stationary_fokker_planck(poisson, [(-1, 1)] * 2, [10, 10])
    with pytest.raises(ValueError, match=r"bounds \(1.0, -1.0\): need finite lower < upper"):
        stationary_fokker_planck(ball, [(1, -1), (-1, 1)], [10, 10])
    with pytest.raises(ValueError, match=r"n=2: need at least 3 cells"):
        stationary_fokker_planck(ball, [(-1, 1), (-1, 1)], [2, 10])
    forced = StochasticSystem(
        drift_fn=lambda t, y, p: -y + jnp.sin(t),
        diffusion_fn=lambda t, y, p: jnp.ones((1, 1), y.dtype),
        params={},
        layout=StateLayout(("u",), ("velocity",)),
        noise_dim=1,
        additive_noise=True,
    )
    with pytest.raises(ValueError, match=r"time-independent drift and diffusion"):
        stationary_fokker_planck(forced, [(-1, 1)], [10])
    with pytest.raises(ValueError, match=r"save_n=4: save_n − 1 must be ≥ 1 and divide the 10 steps"):
        fokker_planck(ball, lambda x: jnp.ones(x.shape[:-1]), [(-1, 1)] * 2, [10, 10], t1=1.0, dt=0.1, save_n=4)
