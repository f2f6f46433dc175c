"""A tilting disk (or hoop) rolling without slipping on a horizontal plane under gravity, from its Lagrangian.

Coordinates ``(x, y, ψ, θ, φ)``: contact point ``P``, heading ``ψ`` (the rolling
direction ``e = (cos ψ, sin ψ, 0)``), tilt ``θ`` of the disk's plane from the
vertical and spin ``φ``.  With ``ℓ = ẑ × e``, the centre is ``G = P + R u``,
``u = cos θ ẑ − sin θ ℓ``, the symmetry axis ``k = u × e`` and the angular velocity
``ω = ψ̇ ẑ + θ̇ e + φ̇ k``:

    T = ½ m |Ġ|² + ½ ω·Iω,   I = A·1 + (C − A) k kᵀ,   V = m g R cos θ,

``C`` the axial and ``A`` the diametral central moment of inertia (thin disk:
``C = mR²/2, A = mR²/4``; hoop: ``C = mR², A = mR²/2``).  The material point at
``P`` is at rest, ``Ġ + ω × (P − G) = 0``, whose horizontal part is
``ẋ = R cos ψ φ̇``, ``ẏ = R sin ψ φ̇`` (the vertical part holds identically).
A Chaplygin system (S4 (4.4)): ``T``, ``V`` and the constraints do not involve
``x, y``; ``ψ, φ`` are pseudo-cyclic and ``θ`` positional.

Friction ``R_f = ε (m|Ġ|² + C (ω·k)² + A(|ω|² − (ω·k)²)) = 2εT`` and random torques
``√ν (√(A + mR²) V₁, √A V₂, √(C + mR²) V₃)`` on the tilt, heading and spin.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ._spec_scene import AbstractSpecScene

__all__ = ["RollingDisk", "RollingDiskParameters", "rolling_disk_kinematics"]


class RollingDiskParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="friction ε, 1/s")
    nu: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="intensity ν of the random torques")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="radius R")
    axial_inertia: jnp.ndarray = parameter(
        default=0.5, lower=0.0, strict=True, doc="central moment of inertia C about the axis"
    )
    diametral_inertia: jnp.ndarray = parameter(
        default=0.25, lower=0.0, strict=True, doc="central moment of inertia A about a diameter"
    )
    gravity: jnp.ndarray = parameter(default=9.81, lower=0.0, doc="gravitational acceleration g")


def _frame(q):
    """``(e, u, k)``: rolling direction, contact → centre, symmetry axis."""
    psi, theta = q[2], q[3]
    zero, one = jnp.zeros((), q.dtype), jnp.ones((), q.dtype)
    e = jnp.stack([jnp.cos(psi), jnp.sin(psi), zero])
    lat = jnp.stack([-jnp.sin(psi), jnp.cos(psi), zero])
    u = jnp.cos(theta) * jnp.stack([zero, zero, one]) - jnp.sin(theta) * lat
    return e, u, jnp.cross(u, e)


def rolling_disk_kinematics(q, v, p):
    """``(Ġ, ω, k)``: velocity of the centre, angular velocity and symmetry axis at ``(q, q̇)``."""
    centre = lambda q: jnp.concatenate([q[:2], jnp.zeros(1, q.dtype)]) + p.radius * _frame(q)[1]
    g_dot = jax.jvp(centre, (q,), (v,))[1]
    e, _, k = _frame(q)
    omega = v[2] * jnp.array([0.0, 0.0, 1.0], q.dtype) + v[3] * e + v[4] * k
    return g_dot, omega, k


def _inertia_tensor(k, p):
    """``A·1 + (C − A) k kᵀ``: the central inertia tensor of a body symmetric about ``k``."""
    return p.diametral_inertia * jnp.eye(3, dtype=k.dtype) + (p.axial_inertia - p.diametral_inertia) * jnp.outer(k, k)


def _mass_matrix(q, pi, t, p):
    """``m J_Gᵀ J_G + Wᵀ I W`` with ``Ġ = J_G q̇``, ``ω = W q̇``: ``T = ½ q̇ᵀ M q̇``."""
    basis = jnp.eye(5, dtype=q.dtype)
    jac_g, omega, k = jax.vmap(lambda b: rolling_disk_kinematics(q, b, p), out_axes=(1, 1, None))(basis)
    return p.mass * jac_g.T @ jac_g + omega.T @ _inertia_tensor(k, p) @ omega


def _kinetic(q, v, pi, t, p):
    return 0.5 * v @ _mass_matrix(q, pi, t, p) @ v


def _potential(q, pi, t, p):
    return p.mass * p.gravity * p.radius * jnp.cos(q[3])


def _rolling(q, pi, t, p):
    one, zero = jnp.ones((), q.dtype), jnp.zeros((), q.dtype)
    c, s = p.radius * jnp.cos(q[2]), p.radius * jnp.sin(q[2])
    return jnp.stack([jnp.stack([one, zero, zero, zero, -c]), jnp.stack([zero, one, zero, zero, -s])])


def _dissipation(q, v, pi, t, p):
    return 2.0 * p.eps * _kinetic(q, v, pi, t, p)


def _torques(q, v, pi, t, p):
    zero = jnp.zeros((), q.dtype)
    tilt = jnp.sqrt(p.diametral_inertia + p.mass * p.radius**2)
    heading = jnp.sqrt(p.diametral_inertia)
    spin = jnp.sqrt(p.axial_inertia + p.mass * p.radius**2)
    rows = [[zero, zero, zero], [zero, zero, zero], [zero, heading, zero], [tilt, zero, zero], [zero, zero, spin]]
    return sqrt_intensity(p.nu) * jnp.stack([jnp.stack(r) for r in rows])


class RollingDisk(AbstractSpecScene):
    """A disk or hoop rolling on a plane under gravity, free to tilt (Voronets form in the rates of ψ, θ, φ).

    ``spin`` is the initial rolling rate ``φ̇`` of the upright straight rolling
    the scene starts from (``ẋ = R φ̇``).
    """

    name: ClassVar[str] = "rolling-disk"
    Parameters: ClassVar[type[RollingDiskParameters]] = RollingDiskParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y", "psi", "theta", "phi")
    terms: ClassVar[dict] = dict(
        mass_matrix=_mass_matrix,
        potential=_potential,
        constraints=_rolling,
        dissipation=_dissipation,
        noise_force=_torques,
    )
    dependent: ClassVar[tuple[str, ...]] = ("x", "y")
    angles: ClassVar[tuple[str, ...]] = ("psi", "theta")

    params: RollingDiskParameters
    route: str = eqx.field(static=True)
    spin: float = eqx.field(static=True)

    def __init__(self, *, route: str = "reduced", spin: float = 3.0, **params):
        self.params, self.route, self.spin = RollingDiskParameters(**params), route, float(spin)

    def configuration(self):
        """Upright at the origin, heading along ``x``, rolling straight at ``φ̇ = spin``."""
        q = jnp.zeros(5)
        qdot = jnp.zeros(5).at[4].set(self.spin).at[0].set(self.spin * self.params.radius)
        return q, qdot
