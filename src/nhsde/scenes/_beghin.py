"""Beghin's plate hinged to a disk (S1 Example 3.1), built from its Lagrangian.

A disk of radius ``R`` and moment of inertia ``I₁`` turns about its fixed centre
``O`` (angle ``α``); a plate of mass ``M`` and central radius of gyration ``k`` is
hinged to the rim at ``A = O + R e(α)`` (angle ``β``), its centre of mass at
``A + b e(β)``, and a constant force ``F`` along ``x`` acts at ``A + a e(β)``
(``e(φ) = (cos φ, sin φ)``):

    T = ½ I₁ α̇² + ½ M (R² α̇² + b² β̇² + 2 R b α̇ β̇ cos(α − β)) + ½ M k² β̇²,
    Π = −F (R cos α + a cos β).

The relation ``α − β = π/2`` is realised either

- by contact (``realisation='contact'``): an ideal holonomic constraint; plate
  and disk turn as one body, S1 (3.5)
  ``[M(R² + b² + k²) + I₁] β̈ + F (a sin β + R cos β) = 0``;
- by a servomotor on the disk (``realisation='servo'``): a servo-constraint
  whose torque acts on ``α`` only, so it does no work on displacements with
  ``δα = 0`` (S1 (3.2)); Beghin's equation S1 (3.4)
  ``M (b² + k²) β̈ − M R b β̇² + F a sin β = 0``, free of ``I₁``.

Bearing friction ``R = ε (I₁ α̇² + M (b² + k²) β̇²)`` and a random torque
``√(ν M (b² + k²)) V`` on the plate.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ..mechanics import ServoConstraint
from ._spec_scene import AbstractSpecScene

__all__ = ["BeghinParameters", "BeghinPlate"]


class BeghinParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.05, lower=0.0, doc="bearing friction ε, 1/s")
    nu: jnp.ndarray = parameter(default=0.01, lower=0.0, doc="intensity ν of the random torque on the plate")
    plate_mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="plate mass M")
    gyration: jnp.ndarray = parameter(default=0.3, lower=0.0, doc="central radius of gyration k of the plate")
    hinge_offset: jnp.ndarray = parameter(
        default=0.5, lower=0.0, doc="distance b from the hinge to the plate's centre of mass"
    )
    disk_radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="disk radius R")
    disk_inertia: jnp.ndarray = parameter(default=2.0, lower=0.0, strict=True, doc="disk moment of inertia I₁")
    force: jnp.ndarray = parameter(default=1.0, doc="force F along x")
    arm: jnp.ndarray = parameter(default=0.8, doc="distance a from the hinge to where F acts")


def _kinetic(q, v, pi, t, p):
    m, r, b, k = p.plate_mass, p.disk_radius, p.hinge_offset, p.gyration
    coupling = 2 * r * b * v[0] * v[1] * jnp.cos(q[0] - q[1])
    return 0.5 * p.disk_inertia * v[0] ** 2 + 0.5 * m * (
        r**2 * v[0] ** 2 + b**2 * v[1] ** 2 + coupling + k**2 * v[1] ** 2
    )


def _potential(q, pi, t, p):
    return -p.force * (p.disk_radius * jnp.cos(q[0]) + p.arm * jnp.cos(q[1]))


def _right_angle(q, pi, t, p):
    return (q[0] - q[1] - jnp.pi / 2)[None]


def _servo_matrix(q, pi, t, p):
    return jnp.array([[1.0, -1.0]], q.dtype)


def _servo_on_disk(q, pi, t, p):
    return jnp.array([[1.0, 0.0]], q.dtype)


def _dissipation(q, v, pi, t, p):
    return p.eps * (p.disk_inertia * v[0] ** 2 + p.plate_mass * (p.hinge_offset**2 + p.gyration**2) * v[1] ** 2)


def _torque(q, v, pi, t, p):
    plate = sqrt_intensity(p.nu) * jnp.sqrt(p.plate_mass * (p.hinge_offset**2 + p.gyration**2))
    return jnp.stack([jnp.zeros((), q.dtype), plate])[:, None]


_TERMS = dict(kinetic_energy=_kinetic, potential=_potential, dissipation=_dissipation, noise_force=_torque)
_SERVO = ServoConstraint(matrix=_servo_matrix, realisation=_servo_on_disk)


class BeghinPlate(AbstractSpecScene):
    """Beghin's plate hinged to a disk, α − β = π/2 kept by contact or by a servomotor.

    S1 Example 3.1.
    """

    name: ClassVar[str] = "beghin-plate"
    Parameters: ClassVar[type[BeghinParameters]] = BeghinParameters
    coordinates: ClassVar[tuple[str, ...]] = ("alpha", "beta")
    dependent: ClassVar[tuple[str, ...]] = ("alpha",)
    angles: ClassVar[tuple[str, ...]] = ("alpha", "beta")

    params: BeghinParameters
    route: str = eqx.field(static=True)
    realisation: str = eqx.field(static=True)

    def __init__(self, *, realisation: str = "servo", route: str = "reduced", **params):
        if realisation not in ("servo", "contact"):
            raise ValueError(f"realisation={realisation!r}; allowed: 'servo', 'contact'.")
        self.params, self.route, self.realisation = BeghinParameters(**params), route, realisation

    @property
    def terms(self):
        return _TERMS | ({"holonomic": _right_angle} if self.realisation == "contact" else {"servo": _SERVO})

    def configuration(self):
        """``β = 0.3``, ``α = β + π/2``, both turning at 0.5."""
        beta = 0.3
        return jnp.array([beta + jnp.pi / 2, beta]), jnp.array([0.5, 0.5])
