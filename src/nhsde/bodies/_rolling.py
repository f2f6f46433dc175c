"""Rolling without slipping (classic) and without slipping and spinning (rubber), S2 §1.

Body-frame equations, ``ω`` the angular velocity, ``γ`` the unit normal of the
support at the contact (into the body), ``r = r(γ)`` the centre of mass →
contact point, ``Ĩ = I + m(r²E − r⊗r)`` the inertia about the contact point:

    Ĩω̇ = (Ĩω + S) × ω − m r × (ω × ṙ) + M_P + λγ,        S2 (1.4), (1.7), (1.12)
    Γγ̇ = γ × ω,   Γ = E − k ∂r/∂γ,   ṙ = (∂r/∂γ) γ̇,        S2 (1.6), (1.13)

``k`` is the signed curvature of a fixed sphere (``k = 0``: the plane, ``Γ = E``).
The no-slip constraint ``v + ω × r = 0`` (S2 (1.1)) has been used to eliminate
the contact force; ``M_P`` is the moment of the external forces about the
contact point (gravity on a plane: ``M_P = m g r × γ``, from
``U = −m g (γ, r(γ))``).  Classic rolling: ``λ = 0``, spin is free.  Rubber
rolling adds the no-spin constraint ``(ω, γ) = 0`` (S2 (1.2)); ``λ`` keeps it:

    λ = −[(γ, Ĩ⁻¹R) + (ω, γ̇)] / (γ, Ĩ⁻¹γ),   R = the right-hand side without λγ,

so that ``d(ω, γ)/dt = 0`` identically (S2 (1.12); on the plane ``(ω, γ̇) = 0``).

Sign of ``k`` (S2 Fig. 2): ``k = 1/a > 0`` when the body is outside the fixed
sphere of radius ``a`` (a: convex body on the sphere; c: the sphere inside a
cavity of the body), ``k = −1/a`` when the body rolls inside a spherical shell (b).
For a ball ``r = −Rγ`` this gives ``γ̇ = κ γ × ω`` with ``κ = 1/(1 + kR)``.

The physics uses ``n = γ/|γ|`` throughout and ``γ̇ = |γ| ṅ``: the flow of
``(ω, n)`` does not depend on ``|γ|``, and ``γ²`` and ``(ω, γ)`` are exact first
integrals in the whole space ``ℝ⁶``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._misc import is_concrete
from .._params import AbstractParameters, parameter
from .._system import StateLayout
from ..mechanics._small import matmul
from ._body import RigidBody
from ._surfaces import Disk, SphericalCavity, fibonacci_directions

__all__ = [
    "FlatBaseField",
    "FlatBaseParameters",
    "RollingField",
    "RollingParameters",
    "angular_acceleration",
    "contact_inertia",
    "contact_kinematics",
    "flat_base_energy",
    "position_rates",
    "rolling_energy",
]


def solve3(a, b):
    """``a⁻¹ b`` for a ``3×3`` matrix by cofactors (fuses into the surrounding code; LAPACK's batched
    small solves cost far more on CPU).  ``b`` is ``(3,)`` or ``(3, k)``."""
    cof = jnp.stack([jnp.cross(a[1], a[2]), jnp.cross(a[2], a[0]), jnp.cross(a[0], a[1])])  # rows: cofactors
    return matmul(cof.T, b) / matmul(a[0], cof[0])


def contact_inertia(inertia, mass, r):
    """``Ĩ = I + m(r²E − r⊗r)``: the inertia tensor about the contact point."""
    return inertia + mass * (matmul(r, r) * jnp.eye(3, dtype=r.dtype) - jnp.outer(r, r))


def contact_kinematics(surface, omega, gamma, curvature=None):
    """``(n, ṅ, r, ṙ)`` with ``n = γ/|γ|``: ``ṅ = n × ω`` on a plane, ``Γṅ = n × ω`` on a sphere.

    ``curvature=None`` is the plane (no Jacobian of ``r`` needed); otherwise
    ``Γ = E − k ∂r/∂γ``, S2 (1.13).
    """
    n = gamma / jnp.linalg.norm(gamma)
    if curvature is None:
        n_dot = jnp.cross(n, omega)
        r, r_dot = jax.jvp(surface.contact_point, (n,), (n_dot,))
        return n, n_dot, r, r_dot
    r = surface.contact_point(n)
    jac = jax.jacfwd(surface.contact_point)(n)
    n_dot = solve3(jnp.eye(3, dtype=n.dtype) - curvature * jac, jnp.cross(n, omega))
    return n, n_dot, r, matmul(jac, n_dot)


def angular_acceleration(inertia, mass, gyrostat, omega, n, n_dot, r, r_dot, torque, rubber: bool):
    """``ω̇`` from ``Ĩω̇ = (Ĩω + S) × ω − m r × (ω × ṙ) + M_P (+ λγ)``, S2 (1.4), (1.7), (1.12)."""
    it = contact_inertia(inertia, mass, r)
    rhs = jnp.cross(matmul(it, omega) + gyrostat, omega) - mass * jnp.cross(r, jnp.cross(omega, r_dot)) + torque
    acc = solve3(it, rhs)
    if not rubber:
        return acc
    it_n = solve3(it, n)
    lam = -(matmul(n, acc) + matmul(omega, n_dot)) / matmul(n, it_n)
    return acc + lam * it_n


def position_rates(alpha, omega, n, r_dot):
    """``(α̇, ẋ, ẏ)``: the fixed horizontal axis ``OX`` in the body axes and the contact point on the plane,
    ``α̇ = α × ω``, ``ẋ = (α, ṙ)``, ``ẏ = (γ × α, ṙ)`` (S2 (1.4); ``α`` normalised like ``γ``)."""
    a = alpha / jnp.linalg.norm(alpha)
    return jnp.concatenate([jnp.cross(alpha, omega), jnp.stack([matmul(a, r_dot), matmul(jnp.cross(n, a), r_dot)])])


class RollingParameters(AbstractParameters):
    """A body rolling on a horizontal plane (``curvature = 0``) or a fixed sphere of curvature ``k``."""

    body: RigidBody
    curvature: jnp.ndarray = parameter(default=0.0, doc="signed curvature k of the fixed sphere (0: plane)")
    gravity: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="gravitational acceleration g (plane only)")

    def __init__(self, *, body: RigidBody, curvature=0.0, gravity=0.0):
        if not isinstance(body, RigidBody):
            raise TypeError(f"RollingParameters: body={body!r}; expected nhsde.bodies.RigidBody.")
        self.body = body
        self.curvature = jnp.asarray(curvature)
        self.gravity = jnp.asarray(gravity)


_OMEGA = ("omega_1", "omega_2", "omega_3")
_GAMMA = ("gamma_1", "gamma_2", "gamma_3")
_ALPHA = ("alpha_1", "alpha_2", "alpha_3")


class RollingField(eqx.Module):
    """Vector field ``f(t, y, params)`` of a body rolling on a plane or a sphere, S2 (1.4)–(1.13).

    State ``y = (ω, γ)``; with ``position=True`` (plane only) also the body-axes
    components ``α`` of the fixed horizontal axis ``OX`` and the contact point
    ``(x, y)`` on the plane: ``α̇ = α × ω``, ``ẋ = (α, ṙ)``, ``ẏ = (γ × α, ṙ)`` (S2 (1.4)).
    ``params`` is a :class:`RollingParameters`.
    """

    rubber: bool = eqx.field(static=True)
    sphere: bool = eqx.field(static=True)
    position: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.sphere and self.position:
            raise ValueError("RollingField: position=True is for the plane; on a sphere the state is (ω, γ).")

    @property
    def layout(self) -> StateLayout:
        names = _OMEGA + _GAMMA + ((_ALPHA + ("x", "y")) if self.position else ())
        roles = ("velocity",) * 3 + ("independent_coordinate",) * 3
        if self.position:
            roles += ("independent_coordinate",) * 3 + ("dependent_coordinate",) * 2
        return StateLayout(names, roles)

    def __call__(self, t, y, p: RollingParameters):
        body = p.body
        omega, gamma = y[:3], y[3:6]
        n, n_dot, r, r_dot = contact_kinematics(body.surface, omega, gamma, p.curvature if self.sphere else None)
        torque = jnp.zeros_like(omega) if self.sphere else p.gravity * body.mass * jnp.cross(r, n)
        omega_dot = angular_acceleration(
            body.inertia, body.mass, body.gyrostat, omega, n, n_dot, r, r_dot, torque, self.rubber
        )
        parts = [omega_dot, jnp.linalg.norm(gamma) * n_dot]
        if self.position:
            parts.append(position_rates(y[6:9], omega, n, r_dot))
        return jnp.concatenate(parts)


def rolling_energy(y, p):
    """``E = ½(ω, Ĩω) + U(γ)``, ``U = −m g (γ, r(γ))``: S2 (1.10), (1.15).  ``p`` has ``body`` and ``gravity``."""
    body = p.body
    omega, n = y[:3], y[3:6] / jnp.linalg.norm(y[3:6])
    r = body.surface.contact_point(n)
    return 0.5 * matmul(
        omega, matmul(contact_inertia(body.inertia, body.mass, r), omega)
    ) - p.gravity * body.mass * matmul(n, r)


def check_rolling_configuration(p: RollingParameters, sphere: bool) -> None:
    """Structural checks of a rolling problem (concrete parameters): support, gravity, surface."""
    surface = p.body.surface
    if not is_concrete(p.curvature, p.gravity):
        return
    k, g = float(p.curvature), float(p.gravity)
    if not sphere and k != 0.0:
        raise ValueError(f"curvature={k:g} on a plane; pass the curvature only for a sphere (curvature=None: plane).")
    if sphere and g != 0.0:
        raise ValueError(
            f"gravity={g:g} on a sphere: the potential then depends on the orientation, not on γ alone, and the "
            "(ω, γ) equations do not close (S2 §1.2, Remark); use gravity=0."
        )
    if isinstance(surface, SphericalCavity):
        radius = float(surface.radius)
        if not (sphere and k * radius > 1.0):
            raise ValueError(
                f"SphericalCavity(radius={radius:g}) rolls only over a fixed sphere inside it: needs a sphere with "
                f"curvature k > 1/R = {1 / radius:g}; got {'the plane' if not sphere else f'k={k:g}'}."
            )
    if sphere and isinstance(surface, Disk):
        raise ValueError("a Disk on a sphere is not modelled; use a Sphere, Ellipsoid or BodyOfRevolution.")
    if sphere and not isinstance(surface, SphericalCavity):
        # the contact is a single point only if Γ = E − k ∂r/∂γ stays non-degenerate
        radii = np.asarray(jax.vmap(surface.curvature_radii)(jnp.asarray(fibonacci_directions(64))))
        if np.any(1.0 + k * radii <= 0):
            raise ValueError(
                f"curvature k={k:g}: the body (radii of curvature up to {float(np.max(radii)):.4g}) "
                "does not fit inside "
                f"the spherical shell of radius {abs(1 / k):.4g}: 1 + k·ρ must stay > 0."
            )


class FlatBaseParameters(AbstractParameters):
    """A body touching a fixed sphere with a flat base, S2 §4.5: the base is the body plane ``x₃ = z``."""

    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    inertia: jnp.ndarray = parameter(
        default=(1.0, 1.0, 1.0), lower=0.0, strict=True, doc="principal moments I₁, I₂, I₃"
    )
    z: jnp.ndarray = parameter(default=-1.0, doc="z = r₃, the base plane x₃ = z (negative: centre of mass above it)")
    curvature: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="curvature k = 1/a of the sphere")

    def __check_init__(self):
        if np.shape(self.inertia) != (3,):
            raise ValueError(
                f"FlatBaseParameters: inertia has shape {np.shape(self.inertia)}; expected the (3,) principal "
                "moments (off-diagonal I₁₃, I₂₃ destroy the measure, S2 §4.5)."
            )


class FlatBaseField(eqx.Module):
    """Rubber rolling of a flat base on a sphere, S2 (4.6)–(4.7).

    ``γ = e₃`` is constant, ``ω₃ = 0`` and the contact point ``r = (r₁, r₂, z)``
    slides over the base: ``ṙ₁ = ω₂/k``, ``ṙ₂ = −ω₁/k`` (from ``ṙ = ω × γ / k``);
    ``(ω₁, ω₂)`` follow S2 (1.12) with ``λ`` keeping ``ω₃ = 0``.  State
    ``(ω₁, ω₂, r₁, r₂)``.
    """

    @property
    def layout(self) -> StateLayout:
        return StateLayout(
            ("omega_1", "omega_2", "r_1", "r_2"),
            ("velocity", "velocity", "independent_coordinate", "independent_coordinate"),
        )

    def __call__(self, t, y, p: FlatBaseParameters):
        zero = jnp.zeros((), y.dtype)
        omega = jnp.stack([y[0], y[1], zero])
        n = jnp.stack([zero, zero, jnp.ones((), y.dtype)])
        r = jnp.stack([y[2], y[3], p.z.astype(y.dtype)])
        r_dot = jnp.cross(omega, n) / p.curvature
        acc = angular_acceleration(
            jnp.diag(p.inertia),
            p.mass,
            jnp.zeros(3, y.dtype),
            omega,
            n,
            jnp.zeros(3, y.dtype),
            r,
            r_dot,
            jnp.zeros(3, y.dtype),
            rubber=True,
        )
        return jnp.concatenate([acc[:2], r_dot[:2]])


def flat_base_energy(y, p: FlatBaseParameters):
    """``E = ½(ω, Ĩω)``, S2 (1.15) with ``U = 0``."""
    zero = jnp.zeros((), y.dtype)
    omega = jnp.stack([y[0], y[1], zero])
    r = jnp.stack([y[2], y[3], p.z.astype(y.dtype)])
    return 0.5 * matmul(omega, matmul(contact_inertia(jnp.diag(p.inertia), p.mass, r), omega))
