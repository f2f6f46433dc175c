"""Vertical rolling disk, built from its Lagrangian by :mod:`nhsde.mechanics`.

Coordinates ``(x, y, θ, φ)``: contact point, rolling angle, heading.
``T = ½ m (ẋ² + ẏ²) + ½ I θ̇² + ½ J φ̇²``; rolling without slipping
``ẋ = R cos φ θ̇``, ``ẏ = R sin φ θ̇``.  Without friction and noise ``θ̇ = Ω_θ``,
``φ̇ = Ω_φ`` are constant, the contact point runs on a circle of radius
``R Ω_θ/Ω_φ``, and the multipliers (reactions ``aᵀλ``) are
``λ = m Ω_φ R Ω_θ (−sin φ, cos φ)``.  Friction ``R = ε (m (ẋ² + ẏ²) + I θ̇² + J φ̇²)``
and random torques ``√ν (√(I + mR²) V₁, √J V₂)`` on the rolling and the turning.

Read as a bath of temperature ``kT = ν/(4ε)`` this is the *naive thermal* model (noise on the friction, not on the
contact's reaction; Jagla, Bloch & Rojo, arXiv 2603.14424).  For this disk it is Gibbs conditioned on no slip, and the
model with a viscous contact and its own noise is :class:`~nhsde.scenes.VerticalRollingDiskInBath`.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ._spec_scene import AbstractSpecScene

__all__ = ["DiskParameters", "VerticalRollingDisk"]


class DiskParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.1, lower=0.0, doc="friction ε, 1/s")
    nu: jnp.ndarray = parameter(default=0.1, lower=0.0, doc="intensity ν of the random torques")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="radius R")
    roll_inertia: jnp.ndarray = parameter(default=0.5, lower=0.0, strict=True, doc="moment of inertia I about the axle")
    turn_inertia: jnp.ndarray = parameter(
        default=0.25, lower=0.0, strict=True, doc="moment of inertia J about the vertical"
    )


def _kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * (v[0] ** 2 + v[1] ** 2) + 0.5 * p.roll_inertia * v[2] ** 2 + 0.5 * p.turn_inertia * v[3] ** 2


def _rolling(q, pi, t, p):
    one, zero = jnp.ones((), q.dtype), jnp.zeros((), q.dtype)
    c, s = p.radius * jnp.cos(q[3]), p.radius * jnp.sin(q[3])
    return jnp.stack([jnp.stack([one, zero, -c, zero]), jnp.stack([zero, one, -s, zero])])


def _dissipation(q, v, pi, t, p):
    return p.eps * (p.mass * (v[0] ** 2 + v[1] ** 2) + p.roll_inertia * v[2] ** 2 + p.turn_inertia * v[3] ** 2)


def _torques(q, v, pi, t, p):
    zero = jnp.zeros((), q.dtype)
    roll = jnp.sqrt(p.roll_inertia + p.mass * p.radius**2)
    return sqrt_intensity(p.nu) * jnp.stack(
        [
            jnp.stack([zero, zero]),
            jnp.stack([zero, zero]),
            jnp.stack([roll, zero]),
            jnp.stack([zero, jnp.sqrt(p.turn_inertia)]),
        ]
    )


class VerticalRollingDisk(AbstractSpecScene):
    """Vertical disk rolling on a plane (Voronets form in (θ̇, φ̇); contact point drifts)."""

    name: ClassVar[str] = "vertical-rolling-disk"
    Parameters: ClassVar[type[DiskParameters]] = DiskParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y", "theta", "phi")
    terms: ClassVar[dict] = dict(
        kinetic_energy=_kinetic, constraints=_rolling, dissipation=_dissipation, noise_force=_torques
    )
    dependent: ClassVar[tuple[str, ...]] = ("x", "y")
    angles: ClassVar[tuple[str, ...]] = ("phi",)

    params: DiskParameters
    route: str = eqx.field(static=True)

    def __init__(self, *, route: str = "reduced", **params):
        self.params, self.route = DiskParameters(**params), route

    def configuration(self):
        """At the origin, heading along x, rolling at ``θ̇ = 1`` and turning at ``φ̇ = 0.5``."""
        q = jnp.zeros(4)
        return q, jnp.stack([self.params.radius, jnp.zeros(()), jnp.ones(()), jnp.full((), 0.5)]).astype(q.dtype)
