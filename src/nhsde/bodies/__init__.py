"""Rigid bodies rolling on a plane or a sphere: surfaces, classic and rubber contact, S2 and S0 §5.

- Surfaces by their inverse Gauss map ``r(γ)`` (S2 (1.5)): :class:`Sphere`
  (displaced centre of mass), :class:`Ellipsoid`, :class:`BodyOfRevolution`
  (from its profile), :class:`Disk`, :class:`SphericalCavity`, or an implicit
  convex body :class:`ImplicitSurface`; subclass :class:`AbstractSurface` to give
  ``r(γ)`` directly.
- :class:`RigidBody`: mass, inertia tensor, surface, gyrostat.
- :class:`RollingField`: the equations of classic and rubber rolling on a plane
  and a sphere (S2 (1.4)–(1.13)); :class:`FlatBaseField`: a flat base on a sphere
  (S2 (4.6)–(4.7)).
- The S2 catalogue of invariant measures and extra integrals.
- Directions on the unit sphere: :func:`fibonacci_directions` (nearly uniform),
  :func:`tangent_basis` (the tangent plane at a point).
"""

from ._body import RigidBody as RigidBody
from ._catalogue import (
    balanced_ball_integral as balanced_ball_integral,
    balanced_ball_measure as balanced_ball_measure,
    ball_in_cavity_integral as ball_in_cavity_integral,
    ellipsoid_inertia as ellipsoid_inertia,
    ellipsoid_measure as ellipsoid_measure,
    flat_base_integral as flat_base_integral,
    flat_base_measure as flat_base_measure,
    revolution_integral as revolution_integral,
    revolution_measure as revolution_measure,
    spherical_inertia_measure as spherical_inertia_measure,
    unbalanced_ball_integral as unbalanced_ball_integral,
)
from ._rolling import (
    FlatBaseField as FlatBaseField,
    FlatBaseParameters as FlatBaseParameters,
    RollingField as RollingField,
    RollingParameters as RollingParameters,
    angular_acceleration as angular_acceleration,
    contact_inertia as contact_inertia,
    contact_kinematics as contact_kinematics,
    flat_base_energy as flat_base_energy,
    position_rates as position_rates,
    rolling_energy as rolling_energy,
)
from ._surfaces import (
    AbstractSurface as AbstractSurface,
    BodyOfRevolution as BodyOfRevolution,
    Disk as Disk,
    Ellipsoid as Ellipsoid,
    ImplicitSurface as ImplicitSurface,
    Sphere as Sphere,
    SphericalCavity as SphericalCavity,
    fibonacci_directions as fibonacci_directions,
    tangent_basis as tangent_basis,
)
