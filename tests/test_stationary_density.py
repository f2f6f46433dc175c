"""Exact stationary densities, S0 Statements 1–2: closed forms, Monte Carlo, moment method; refusals name the
condition."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

import nhsde
from nhsde import AbstractParameters, StateLayout, StochasticSystem, parameter
from nhsde.noise import CompoundPoisson, NormalJumps
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh
from nhsde.statistics import stationary_density, stationary_moments


class Friction(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="friction ε")
    nu: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="noise intensity ν")


def system_of(drift, names, roles, diffusion=None, **params):
    """A test system; the noise √ν acts on the last component unless ``diffusion`` is given."""
    d = len(names)

    def default_diffusion(t, y, p):
        return jnp.zeros((d, 1), y.dtype).at[-1, 0].set(jnp.sqrt(p.nu))

    return StochasticSystem(
        drift_fn=drift,
        diffusion_fn=diffusion or default_diffusion,
        params=Friction(**params),
        layout=StateLayout(names, roles),
        noise_dim=1 if diffusion is None else d,
        additive_noise=True,
    )


def relativistic(**params):
    """ṗ = −2ε ∂H/∂p + √ν V with H = √(1 + p²): a one-dimensional system of Statement 1 (Jüttner law)."""
    return system_of(lambda t, y, p: -2 * p.eps * y / jnp.sqrt(1 + y**2), ("p",), ("momentum",), **params)


def relativistic_hamiltonian(x, p):
    return jnp.sqrt(1 + x[0] ** 2)


def conformal(**params):
    """q̇ = g(q) p, ṗ = −g(q) q − 2ε p + √ν V, g = 1 + q²/2: frictionless flow g·(Hamiltonian flow of
    H = (p² + q²)/2), which preserves N = 1/g (Statement 2) but not Lebesgue measure."""

    def drift(t, y, p):
        g = 1 + y[0] ** 2 / 2
        return jnp.stack([g * y[1], -g * y[0] - 2 * p.eps * y[1]])

    return system_of(drift, ("q", "p"), ("independent_coordinate", "momentum"), **params)


def oscillator_hamiltonian(x, p):
    return 0.5 * (x[0] ** 2 + x[1] ** 2)


def conformal_measure(x, p):
    return 1 / (1 + x[0] ** 2 / 2)


def test_ball_velocity_satisfies_statement_1():
    """α = 4ε/(νδ²) from the flux balance; covariance νδ²/(4ε) by quadrature, and Monte Carlo within 4 SE."""
    eps, nu = 0.7, 1.3
    scene = BallOnVibratingPlane(eps=eps, nu=nu, drift=False)
    delta = float(scene.params.delta)
    density = stationary_density(scene.build(), lambda x, p: 0.5 * x @ x)
    assert density.names == ("u_x", "u_y")
    np.testing.assert_allclose(density.alpha, 4 * eps / (nu * delta**2), rtol=1e-12)
    var = nu * delta**2 / (4 * eps)
    np.testing.assert_allclose(density.moments().cov, var * np.eye(2), rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(density.log_normaliser, math.log(2 * math.pi * var), rtol=1e-10)
    np.testing.assert_allclose(
        density.pdf(jnp.array([[0.3, -0.2]])), np.exp(-(0.09 + 0.04) / (2 * var)) / (2 * np.pi * var), rtol=1e-10
    )
    ens = nhsde.simulate(
        scene.build(),
        jnp.zeros(2),
        jax.random.key(3),
        n_paths=2048,
        t1=4.0,
        dt=0.02,
        solver="sra1",
        save=nhsde.Save(n=5),
    )
    mc = stationary_moments(ens, t_from=2.0)
    assert np.all(np.abs(np.asarray(mc.cov) - np.asarray(density.cov)) <= 4 * np.asarray(ens.cov_se[-1])), mc.cov


def test_relativistic_momentum_has_the_juttner_normaliser():
    """∫ exp(−α√(1 + p²)) dp = 2 K₁(α), α = 4ε/ν."""
    eps, nu = 0.5, 1.0
    density = stationary_density(relativistic(eps=eps, nu=nu), relativistic_hamiltonian)
    alpha = 4 * eps / nu
    np.testing.assert_allclose(density.alpha, alpha, rtol=1e-12)
    np.testing.assert_allclose(density.log_normaliser, math.log(2 * scipy.special.k1(alpha)), rtol=1e-10)
    # E[√(1 + p²)] = −d log Z/dα = K₀/K₁ + 1/α
    p = jnp.linspace(-40.0, 40.0, 400_001)
    mean_h = float(jnp.sum(density.pdf(p[:, None]) * jnp.sqrt(1 + p**2)) * (p[1] - p[0]))
    k0, k1 = scipy.special.k0(alpha), scipy.special.k1(alpha)
    np.testing.assert_allclose(mean_h, k0 / k1 + 1 / alpha, rtol=1e-8)


def test_statement_2_invariant_measure():
    """With N = 1/g the density is N e^{−αH}; without it (Statement 1) the Liouville condition fails."""
    eps, nu = 0.5, 1.0
    density = stationary_density(conformal(eps=eps, nu=nu), oscillator_hamiltonian, invariant_density=conformal_measure)
    alpha = 4 * eps / nu
    np.testing.assert_allclose(density.alpha, alpha, rtol=1e-12)
    # the q marginal is ∝ e^{−αq²/2}/(1 + q²/2): its normaliser by 1-D quadrature
    q = np.linspace(-30, 30, 600_001)
    z_q = np.sum(np.exp(-alpha * q**2 / 2) / (1 + q**2 / 2)) * (q[1] - q[0])
    np.testing.assert_allclose(density.log_normaliser, math.log(z_q * math.sqrt(2 * math.pi / alpha)), rtol=1e-10)
    assert float(density.cov[0, 0]) < 1 / alpha < float(density.cov[1, 1]) + 1e-12  # N thins out large |q|
    with pytest.raises(
        ValueError,
        match=r"invariant measure of the frictionless, noiseless flow fails: "
        r"N = 1 \(Liouville, Statement 1\) is not invariant",
    ):
        stationary_density(conformal(eps=eps, nu=nu), oscillator_hamiltonian)


def test_above_three_dimensions_the_density_is_known_up_to_its_constant():
    names = ("u1", "u2", "u3", "u4")
    system = system_of(
        lambda t, y, p: -2 * p.eps * y,
        names,
        ("velocity",) * 4,
        diffusion=lambda t, y, p: jnp.sqrt(p.nu) * jnp.eye(4, dtype=y.dtype),
    )
    density = stationary_density(system, lambda x, p: 0.5 * x @ x)
    np.testing.assert_allclose(density.alpha, 4 * 0.5 / 1.0, rtol=1e-12)
    assert density.log_normaliser is None
    np.testing.assert_allclose(density.log_unnormalised(jnp.ones((3, 4))), -4.0, rtol=1e-12)
    with pytest.raises(ValueError, match=r"known only up to 3 dimensions \(here 4\); use log_unnormalised"):
        density.log_pdf(jnp.ones(4))
    with pytest.raises(ValueError, match=r"moments by quadrature need ≤ 3 dimensions"):
        density.moments()


def test_noisy_chaplygin_sleigh_is_refused():
    """The sleigh's frictionless flow compresses phase volume (div = −(ma/J) v): no invariant measure."""

    def energy(x, p):
        return 0.5 * (p.mass * x[-2] ** 2 + (p.inertia + p.mass * p.offset**2) * x[-1] ** 2)

    for drift in (False, True):
        with pytest.raises(ValueError, match=r"invariant measure of the frictionless, noiseless flow fails"):
            stationary_density(ChaplyginSleigh(drift=drift).build(), energy)


