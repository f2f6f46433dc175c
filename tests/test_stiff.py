"""Stiff friction: the exponential solver against Euler–Maruyama, with their exact amplification factors."""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane


def velocity_after(solver, eps, dt, steps, nu=0.0):
    scene = BallOnVibratingPlane(eps=eps, nu=nu, drift=False)
    ens = nhsde.simulate(
        scene.build(),
        jnp.array([1.0, -2.0], jnp.float64),
        jax.random.key(0),
        n_paths=64,
        t1=steps * dt,
        dt=dt,
        solver=solver,
        save=nhsde.Save(n=2, paths=True),
        on_failure="exclude",
    )
    return ens


@pytest.mark.parametrize("eps_dt", [0.1, 0.5, 0.9, 1.0, 1.1, 2.0, 10.0, 100.0])
def test_stability_region_against_euler_maruyama(eps_dt):
    """ν = 0: EM multiplies u by (1 − 2εh) per step (damped iff εh < 1: from the limit on, refused before the run);
    the exponential solver by e^{−2εh} at any step."""
    eps, steps = 100.0, 50
    dt = eps_dt / eps
    ex = velocity_after("exponential", eps, dt, steps)
    u0 = np.array([1.0, -2.0])
    np.testing.assert_allclose(ex.paths[0, -1], u0 * np.exp(-2 * eps_dt * steps), rtol=1e-9, atol=1e-300)
    if abs(1 - 2 * eps_dt) >= 1:
        with pytest.raises(ValueError, match="solver 'euler' is unstable"):
            velocity_after("euler", eps, dt, steps)
        return
    em = velocity_after("euler", eps, dt, steps)
    np.testing.assert_allclose(em.paths[0, -1], u0 * (1 - 2 * eps_dt) ** steps, rtol=1e-9)


def test_exponential_solver_bounded_at_eps_dt_100_where_em_diverges():
    eps, dt, nu = 1e4, 0.01, 1.0
    scene = BallOnVibratingPlane(eps=eps, nu=nu, drift=False)
    args: dict[str, Any] = dict(n_paths=4096, t1=1.0, dt=dt, save=nhsde.Save(n=2))
    with pytest.raises(ValueError, match="solver 'euler' is unstable"):
        nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(1), solver="euler", **args)
    ens = nhsde.simulate(
        scene.build(), scene.initial_state().astype(jnp.float64), jax.random.key(1), solver="exponential", **args
    )
    assert int(ens.n_failed) == 0
    # the exact stationary variance σ²/(4ε) at εh = 100: the step's noise has the linear flow's covariance
    # (nhsde._solvers; Euler–Maruyama's noise φ₁(Ah) b ΔW gave σ²(1 − e^{−2s})/(4ε²h(1 + e^{−2s})), s = εh, 1/200 of it)
    sigma2 = nu * float(scene.params.delta) ** 2
    expected = sigma2 * (1 - np.exp(-4 * eps * 1.0)) / (4 * eps)
    assert abs(float(ens.cov[-1, 0, 0]) - expected) <= 4 * float(ens.cov_se[-1, 0, 0])


def test_exponential_solver_converges_to_the_stationary_variance():
    """The step's noise has the covariance of the linear flow: the stationary variance σ²/(4ε) at any εh."""
    eps, nu = 50.0, 1.0
    sigma2 = nu * (1 / 1.4) ** 2
    # the ensemble at εh = 0.1 sits on the exact value within MC error
    scene = BallOnVibratingPlane(eps=eps, nu=nu, drift=False)
    ens = nhsde.simulate(
        scene.build(),
        scene.initial_state().astype(jnp.float64),
        jax.random.key(2),
        n_paths=8192,
        t1=0.5,
        dt=0.002,
        solver="exponential",
        save=nhsde.Save(n=2),
    )
    exact = sigma2 / (4 * eps)
    assert abs(float(ens.cov[-1, 0, 0]) - exact) <= 4 * float(ens.cov_se[-1, 0, 0])


def test_exponential_needs_a_linear_part():
    from nhsde import StateLayout, StochasticSystem

    system = StochasticSystem(
        drift_fn=lambda t, y, p: -y,
        diffusion_fn=lambda t, y, p: jnp.ones((1, 1), y.dtype),
        params=None,
        layout=StateLayout(("y",), ("independent_coordinate",)),
        noise_dim=1,
        additive_noise=True,
    )
    with pytest.raises(ValueError, match="linear drift part"):
        nhsde.simulate(system, jnp.zeros(1), jax.random.key(0), n_paths=8, t1=1.0, dt=0.1, solver="exponential")
