"""Shaping filters (S0 (1.2)): coloured noise in the state only when asked, Wong–Zakai limit, closed forms."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import StateLayout, StochasticSystem
from nhsde.noise import OrnsteinUhlenbeck, ShapingFilter, with_shaping_filter
from nhsde.scenes import BallOnVibratingPlane
from nhsde.statistics import normal_approximation, stationary_drift


def gbm(mu=0.3, sigma=0.8, interpretation="ito"):
    """dX = μX dt + σX dW."""
    return StochasticSystem(
        drift_fn=lambda t, y, p: p["mu"] * y,
        diffusion_fn=lambda t, y, p: p["sigma"] * y[:, None],
        params={"mu": jnp.float64(mu), "sigma": jnp.float64(sigma)},
        layout=StateLayout(("x",), ("independent_coordinate",)),
        noise_dim=1,
        interpretation=interpretation,
    )


def stationary_start(n, variance, rest, seed=0):
    pi = np.random.default_rng(seed).normal(scale=math.sqrt(variance), size=(n, 1))
    return jnp.asarray(np.concatenate([pi, np.broadcast_to(rest, (n, len(rest)))], axis=1))


def test_coloured_multiplicative_noise_has_the_closed_form_mean_and_the_white_limit():
    """X driven by OU noise (rate γ, unit intensity, stationary start) through the Stratonovich drift:
    ln X = (μ − σ²/2)t + σ∫π, so E X(t) = exp(μt − σ²(1 − e^{−γt})/(2γ)) → e^{μt} (the Itô system) as γ → ∞."""
    mu, sigma, gamma, t1, n = 0.3, 0.8, 5.0, 1.0, 8192
    system = with_shaping_filter(gbm(mu, sigma), OrnsteinUhlenbeck(("pi",), rate=gamma))
    assert system.layout.names == ("pi", "x") and system.additive_noise
    y0 = stationary_start(n, gamma / 2, [1.0])
    ens = nhsde.simulate(
        system, y0, jax.random.key(0), n_paths=n, t1=t1, dt=2.0**-8, solver="sra1", save=nhsde.Save(names=("x",), n=2)
    )
    exact = math.exp(mu * t1 - sigma**2 * (1 - math.exp(-gamma * t1)) / (2 * gamma))
    assert abs(float(ens.mean[-1, 0]) - exact) <= 4 * float(ens.mean_se[-1, 0])
    # the coloured mean differs from the white one by more than the error here, and the gap closes as γ grows
    white = math.exp(mu * t1)
    assert abs(exact - white) > 4 * float(ens.mean_se[-1, 0])
    assert abs(math.exp(mu * t1 - sigma**2 * (1 - math.exp(-1e3 * t1)) / 2e3) - white) < 1e-3


def test_coloured_vibration_of_the_ball():
    """u̇ = −2εu + √ν δ π, π OU of unit intensity: Var u = νδ²/(4ε)·γ/(2ε + γ); effective diffusion νδ²/(8ε²)
    unchanged (same low-frequency intensity).  The moment equations (exact: the system is linear) give both to 1e-10."""
    eps, nu, gamma = 1.0, 1.0, 3.0
    scene = BallOnVibratingPlane(eps=eps, nu=nu, angular_velocity=True)
    system = with_shaping_filter(scene.build(), OrnsteinUhlenbeck(("pi_x", "pi_y"), rate=gamma))
    assert system.layout.names == ("pi_x", "pi_y", "x", "y", "u_x", "u_y")
    assert system.layout.roles[:2] == ("random_parameter", "random_parameter")
    assert scene.build().layout.names == ("x", "y", "u_x", "u_y")  # filter states only when asked
    g = nu * float(scene.params.delta) ** 2
    var_u = g / (4 * eps) * gamma / (2 * eps + gamma)
    y0 = jnp.zeros(6)
    cov0 = jnp.diag(jnp.array([gamma / 2, gamma / 2, 0, 0, 0, 0]))
    stat = stationary_drift(system, y0, cov0, t_relax=10.0, dt=0.01)
    np.testing.assert_allclose(jnp.diagonal(stat.moments.cov)[2:], [var_u, var_u], rtol=1e-10)
    np.testing.assert_allclose(stat.diffusion, g / (8 * eps**2) * np.eye(2), rtol=1e-10, atol=1e-14)

    # the observable ω_y = u_x/r reads the system's state inside the filtered one
    y = jnp.arange(6.0)
    np.testing.assert_allclose(system.observe(("omega_y",))(0.0, y, system.params), [4.0 / float(scene.params.radius)])
    # parameters reach the system and the filter by name
    changed = system.replace_params(eps=2.0, rate=4.0)
    assert float(changed.params.system.eps) == 2.0 and float(changed.params.filter.rate) == 4.0


def test_general_filter_and_its_moments():
    """A general φ, ψ: the filter alone, π̇ = −γπ + σ V as a ShapingFilter, has the OU moments."""
    filt = ShapingFilter(
        lambda t, pi, p: -p["rate"] * pi,
        lambda t, pi, p: p["scale"] * jnp.eye(1, dtype=pi.dtype),
        {"rate": jnp.float64(2.0), "scale": jnp.float64(1.5)},
        ("pi",),
        1,
        additive_noise=True,
    )
    carrier = StochasticSystem(  # ẋ = π: the position driven by the coloured noise
        drift_fn=lambda t, y, p: jnp.zeros_like(y),
        diffusion_fn=lambda t, y, p: jnp.ones((1, 1), y.dtype),
        params={},
        layout=StateLayout(("x",), ("dependent_coordinate",)),
        noise_dim=1,
        additive_noise=True,
    )
    system = with_shaping_filter(carrier, filt)
    ens = normal_approximation(system, jnp.zeros(2), t1=2.0, dt=0.01, save=nhsde.Save(n=3))
    # Var π(t) = σ²(1 − e^{−2γt})/(2γ); Var x(t) = σ²/γ² [t − 2(1 − e^{−γt})/γ + (1 − e^{−2γt})/(2γ)]
    t = np.asarray(ens.ts)
    var_pi = 1.5**2 * (1 - np.exp(-4 * t)) / 4
    var_x = 1.5**2 / 4 * (t - 2 * (1 - np.exp(-2 * t)) / 2 + (1 - np.exp(-4 * t)) / 4)
    np.testing.assert_allclose(ens.cov[:, 0, 0], var_pi, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(ens.cov[:, 1, 1], var_x, rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize(
    "make, exc, match",
    [
        (lambda: OrnsteinUhlenbeck("pi"), ValueError, r"names='pi'; expected a non-empty tuple"),
        (lambda: OrnsteinUhlenbeck(("pi",), rate=0.0), ValueError, r"rate=0.0 .*> 0"),
        (lambda: OrnsteinUhlenbeck(("pi",), intensity=-1.0), ValueError, r"intensity=-1.0 .*≥ 0"),
        (
            lambda: with_shaping_filter(gbm(), OrnsteinUhlenbeck(("a", "b"))),
            ValueError,
            r"filter has 2 outputs \('a', 'b'\) but the system has 1 noise channels",
        ),
        (lambda: with_shaping_filter(gbm(), OrnsteinUhlenbeck(("x",))), ValueError, r"clash"),
        (lambda: with_shaping_filter(gbm(), "ou"), TypeError, r"expected a shaping filter"),
    ],
)
def test_bad_filters_are_refused(make, exc, match):
    with pytest.raises(exc, match=match):
        make()