def test_refusals_name_the_failing_condition():
    ball = BallOnVibratingPlane(drift=False)
    poisson = dataclasses.replace(ball.build(), noise=CompoundPoisson(law=NormalJumps(), intensity=1.0))
    with pytest.raises(
        ValueError, match=r"normal system \(Wiener noise\) fails: the system is driven by CompoundPoisson"
    ):
        stationary_density(poisson, lambda x, p: 0.5 * x @ x)

    cubic = system_of(lambda t, y, p: -2 * p.eps * (y + y**3), ("u",), ("velocity",))
    with pytest.raises(
        ValueError,
        match=r"friction proportional to bbᵀ \(S0 condition 1, a \+ aᵀ = 2bbᵀ\) fails: "
        r"the flux-balance α .* ranges over",
    ):
        stationary_density(cubic, lambda x, p: 0.5 * x @ x)

    def twisted(t, y, p):  # antisymmetric friction with a non-radial coefficient: α is constant, the flux is not
        rot = jnp.stack([-y[1], y[0]])
        return -2 * p.eps * (y + y[0] * rot)

    swirl = system_of(
        twisted,
        ("u", "w"),
        ("velocity", "velocity"),
        diffusion=lambda t, y, p: jnp.sqrt(p.nu) * jnp.eye(2, dtype=y.dtype),
    )
    with pytest.raises(ValueError, match=r"antisymmetric part must conserve N e\^\{−αH\}.*Fokker–Planck residual"):
        stationary_density(swirl, lambda x, p: 0.5 * x @ x)

    free = system_of(
        lambda t, y, p: jnp.stack([y[1], -2 * p.eps * y[1]]), ("q", "p"), ("independent_coordinate", "momentum")
    )
    with pytest.raises(ValueError, match=r"integrability ∫ N exp\(−αH\) < ∞ \(S0 condition 3\) fails"):
        stationary_density(free, lambda x, p: 0.5 * x[1] ** 2)

    spring = system_of(
        lambda t, y, p: jnp.stack([y[1], -y[0] - 2 * p.eps * y[1]]), ("x", "u"), ("dependent_coordinate", "velocity")
    )
    with pytest.raises(ValueError, match=r"Chaplygin decoupling fails"):
        stationary_density(spring, lambda x, p: 0.5 * x @ x)

    with pytest.raises(ValueError, match=r"H is a first integral .* fails"):
        stationary_density(conformal(), lambda x, p: 0.5 * x[1] ** 2)
    with pytest.raises(ValueError, match=r"friction='mu', noise='nu'"):
        stationary_density(ball.build(), lambda x, p: 0.5 * x @ x, friction="mu")


