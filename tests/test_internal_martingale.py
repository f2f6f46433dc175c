"""The martingale controls themselves (private ``martingale_system``): mean exactly zero for the discretisation.

Each control ``M_k = Σₙ ψ_k(tₙ, Xₙ)·ΔWₙ`` (Euler) or its weak-scheme analogue (three-point increments, with the
centred ``ΔŴ² − h`` and ``ΔŴʳΔŴʲ + V_rj`` terms) has mean zero given the past at every step, whatever ``ψ``.  On
2¹⁶ paths of the (nonlinear) Chaplygin sleigh, every raw control of a deliberately poor basis and of the quadratic
basis has a sample mean within 4.5 SE of zero (a Bonferroni-safe bound over the ≤ 40 controls: each |z| > 4.5 has
probability 7·10⁻⁶).  The system's own components are those of a plain solve with the same key (to rounding).
"""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import ChaplyginSleigh
from nhsde.statistics._martingale import fitted_system, martingale_system

SCENE = ChaplyginSleigh(eps=0.3, nu=1.0)
N = 2**16


def _poor(t, x, params):
    """Unrelated to the sleigh's value functions: oscillating in heading and speed, one row per channel."""
    return jnp.stack([jnp.sin(3.0 * x[2] + 5.0 * t) * x[3:5], jnp.cos(4.0 * x[3] * x[4]) * jnp.ones(2, x.dtype)])


@pytest.mark.parametrize(("solver", "basis"), [("euler", "poor"), ("weak2", "poor"), ("weak2", "quadratic")])
def test_every_raw_control_has_mean_zero(solver, basis):
    system = SCENE.build()
    y0 = SCENE.initial_state()
    augmented = martingale_system(system, y0, _poor if basis == "poor" else basis, time_degree=1, t1=1.0)
    size = augmented.state_dim - system.state_dim
    start = jnp.concatenate([y0, jnp.zeros(size, y0.dtype)])
    ens = nhsde.simulate(augmented, start, jax.random.key(3), n_paths=N, t1=1.0, dt=0.125, solver=solver)
    mean, se = np.asarray(ens.mean[-1, system.state_dim :]), np.asarray(ens.mean_se[-1, system.state_dim :])
    assert np.all(se > 0)
    z = mean / se
    assert np.all(np.abs(z) <= 4.5), z
    plain = nhsde.simulate(system, y0, jax.random.key(3), n_paths=N, t1=1.0, dt=0.125, solver=solver)
    # the same paths: equal up to the rounding of the mean's reduction over a wider state
    np.testing.assert_allclose(
        np.asarray(ens.mean[:, : system.state_dim]), np.asarray(plain.mean), rtol=1e-12, atol=1e-15
    )


@pytest.mark.parametrize(("solver", "basis"), [("weak2", "cubic"), ("euler", "poor")])
def test_the_fitted_combinations_are_those_of_the_controls_on_the_same_paths(solver, basis):
    """The main run's ``R`` fitted combinations ``M̃_r`` (:func:`fitted_system`, the polynomial form of the monomial
    basis or the callable's rows) equal ``β_r·M`` of the ``K`` controls on the same paths, to rounding."""
    system, y0 = SCENE.build(), SCENE.initial_state()
    augmented = martingale_system(system, y0, _poor if basis == "poor" else basis, time_degree=2, t1=1.0)
    d, size = system.state_dim, augmented.state_dim - system.state_dim
    beta = jnp.asarray(np.random.default_rng(0).normal(size=(3, size)))
    fitted = fitted_system(augmented, d, beta)
    args: dict[str, Any] = dict(n_paths=64, t1=1.0, dt=0.125, solver=solver)
    full = nhsde.simulate(augmented, jnp.concatenate([y0, jnp.zeros(size)]), jax.random.key(4), **args)
    few = nhsde.simulate(fitted, jnp.concatenate([y0, jnp.zeros(3)]), jax.random.key(4), **args)
    m, combined = np.asarray(full.mean[:, d:]), np.asarray(few.mean[:, d:])
    np.testing.assert_allclose(combined, m @ np.asarray(beta).T, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(few.mean[:, :d]), np.asarray(full.mean[:, :d]), rtol=1e-12, atol=1e-15)
