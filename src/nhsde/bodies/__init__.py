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
"""

from ._body import RigidBody as RigidBody
from ._catalogue import balanced_ball_integral as balanced_ball_integral
from ._catalogue import balanced_ball_measure as balanced_ball_measure
from ._catalogue import ball_in_cavity_integral as ball_in_cavity_integral
from ._catalogue import ellipsoid_inertia as ellipsoid_inertia
from ._catalogue import ellipsoid_measure as ellipsoid_measure
from ._catalogue import flat_base_integral as flat_base_integral
from ._catalogue import flat_base_measure as flat_base_measure
from ._catalogue import revolution_integral as revolution_integral
from ._catalogue import revolution_measure as revolution_measure
from ._catalogue import spherical_inertia_measure as spherical_inertia_measure
from ._catalogue import unbalanced_ball_integral as unbalanced_ball_integral
from ._rolling import FlatBaseField as FlatBaseField
from ._rolling import FlatBaseParameters as FlatBaseParameters
from ._rolling import RollingField as RollingField
from ._rolling import RollingParameters as RollingParameters
from ._rolling import angular_acceleration as angular_acceleration
from ._rolling import contact_inertia as contact_inertia
from ._rolling import contact_kinematics as contact_kinematics
from ._rolling import flat_base_energy as flat_base_energy
from ._rolling import position_rates as position_rates
from ._rolling import rolling_energy as rolling_energy
from ._surfaces import AbstractSurface as AbstractSurface
from ._surfaces import BodyOfRevolution as BodyOfRevolution
from ._surfaces import Disk as Disk
from ._surfaces import Ellipsoid as Ellipsoid
from ._surfaces import ImplicitSurface as ImplicitSurface
from ._surfaces import Sphere as Sphere
from ._surfaces import SphericalCavity as SphericalCavity
