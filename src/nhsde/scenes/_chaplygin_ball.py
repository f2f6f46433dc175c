"""Chaplygin's balanced ball rolling (classic, no slip) on a rough plane, under a random couple.

A ball of radius ``R``, mass ``m``, centre of mass at its centre and principal
moments ``I = diag(I₁, I₂, I₃)`` rolls without slipping on a horizontal plane.
With ``M = Ĩω`` its angular momentum about the contact point,
``Ĩ = I + D(E − γ⊗γ)``, ``D = mR²``, the rolling equations (S2 (1.4) with
``r = −Rγ``) become Chaplygin's

    Ṁ = M × ω + K,   γ̇ = γ × ω,   ω = A M + D (γ, A M)/(1 − D(γ, Aγ)) · Aγ,   A = (I + D E)⁻¹,

with first integrals ``(M, M)``, ``(M, γ)``, ``H = ½(M, ω)`` and the invariant
measure ``(1 − D(γ, Aγ))^{−1/2} dM dγ`` when ``K = 0``.  Here ``K`` is an external
couple: a viscous rolling resistance ``−2εω`` and a random isotropic couple
``√ν V`` (``V`` standard white noise in the body axes).  Friction is
``a ∂H/∂M`` with ``a = E`` and the noise matrix is ``b = E`` in S0 Statement 2's
form, so the stationary density is

    f = c (1 − D(γ, Aγ))^{−1/2} exp(−αH),   α = 4ε/ν,

from the flux balance ``−2εω f − ½ν ∂f/∂M = 0``.  Integrating over ``M``: ``γ``
is uniform on the sphere and ``E[H] = 3/(2α) = 3ν/(8ε)``.  The noise does not
depend on the state (additive), the drift is nonlinear.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from .._system import StateLayout, StochasticSystem
from ..bodies import position_rates
from ..mechanics._small import matmul
from ._base import AbstractScene

__all__ = ["ChaplyginBall", "ChaplyginBallParameters", "chaplygin_ball_measure", "chaplygin_ball_omega"]


class ChaplyginBallParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="rolling resistance ε: couple −2εω")
    nu: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="intensity ν of the random couple, per axis")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="radius R")
    inertia_1: jnp.ndarray = parameter(default=0.3, lower=0.0, strict=True, doc="principal moment I₁")
    inertia_2: jnp.ndarray = parameter(default=0.4, lower=0.0, strict=True, doc="principal moment I₂")
    inertia_3: jnp.ndarray = parameter(default=0.5, lower=0.0, strict=True, doc="principal moment I₃")

    @property
    def inertia(self):
        return jnp.stack([self.inertia_1, self.inertia_2, self.inertia_3])


def chaplygin_ball_omega(m_vec, gamma, p: ChaplyginBallParameters):
    """``ω = Ĩ⁻¹M = AM + D(γ, AM)/(1 − D(γ, Aγ)) Aγ`` (Sherman–Morrison), ``A = (I + DE)⁻¹``."""
    d = p.mass * p.radius**2
    a = 1.0 / (p.inertia + d)
    am, ag = a * m_vec, a * gamma
    return am + d * matmul(gamma, am) / (1 - d * matmul(gamma, ag)) * ag


def chaplygin_ball_measure(y, p: ChaplyginBallParameters):
    """``(1 − D(γ, Aγ))^{−1/2}``: the invariant measure in ``(M, γ)``."""
    d = p.mass * p.radius**2
    gamma = y[3:6] / jnp.linalg.norm(y[3:6])
    return (1 - d * matmul(gamma, gamma / (p.inertia + d))) ** -0.5


def _energy(t, y, p):
    gamma = y[3:6] / jnp.linalg.norm(y[3:6])
    return 0.5 * matmul(y[:3], chaplygin_ball_omega(y[:3], gamma, p))


def _drift(t, y, p):
    m_vec, gamma = y[:3], y[3:6]
    omega = chaplygin_ball_omega(m_vec, gamma / jnp.linalg.norm(gamma), p)
    parts = [jnp.cross(m_vec, omega) - 2 * p.eps * omega, jnp.cross(gamma, omega)]
    if y.shape[0] > 6:  # the contact point r = −Rγ moves with ṙ = −R γ̇
        n = gamma / jnp.linalg.norm(gamma)
        parts.append(position_rates(y[6:9], omega, n, -p.radius * jnp.cross(n, omega)))
    return jnp.concatenate(parts)


def _diffusion(t, y, p):
    noise = sqrt_intensity(p.nu) * jnp.eye(3, dtype=y.dtype)
    return jnp.concatenate([noise, jnp.zeros((y.shape[0] - 3, 3), y.dtype)])


class ChaplyginBall(AbstractScene):
    """Chaplygin's balanced ball on a rough plane under a random couple and rolling resistance.

    State ``(M, γ)`` (angular momentum about the contact point, upward vertical in
    the body axes); ``drift=True`` adds the horizontal axis ``α`` and the contact
    point ``(x, y)``.  Additive noise; observable ``energy`` ``H = ½(M, ω)``.

    Arguments:
        drift: keep ``α`` and the contact point ``(x, y)`` in the state.
        **params: the :class:`ChaplyginBallParameters`.
    """

    name: ClassVar[str] = "chaplygin-ball"
    Parameters: ClassVar[type[ChaplyginBallParameters]] = ChaplyginBallParameters

    params: ChaplyginBallParameters
    drift: bool = eqx.field(static=True)

    def __init__(self, *, drift: bool = False, **params):
        self.params = ChaplyginBallParameters(**params)
        self.drift = bool(drift)

    def build(self) -> StochasticSystem:
        names = ("M_1", "M_2", "M_3", "gamma_1", "gamma_2", "gamma_3")
        roles = ("momentum",) * 3 + ("independent_coordinate",) * 3
        if self.drift:
            names += ("alpha_1", "alpha_2", "alpha_3", "x", "y")
            roles += ("independent_coordinate",) * 3 + ("dependent_coordinate",) * 2
        return StochasticSystem(
            drift_fn=_drift,
            diffusion_fn=_diffusion,
            params=self.params,
            layout=StateLayout(names, roles),
            noise_dim=3,
            additive_noise=True,
            observables=(("energy", _energy),),
        )

    def initial_state(self):
        """At rest, ``e₃`` up, ``e₁`` along ``OX``, contact point at the origin."""
        y = jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        if self.drift:
            y = jnp.concatenate([y, jnp.array([1.0, 0.0, 0.0, 0.0, 0.0])])
        return y
