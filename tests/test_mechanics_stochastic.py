"""Spec-built stochastic systems: the ball rebuilt from its Lagrangian, and random parameters π (S0 (1.2))."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import pytest

import nhsde
from nhsde import AbstractParameters, mechanics as mech, parameter
from nhsde.scenes import (
    BallFromLagrangian,
    BallOnVibratingPlane,
    VerticalRollingDisk,
    ball_covariances,
)
from nhsde.statistics import drift_statistics

KEY = jax.random.key(12)
BALL: dict[str, Any] = {"eps": 0.8, "nu": 1.3, "radius": 0.6, "inertia_ratio": 0.4}


def _drift_statistics(system, y0, names, eps, nu):
    """``(m_q'', K_q'', K)`` at the save times, and the standard errors of ``K`` as aux."""
    ens = nhsde.simulate(
        system.replace_params(eps=eps, nu=nu), y0, KEY, n_paths=256, t1=1.0, dt=0.01, save=nhsde.Save(names=names, n=3)
    )
    stats = drift_statistics(ens)
    assert stats.names == ("x", "y")
    return (stats.systematic, stats.fluctuation, ens.cov), ens.cov_se


def test_ball_from_its_lagrangian_matches_the_hand_written_scene():
    """Same key, same noise channels (the plane's acceleration along x, y), same Euler recursion.

    The library's reduced equations for ``u = (r φ̇_y, −r φ̇_x)`` are
    ``u̇ = −2ε u + δ √ν V`` with the noise channels in the same order as the
    hand-written scene, so the drift statistics and their ε-, ν-derivatives agree
    to rounding, not merely within Monte-Carlo error.
    """
    eps, nu = jnp.asarray(BALL["eps"]), jnp.asarray(BALL["nu"])
    results = {}
    for label, scene, names in (
        ("hand", BallOnVibratingPlane(**BALL), ("x", "y", "u_x", "u_y")),
        ("spec", BallFromLagrangian(mass=2.0, **BALL), ("x", "y", "x_dot", "y_dot")),
    ):
        system, y0 = scene.build(), scene.initial_state().astype(jnp.float64)

        def statistics(e, n, system=system, y0=y0, names=names):
            out, se = _drift_statistics(system, y0, names, e, n)
            return out, (out, se)

        grads, (values, cov_se) = jax.jacfwd(statistics, argnums=(0, 1), has_aux=True)(eps, nu)
        results[label] = (values, grads, cov_se)
    (v_hand, g_hand, se), (v_ours, g_ours, _) = results["hand"], results["spec"]
    for a, b in zip(v_hand, v_ours):
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-13)
    for ga, gb in zip(jax.tree_util.tree_leaves(g_hand), jax.tree_util.tree_leaves(g_ours)):
        np.testing.assert_allclose(gb, ga, rtol=1e-9, atol=1e-12)
    d_fluct_d_eps = np.asarray(g_ours[0][1][-1])  # ∂K_q''/∂ε at t1
    assert np.max(np.abs(d_fluct_d_eps)) > 1e-3  # the fluctuation drift does move with ε
    # and both are the closed form S0 (3.1) within Monte-Carlo error
    k_xx, _, k_uu = ball_covariances(1.0, BALL["eps"], BALL["nu"], 1 / 1.4)
    cov = np.asarray(v_ours[2][-1])
    assert abs(cov[0, 0] - float(k_xx)) < 4 * float(se[-1, 0, 0])
    assert abs(cov[2, 2] - float(k_uu)) < 4 * float(se[-1, 2, 2])


def test_additive_noise_is_recognised():
    """The ball's b does not depend on the state (additive-only solvers apply); the disk's does (B'(φ))."""
    ball = BallFromLagrangian()
    assert ball.build().additive_noise
    assert mech.build(ball.spec(), "multipliers", dependent=("x", "y")).additive_noise
    assert not mech.build(VerticalRollingDisk().spec(), "reduced", dependent=("x", "y")).additive_noise


# --------------------------------------------------------------------------- random parameters π


class ColouredParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.5, lower=0.0)
    nu: jnp.ndarray = parameter(default=0.8, lower=0.0)
    alpha: jnp.ndarray = parameter(default=2.0, lower=0.0, strict=True, doc="filter rate α")
    kappa: jnp.ndarray = parameter(default=0.4, lower=0.0)
    radius: jnp.ndarray = parameter(default=0.6, lower=0.0, strict=True)


def _ball_kinetic(q, v, pi, t, p):
    return 0.5 * (v[0] ** 2 + v[1] ** 2) + 0.5 * p.kappa * p.radius**2 * v[2:] @ v[2:]


def _rolling(q, pi, t, p):
    one, zero, r = jnp.ones((), q.dtype), jnp.zeros((), q.dtype), p.radius
    return jnp.stack([jnp.stack([one, zero, zero, -r, zero]), jnp.stack([zero, one, r, zero, zero])])


def _friction(q, v, pi, t, p):
    return p.eps * (1 + p.kappa) * (v[0] ** 2 + v[1] ** 2)


def _inertial_force(q, v, pi, t, p):
    """The plane's coloured acceleration π acts on the centre (unit mass)."""
    return jnp.concatenate([pi, jnp.zeros(3, q.dtype)])


def _filter_drift(pi, t, p):
    return -p.alpha * pi


def _filter_diffusion(pi, t, p):
    return nhsde.sqrt_intensity(p.nu) * jnp.eye(2, dtype=pi.dtype)


def coloured_ball_spec(**kw):
    return mech.MechanicalSpec(
        coordinates=("x", "y", "phi_x", "phi_y", "phi_z"),
        params=ColouredParameters(**kw),
        kinetic_energy=_ball_kinetic,
        constraints=_rolling,
        dissipation=_friction,
        force=_inertial_force,
        random_parameters=("pi_x", "pi_y"),
        random_drift=_filter_drift,
        random_diffusion=_filter_diffusion,
    )


def test_random_parameters_shaping_filter_closed_form():
    """π̇ = −απ + √ν V, u̇ = −2εu + δπ, ẋ = u: the covariance of (π_x, u_x, x) is ∫ e^{As} BBᵀ e^{Aᵀs} ds (Van Loan)."""
    spec = coloured_ball_spec()
    p = spec.params
    form = mech.formulate(spec, "reduced", dependent=("x", "y"))
    system = form.system()
    assert system.layout.names[:2] == ("pi_x", "pi_y") and system.layout.roles[0] == "random_parameter"
    y0 = form.state(jnp.zeros(5), jnp.zeros(5), pi=jnp.zeros(2))
    t1 = 2.0
    ens = nhsde.simulate(
        system, y0, KEY, n_paths=2048, t1=t1, dt=0.002, save=nhsde.Save(names=("pi_x", "x_dot", "x"), n=3)
    )
    delta = 1 / (1 + float(p.kappa))
    a = np.array([[-float(p.alpha), 0, 0], [delta, -2 * float(p.eps), 0], [0, 1, 0]])
    bb = np.diag([float(p.nu), 0.0, 0.0])
    block = jsl.expm(jnp.asarray(np.block([[-a, bb], [np.zeros((3, 3)), a.T]]) * t1))
    exact = np.asarray(block[3:, 3:]).T @ np.asarray(block[:3, 3:])
    err = np.abs(np.asarray(ens.cov[-1]) - exact) / np.asarray(ens.cov_se[-1])
    print("coloured ball: |K − exact| in standard errors:\n", np.round(err, 2))
    assert np.all(err < 4)
    assert exact[2, 2] > 10 * float(ens.cov_se[-1, 2, 2])  # far from zero in standard errors: the test can fail


def test_random_parameters_in_independent_routes():
    spec = coloured_ball_spec()
    k = jax.random.split(jax.random.key(2), 3)
    q, pi, raw = jax.random.normal(k[0], (5,)), jax.random.normal(k[1], (2,)), jax.random.normal(k[2], (5,))
    v = mech.project_velocity(spec, q, raw, pi=pi)
    accs = [
        eqx.filter_jit(mech.formulate(spec, r, dependent=("x", "y")).accelerations)(q, v, pi=pi)
        for r in ("reduced", "gauss")
    ]
    for acc in accs[1:]:
        np.testing.assert_allclose(acc, accs[0], rtol=1e-12, atol=1e-13)
    drift = mech.build(spec, "reduced", dependent=("x", "y")).drift(0.0, jnp.concatenate([pi, q, v[2:]]), spec.params)
    np.testing.assert_allclose(drift[:2], -spec.params.alpha * pi)  # φ(π) heads the state, S0 (1.15)


def test_random_parameters_in_the_kinetic_energy_are_refused():
    def kinetic(q, v, pi, t, p):
        return 0.5 * (1 + pi[0] ** 2) * v @ v

    with pytest.raises(ValueError, match="Δσ"):
        mech.MechanicalSpec(
            coordinates=("x", "y"),
            params=ColouredParameters(),
            kinetic_energy=kinetic,
            random_parameters=("pi",),
            random_drift=lambda pi, t, p: -pi,
        )
    with pytest.raises(ValueError, match="constraints depends on the random parameters"):
        mech.MechanicalSpec(
            coordinates=("x", "y"),
            params=ColouredParameters(),
            kinetic_energy=lambda q, v, pi, t, p: 0.5 * v @ v,
            constraints=lambda q, pi, t, p: jnp.stack([jnp.ones(()), pi[0]])[None, :],
            random_parameters=("pi",),
            random_drift=lambda pi, t, p: -pi,
        )
