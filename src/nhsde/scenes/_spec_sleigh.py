"""The Chaplygin sleigh built from its Lagrangian (conventions of :mod:`._sleigh`).

Coordinates ``(x, y, θ)`` of the knife point ``P``, the centre of mass a distance
``a`` ahead of it along ``e₁ = (cos θ, sin θ)``:
``T = ½ m |Ṗ + a θ̇ e₂|² + ½ I θ̇²``, knife constraint ``−sin θ ẋ + cos θ ẏ = 0``.
Friction ``R = ε (m v² + J θ̇²)`` with ``v = e₁·Ṗ`` and ``J = I + m a²``; a random
force ``√(m ν) V₁`` along the knife at ``P`` and torque ``√(J ν) V₂``.  This gives
the hand-written scene's equations.  The Voronets choice ``ẏ = tan θ ẋ`` is
singular at ``cos θ = 0``, so the default route keeps all velocities.

Like :class:`~nhsde.scenes.ChaplyginSleigh` this is the *naive thermal* model, noise on the friction but not on the
knife's reaction, which drifts forward at finite temperature (Jagla, Bloch & Rojo, arXiv 2603.14424); the spec
route's consistent one declares the knife a :class:`~nhsde.mechanics.SoftConstraint` with a ``temperature``.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import sqrt_intensity
from ._sleigh import SleighParameters
from ._spec_scene import AbstractSpecScene

__all__ = ["ChaplyginSleighFromSpec"]


def _kinetic(q, v, pi, t, p):
    s, c = jnp.sin(q[2]), jnp.cos(q[2])
    vx, vy = v[0] - p.offset * s * v[2], v[1] + p.offset * c * v[2]
    return 0.5 * p.mass * (vx**2 + vy**2) + 0.5 * p.inertia * v[2] ** 2


def _knife(q, pi, t, p):
    return jnp.stack([-jnp.sin(q[2]), jnp.cos(q[2]), jnp.zeros((), q.dtype)])[None, :]


def _dissipation(q, v, pi, t, p):
    speed = jnp.cos(q[2]) * v[0] + jnp.sin(q[2]) * v[1]
    return p.eps * (p.mass * speed**2 + (p.inertia + p.mass * p.offset**2) * v[2] ** 2)


def _force_and_torque(q, v, pi, t, p):
    zero = jnp.zeros((), q.dtype)
    f, tau = jnp.sqrt(p.mass), jnp.sqrt(p.inertia + p.mass * p.offset**2)
    return sqrt_intensity(p.nu) * jnp.stack(
        [jnp.stack([f * jnp.cos(q[2]), zero]), jnp.stack([f * jnp.sin(q[2]), zero]), jnp.stack([zero, tau])]
    )


class ChaplyginSleighFromSpec(AbstractSpecScene):
    """Chaplygin sleigh with friction and random force/torque, from its Lagrangian (the naive thermal model)."""

    name: ClassVar[str] = "chaplygin-sleigh-from-spec"
    Parameters: ClassVar[type[SleighParameters]] = SleighParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y", "theta")
    terms: ClassVar[dict] = dict(
        kinetic_energy=_kinetic, constraints=_knife, dissipation=_dissipation, noise_force=_force_and_torque
    )
    dependent: ClassVar[tuple[str, ...]] = ("y",)
    angles: ClassVar[tuple[str, ...]] = ("theta",)

    params: SleighParameters
    route: str = eqx.field(static=True)

    def __init__(self, *, route: str = "multipliers", **params):
        self.params, self.route = SleighParameters(**params), route

    def configuration(self):
        """Moving straight ahead at unit speed from the origin."""
        return jnp.zeros(3), jnp.array([1.0, 0.0, 0.0])
