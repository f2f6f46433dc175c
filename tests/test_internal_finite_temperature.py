"""Internals of the finite-temperature models: the stability limit on the contact viscosity, the PSD factor."""

import jax
import jax.numpy as jnp
import numpy as np

from nhsde._simulate import stable_step
from nhsde.mechanics._small import psd_factor
from nhsde.scenes import ChaplyginSleighInBath


def test_euler_limit_is_the_contact_rate():
    """Euler–Maruyama is stable on the soft knife exactly while ``λ dt < 2``, ``λ`` the fastest damping rate,
    here the largest eigenvalue of ``M⁻¹ diag(2εm, γ, 2εJ)`` in ``(v, w, ω)``: ``≈ γ (1/m + a²/I) = 2000``."""
    eps, gamma, m, i, a = 0.5, 1000.0, 1.0, 1.0, 1.0
    j = i + m * a**2
    mass = np.array([[m, 0, 0], [0, m, m * a], [0, m * a, j]])
    rate = np.max(np.linalg.eigvals(np.linalg.solve(mass, np.diag([2 * eps * m, gamma, 2 * eps * j]))).real)
    system = ChaplyginSleighInBath(model="soft", drift=False, gamma=gamma, eps=eps).build()
    assert stable_step(system, "euler", 0.999 * 2 / rate)
    assert not stable_step(system, "euler", 1.001 * 2 / rate)


def test_psd_factor_of_singular_friction():
    """``L Lᵀ = C`` for a positive semidefinite ``C`` of rank 2 (the sleigh's ``∂²R/∂q̇²``), at every heading,
    including where a pivot vanishes (``cos θ = 0``)."""
    for theta in (0.0, 0.3, np.pi / 2, 2.0, np.pi):
        e1 = np.array([np.cos(theta), np.sin(theta), 0.0])
        c = 2 * 0.5 * (np.outer(e1, e1) + 2.0 * np.diag([0.0, 0.0, 1.0]))
        low = np.asarray(psd_factor(jnp.asarray(c)))
        assert np.all(np.isfinite(low)) and np.allclose(np.tril(low), low)
        np.testing.assert_allclose(low @ low.T, c, atol=1e-14)
    assert np.allclose(jax.jacfwd(lambda x: psd_factor(jnp.diag(jnp.stack([x, x]))))(jnp.asarray(4.0)).sum(), 0.5)
