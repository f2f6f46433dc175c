"""Itô ↔ Stratonovich (S0 §2, Remark): every solver converges to the solution in the calculus the system declares."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import StateLayout, StochasticSystem


def gbm_stratonovich(mu=0.3, sigma=0.8):
    """dX = μX dt + σX ∘ dW: X = e^{μt + σW}, E X(t) = e^{(μ + σ²/2)t} (Itô: e^{μt})."""
    return StochasticSystem(
        drift_fn=lambda t, y, p: p["mu"] * y,
        diffusion_fn=lambda t, y, p: p["sigma"] * y[:, None],
        params={"mu": jnp.float64(mu), "sigma": jnp.float64(sigma)},
        layout=StateLayout(("x",), ("independent_coordinate",)),
        noise_dim=1,
        interpretation="stratonovich",
    )


@pytest.mark.parametrize("solver", ["euler", "heun"])
def test_stratonovich_system_converges_to_the_stratonovich_solution(solver):
    """Euler (Itô) gets the system converted by the ½(∂b/∂Z)b drift correction; Heun (Stratonovich) takes it as is."""
    ens = nhsde.simulate(
        gbm_stratonovich(), jnp.array([1.0]), jax.random.key(6), n_paths=4096, t1=1.0, dt=2.0**-8, solver=solver
    )
    exact, ito = np.exp(0.3 + 0.32), np.exp(0.3)
    err = abs(float(ens.mean[-1, 0]) - exact)
    assert err <= 4 * float(ens.mean_se[-1, 0]), (solver, float(ens.mean[-1, 0]), exact)
    assert abs(exact - ito) > 10 * float(ens.mean_se[-1, 0])  # the two calculi are told apart
    converted = gbm_stratonovich().converted("ito")
    np.testing.assert_allclose(converted.drift(0.0, jnp.array([2.0]), converted.params), [(0.3 + 0.32) * 2.0])