def test_the_default_quadrature_refines_until_the_integral_converges():
    """A 2-D Duffing oscillator's Gibbs density ∝ exp(−α(p²/2 + q²/2 + q⁴/4)), α = 4ε/ν: 96 nodes per dimension
    used to be refused ("did not converge"; 192 converge). Var p = 1/α exactly, Var q by an independent 1-D
    quadrature (scipy)."""
    import scipy.integrate

    eps, nu = 0.5, 1.0
    system = system_of(
        lambda t, y, p: jnp.stack([y[1], -y[0] - y[0] ** 3 - 2 * p.eps * y[1]]),
        ("q", "p"),
        ("independent_coordinate", "momentum"),
        eps=eps,
        nu=nu,
    )

    def hamiltonian(x, p):
        return x[1] ** 2 / 2 + x[0] ** 2 / 2 + x[0] ** 4 / 4

    with pytest.raises(ValueError, match="did not converge with quadrature_nodes=96"):
        stationary_density(system, hamiltonian, quadrature_nodes=96)  # a given number is checked, not refined
    density = stationary_density(system, hamiltonian)
    alpha = 4 * eps / nu
    weight = lambda q, j: q**j * np.exp(-alpha * (q**2 / 2 + q**4 / 4))
    var_q = (
        scipy.integrate.quad(weight, -np.inf, np.inf, args=(2,))[0]
        / scipy.integrate.quad(weight, -np.inf, np.inf, args=(0,))[0]
    )
    np.testing.assert_allclose(np.diag(np.asarray(density.cov)), [var_q, 1 / alpha], rtol=1e-9)
