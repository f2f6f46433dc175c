"""The ball on the vibrating plane (S0 §3) rebuilt from its Lagrangian.

Coordinates ``(x, y)`` of the centre relative to the plane and quasi-coordinates
``φ`` with ``φ̇ = ω`` (space axes).  For a ball (spherical inertia ``J = κ m r²``)
``T = ½ m (ẋ² + ẏ²) + ½ J |φ̇|²`` is independent of the orientation and the
rolling constraints ``ẋ = r φ̇_y``, ``ẏ = −r φ̇_x`` involve ``ω`` only, so Lagrange's
equations in ``φ`` are the Euler–Hamel equations (their extra terms ``ω × Jω``
vanish).  The plane's random acceleration acts as the inertial force
``m √ν V`` on the centre; rolling resistance ``R = ε m (1 + κ)(ẋ² + ẏ²)``.
The library's elimination gives ``u̇ + 2ε u = δ √ν V``, ``δ = 1/(1 + κ)`` (S0 (3.1)).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ._spec_scene import AbstractSpecScene

__all__ = ["BallFromLagrangian", "RollingBallParameters"]


class RollingBallParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="friction ε of (3.1), 1/s")
    nu: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="intensity ν of the vibration acceleration, per axis")
    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="ball radius r")
    inertia_ratio: jnp.ndarray = parameter(default=0.4, lower=0.0, doc="κ = J/(m r²); 2/5 for a homogeneous ball")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m (drops out of the motion)")


def _kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * (v[0] ** 2 + v[1] ** 2) + 0.5 * p.inertia_ratio * p.mass * p.radius**2 * v[2:] @ v[2:]


def _rolling(q, pi, t, p):
    one, zero, r = jnp.ones((), q.dtype), jnp.zeros((), q.dtype), p.radius
    return jnp.stack([jnp.stack([one, zero, zero, -r, zero]), jnp.stack([zero, one, r, zero, zero])])


def _dissipation(q, v, pi, t, p):
    return p.eps * p.mass * (1 + p.inertia_ratio) * (v[0] ** 2 + v[1] ** 2)


def _vibration(q, v, pi, t, p):
    return p.mass * sqrt_intensity(p.nu) * jnp.eye(5, 2, dtype=q.dtype)


class BallFromLagrangian(AbstractSpecScene):
    """Ball rolling on a randomly vibrating plane, equations derived by the library."""

    name: ClassVar[str] = "ball-from-lagrangian"
    Parameters: ClassVar[type[RollingBallParameters]] = RollingBallParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y", "phi_x", "phi_y", "phi_z")
    terms: ClassVar[dict] = dict(
        kinetic_energy=_kinetic, constraints=_rolling, dissipation=_dissipation, noise_force=_vibration
    )
    dependent: ClassVar[tuple[str, ...]] = ("x", "y")

    params: RollingBallParameters
    route: str = eqx.field(static=True)

    def __init__(self, *, route: str = "reduced", **params):
        self.params, self.route = RollingBallParameters(**params), route

    def configuration(self):
        """At rest at the origin of the plane."""
        return jnp.zeros(5), jnp.zeros(5)
