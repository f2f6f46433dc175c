"""A point with a linear kinematic constraint: the contact oscillator (McLachlan–Perlmutter) and S3's example.

Coordinates ``(x, y, z)`` of a point of mass ``m``; constraint ``ẋ + y ż = 0``;
potential ``Π = ½ k (x² + y²) + m g z``.  The reaction ``(1, 0, y)ᵀλ`` has no
``y`` component, so besides the energy ``H = T + Π`` the ``y`` oscillator keeps
``H_y = ½ (m ẏ² + k y²)`` (with ``m = k = 1``: ``½ (y² + ẏ²)``).  With ``k = 0``
it is the constrained point of S3, free (``g = 0``) or in gravity.  Friction
``R = ε m |q̇|²`` and random forces ``√(m ν) V``.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ._spec_scene import AbstractSpecScene

__all__ = ["ContactOscillator", "ContactOscillatorParameters"]


class ContactOscillatorParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.1, lower=0.0, doc="friction ε, 1/s")
    nu: jnp.ndarray = parameter(default=0.1, lower=0.0, doc="intensity ν of the random forces")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    stiffness: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="spring constant k of x and y")
    gravity: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="gravity g along −z")


def _kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * v @ v


def _potential(q, pi, t, p):
    return 0.5 * p.stiffness * (q[0] ** 2 + q[1] ** 2) + p.mass * p.gravity * q[2]


def _contact(q, pi, t, p):
    return jnp.stack([jnp.ones((), q.dtype), jnp.zeros((), q.dtype), q[1]])[None, :]


def _dissipation(q, v, pi, t, p):
    return p.eps * p.mass * v @ v


def _forces(q, v, pi, t, p):
    return sqrt_intensity(p.nu) * jnp.sqrt(p.mass) * jnp.eye(3, dtype=q.dtype)


class ContactOscillator(AbstractSpecScene):
    """Point with the constraint ẋ + y ż = 0 in a harmonic (and gravity) potential."""

    name: ClassVar[str] = "contact-oscillator"
    Parameters: ClassVar[type[ContactOscillatorParameters]] = ContactOscillatorParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y", "z")
    terms: ClassVar[dict] = dict(
        kinetic_energy=_kinetic,
        potential=_potential,
        constraints=_contact,
        dissipation=_dissipation,
        noise_force=_forces,
    )
    dependent: ClassVar[tuple[str, ...]] = ("x",)

    params: ContactOscillatorParameters
    route: str = eqx.field(static=True)

    def __init__(self, *, route: str = "reduced", **params):
        self.params, self.route = ContactOscillatorParameters(**params), route

    def configuration(self):
        """``q = (1, 0.5, 0)``, ``ẏ = 0.3``, ``ż = 0.4``, ``ẋ = −y ż``."""
        return jnp.array([1.0, 0.5, 0.0]), jnp.array([-0.2, 0.3, 0.4])
