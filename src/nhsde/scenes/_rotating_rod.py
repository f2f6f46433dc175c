"""A bead on a rod turned by a control: a parametric constraint (S1 (1.1), (2.3)–(2.6)).

A bead of mass ``m`` moves in a horizontal plane, ``q = (x, y)``, on a rod through
the origin at the controlled angle ``u(t) = Ω t + A sin(w t)``:
``f = −x sin u + y cos u = 0``.  Its rate ``u̇`` enters the velocity constraint and
``ü`` the accelerations (S1 (1.4)–(1.5), (2.4)); the reaction ``λ ∇f`` works on the
real motion, ``dT = λ ∇f·dq`` (S1 (2.5)–(2.6)), so the energy follows the control.
Without friction the reaction is ``λ = m (2 ṙ u̇ + r ü)``.  Friction along the rod
``R = ε m ṙ²`` and a random force ``√(m ν) V`` along it (``ṙ = e_u·q̇``, ``e_u = (cos u, sin u)``).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ._spec_scene import AbstractSpecScene

__all__ = ["BeadOnRotatingRod", "RodParameters"]


class RodParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.1, lower=0.0, doc="friction ε along the rod, 1/s")
    nu: jnp.ndarray = parameter(default=0.1, lower=0.0, doc="intensity ν of the random force along the rod")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="bead mass m")
    spin: jnp.ndarray = parameter(default=1.0, doc="mean angular rate Ω of the rod")
    wobble: jnp.ndarray = parameter(default=0.5, doc="amplitude A of the angle's oscillation")
    wobble_rate: jnp.ndarray = parameter(default=2.0, doc="frequency w of the angle's oscillation")

    def control(self, t):
        """The rod's angle ``u(t) = Ω t + A sin(w t)``."""
        return self.spin * t + self.wobble * jnp.sin(self.wobble_rate * t)


def _kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * v @ v


def _on_rod(q, pi, t, p):
    u = p.control(t)
    return (-q[0] * jnp.sin(u) + q[1] * jnp.cos(u))[None]


def _along_rod(q, v, pi, t, p):
    u = p.control(t)
    return jnp.cos(u) * v[0] + jnp.sin(u) * v[1]


def _dissipation(q, v, pi, t, p):
    return p.eps * p.mass * _along_rod(q, v, pi, t, p) ** 2


def _random_force(q, v, pi, t, p):
    u = p.control(t)
    return sqrt_intensity(p.nu) * jnp.sqrt(p.mass) * jnp.stack([jnp.cos(u), jnp.sin(u)])[:, None]


class BeadOnRotatingRod(AbstractSpecScene):
    """Bead on a rod turned by a prescribed control angle u(t) (a parametric constraint)."""

    name: ClassVar[str] = "bead-on-rotating-rod"
    Parameters: ClassVar[type[RodParameters]] = RodParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y")
    terms: ClassVar[dict] = dict(
        kinetic_energy=_kinetic, holonomic=_on_rod, dissipation=_dissipation, noise_force=_random_force
    )
    dependent: ClassVar[tuple[str, ...]] = ("y",)

    params: RodParameters
    route: str = eqx.field(static=True)

    def __init__(self, *, route: str = "multipliers", **params):
        self.params, self.route = RodParameters(**params), route

    def configuration(self):
        """At ``r = 1`` on the rod (``u(0) = 0``), sliding out at 0.2, carried round at ``u̇(0) = Ω + A w``."""
        u_dot = self.params.spin + self.params.wobble * self.params.wobble_rate
        return jnp.array([1.0, 0.0]), jnp.stack([jnp.full((), 0.2), u_dot]).astype(jnp.zeros(()).dtype)
