"""Invariant measures and extra first integrals of rubber rolling: the S2 catalogue (§3–4).

Each function takes the state ``y = (ω, γ)`` (or ``(ω₁, ω₂, r₁, r₂)`` for the
flat base) and the parameters, and returns a density ``ρ`` of an invariant
measure ``ρ dω dγ`` or a first integral.  They hold on the manifold
``γ² = 1, (ω, γ) = 0`` and raise ``ValueError`` when the body is not the one the
formula belongs to.  Every formula here was checked against the Liouville
equation and against long integrations (``tests/test_bodies_catalogue.py``);
where the printed S2 text is unreadable or its sign convention differs, the
docstring gives the verified form.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._misc import is_concrete
from ._rolling import FlatBaseParameters, RollingParameters, contact_inertia
from ._surfaces import Ellipsoid, Sphere, SphericalCavity

__all__ = [
    "balanced_ball_integral",
    "balanced_ball_measure",
    "ball_in_cavity_integral",
    "ellipsoid_inertia",
    "ellipsoid_measure",
    "flat_base_integral",
    "flat_base_measure",
    "revolution_integral",
    "revolution_measure",
    "spherical_inertia_measure",
    "unbalanced_ball_integral",
]


def _split(y):
    omega, gamma = y[:3], y[3:6]
    return omega, gamma / jnp.linalg.norm(gamma)


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _ball(p: RollingParameters, *, balanced: bool) -> Sphere | SphericalCavity:
    surface = p.body.surface
    if not isinstance(surface, (Sphere, SphericalCavity)):
        raise ValueError(
            f"this formula is for a ball (Sphere or SphericalCavity surface); got {type(surface).__name__}."
        )
    if balanced and is_concrete(surface.offset):
        _require(
            bool(np.all(np.asarray(surface.offset) == 0)),
            f"this formula is for a balanced ball (offset 0); got offset={np.asarray(surface.offset).tolist()}.",
        )
    return surface


def _plane(p: RollingParameters) -> None:
    if is_concrete(p.curvature):
        _require(
            float(p.curvature) == 0.0, f"this formula is for the plane (curvature 0); got k={float(p.curvature):g}."
        )


def _ball_j(p: RollingParameters):
    surface = _ball(p, balanced=True)
    return p.body.inertia + p.body.mass * surface.radius**2 * jnp.eye(3), surface


def _kappa(curvature, surface, radius):
    """``γ̇ = κ γ × ω``: ``κ = 1/(1 + kR)`` for a ball, ``1/(1 − kR)`` for a cavity (S2 (4.3))."""
    sign = -1.0 if isinstance(surface, SphericalCavity) else 1.0
    return 1.0 / (1.0 + sign * curvature * radius)


def balanced_ball_measure(y, p: RollingParameters):
    """``ρ = (γ, J⁻¹γ)^{1/(2κ)}``, ``J = I + mR²E``: S2 (3.15) on the plane (``κ = 1``), (4.3)–(4.4) on a sphere."""
    j, surface = _ball_j(p)
    _, n = _split(y)
    return jnp.dot(n, jnp.linalg.solve(j, n)) ** (0.5 / _kappa(p.curvature, surface, surface.radius))


def balanced_ball_integral(y, p: RollingParameters):
    """``F₂ = (Jω + S)² − (Jω + S, γ)²`` at ``U = 0`` on the plane: S2 §3.4 (``S = 0``: ``(Jω × γ)²``)."""
    j, _ = _ball_j(p)
    _plane(p)
    omega, n = _split(y)
    k = j @ omega + p.body.gyrostat
    return jnp.dot(k, k) - jnp.dot(k, n) ** 2


def ball_in_cavity_integral(y, p: RollingParameters):
    """At ``κ = −1`` (cavity of radius ``R = 2a`` over a sphere of radius ``a``), S2 §4.3:

    F = [(Jω, Jω) + det J (ω, Jω)(J⁻¹γ, J⁻¹γ)] / (γ, J⁻¹γ).
    """
    j, surface = _ball_j(p)
    if is_concrete(p.curvature, surface.radius):
        kappa = float(_kappa(np.asarray(p.curvature), surface, np.asarray(surface.radius)))
        _require(abs(kappa + 1.0) < 1e-12, f"this integral exists at κ = −1 (k = 2/R); here κ = {kappa:g}.")
    omega, n = _split(y)
    jw, jin = j @ omega, jnp.linalg.solve(j, n)
    return (jnp.dot(jw, jw) + jnp.linalg.det(j) * jnp.dot(omega, jw) * jnp.dot(jin, jin)) / jnp.dot(n, jin)


def unbalanced_ball_integral(y, p: RollingParameters):
    """``F₂ = (Ĩω × γ)² − 2mR(γ, c)(Ĩω, ω)`` at ``U = 0`` on the plane, S2 (3.19), ``c`` = offset."""
    surface = _ball(p, balanced=False)
    _plane(p)
    omega, n = _split(y)
    body = p.body
    iw = contact_inertia(body.inertia, body.mass, surface.contact_point(n)) @ omega
    cross = jnp.cross(iw, n)
    return jnp.dot(cross, cross) - 2 * body.mass * surface.radius * jnp.dot(n, surface.offset) * jnp.dot(iw, omega)


def _revolution(y, p: RollingParameters):
    inertia = p.body.inertia
    if is_concrete(inertia):
        i = np.asarray(inertia)
        _require(
            np.allclose(i, np.diag(np.diag(i))) and np.isclose(i[0, 0], i[1, 1]),
            f"this formula is for a dynamically symmetric body, I = diag(I₁, I₁, I₃); got {i.tolist()}.",
        )
    _plane(p)
    omega, n = _split(y)
    r = p.body.surface.contact_point(n)
    i1, i3, m = inertia[0, 0], inertia[2, 2], p.body.mass
    g1 = i1 * n[2] ** 2 + i3 * (1 - n[2] ** 2) + m * jnp.dot(r, n) ** 2
    g2 = i1 + m * jnp.dot(r, r)
    return omega, g1, g2


def revolution_measure(y, p: RollingParameters):
    """Body of revolution (``I₁ = I₂``, axis ``e₃``) on the plane: ``ρ = g₁^{1/2} g₂``, S2 (3.2), Table 1,

    ``g₁ = I₁γ₃² + I₃(1 − γ₃²) + m(r, γ)²``, ``g₂ = I₁ + m r²``.
    """
    _, g1, g2 = _revolution(y, p)
    return jnp.sqrt(g1) * g2


def revolution_integral(y, p: RollingParameters):
    """``F₂ = g₁^{1/2} ω₃``, S2 (3.4)."""
    omega, g1, _ = _revolution(y, p)
    return jnp.sqrt(g1) * omega[2]


def spherical_inertia_measure(y, p: RollingParameters):
    """``I = μE``, any surface, on the plane: ``ρ = (μ + m r²)(μ + m(r, γ)²)^{1/2}``, S2 (3.7)."""
    inertia = p.body.inertia
    if is_concrete(inertia):
        i = np.asarray(inertia)
        _require(np.allclose(i, i[0, 0] * np.eye(3)), f"this formula is for I = μE; got {i.tolist()}.")
    _plane(p)
    _, n = _split(y)
    r = p.body.surface.contact_point(n)
    mu, m = inertia[0, 0], p.body.mass
    return (mu + m * jnp.dot(r, r)) * jnp.sqrt(mu + m * jnp.dot(r, n) ** 2)


def ellipsoid_inertia(semi_axes, mass, alpha, beta):
    """Principal moments on the hyperboloid (3.8), parametrised by S2 (3.9): ``I_k = m det B (α + a_k⁻²)/(β +
    a_k²)``."""
    a2 = jnp.asarray(semi_axes) ** 2
    return mass * jnp.prod(a2) * (alpha + 1.0 / a2) / (beta + a2)


def ellipsoid_measure(y, p: RollingParameters):
    """Ellipsoid ``B = diag(a²)`` (centre of mass at the centre) with inertia on the hyperboloid (3.8):

        ρ = (χ + (αβ − 1) det B)^{1/2} |(r, γ)²(Δ + β r²) − det B| / (r, γ)²,
        χ = (β² + β Tr B + Δ)(r, γ)²,   Δ = det B (α + Tr B⁻¹),

    S2 §3.3, Table 1, with ``(α, β)`` recovered from ``I`` through (3.9).
    """
    surface = p.body.surface
    if not isinstance(surface, Ellipsoid):
        raise ValueError(f"this formula is for an Ellipsoid surface; got {type(surface).__name__}.")
    _plane(p)
    a2 = surface.semi_axes**2
    inertia, m = jnp.diag(p.body.inertia), p.body.mass
    det_b = jnp.prod(a2)
    # (3.9) is linear in (α, β): −m det B α + I_k β = m det B / a_k² − I_k a_k²
    lhs = jnp.stack([-m * det_b * jnp.ones(3), inertia], axis=1)
    rhs = m * det_b / a2 - inertia * a2
    alpha, beta = jnp.linalg.lstsq(lhs, rhs)[0]
    if is_concrete(inertia, a2):
        off = np.asarray(lhs @ jnp.stack([alpha, beta]) - rhs)
        _require(
            bool(np.all(np.abs(off) <= 1e-9 * np.max(np.abs(np.asarray(rhs)))))
            and bool(np.all(np.asarray(p.body.inertia) == np.diag(np.asarray(inertia))))
            and bool(np.all(np.asarray(surface.offset) == 0)),
            "this formula needs principal axes along the semi-axes, the centre of mass at the centre and the "
            f"inertia on the hyperboloid S2 (3.8); (3.9) is off by {off.tolist()}.",
        )
    _, n = _split(y)
    r = surface.contact_point(n)
    rg2 = jnp.dot(r, n) ** 2
    delta = det_b * (alpha + jnp.sum(1.0 / a2))
    chi = (beta**2 + beta * jnp.sum(a2) + delta) * rg2
    return jnp.sqrt(chi + (alpha * beta - 1) * det_b) * jnp.abs(rg2 * (delta + beta * jnp.dot(r, r)) - det_b) / rg2


def _flat_base_check(p: FlatBaseParameters) -> None:
    if is_concrete(p.z, p.inertia):
        _require(
            float(p.z) == 0.0 or float(p.inertia[0]) == float(p.inertia[1]),
            "the flat base has a measure and an extra integral for z = 0 or I₁ = I₂ (S2 §4.5); got "
            f"z={float(p.z):g}, I = {np.asarray(p.inertia).tolist()}.",
        )


def _flat_base_exponent(y, p: FlatBaseParameters):
    """``−k z m (r₁² + r₂²) / (2(I₁ + m z²))``."""
    return -p.curvature * p.z * p.mass * (y[2] ** 2 + y[3] ** 2) / (2 * (p.inertia[0] + p.mass * p.z**2))


def flat_base_measure(y, p: FlatBaseParameters):
    """Density on ``(ω₁, ω₂, r₁, r₂)``, S2 §4.5:

    - ``z = 0``: ``ρ = I₁I₂ + m(I₁r₁² + I₂r₂²)``;
    - ``I₁ = I₂``: ``ρ = (I₁ + m(r₁² + r₂² + z²)) exp(−k z m (r₁² + r₂²)/(2(I₁ + m z²)))``

    (proportional to each other when both hold).
    """
    _flat_base_check(p)
    i1, i2, m = p.inertia[0], p.inertia[1], p.mass
    flat = i1 * i2 + m * (i1 * y[2] ** 2 + i2 * y[3] ** 2)
    symmetric = (i1 + m * (y[2] ** 2 + y[3] ** 2 + p.z**2)) * jnp.exp(_flat_base_exponent(y, p))
    return jnp.where(p.z == 0, flat, symmetric)


def flat_base_integral(y, p: FlatBaseParameters):
    """Extra integral, S2 §4.5:

    - ``z = 0``: ``F₂ = (Ĩω, Ĩω) − m(r₁² + r₂²)(Ĩω, ω)``;
    - ``I₁ = I₂, z ≠ 0``: ``F₂ = (r₁ω₁ + r₂ω₂) exp(−k z m (r₁² + r₂²)/(2(I₁ + m z²)))``.
    """
    _flat_base_check(p)
    zero = jnp.zeros((), y.dtype)
    omega = jnp.stack([y[0], y[1], zero])
    r = jnp.stack([y[2], y[3], zero])
    iw = contact_inertia(jnp.diag(p.inertia), p.mass, r) @ omega
    flat = jnp.dot(iw, iw) - p.mass * (y[2] ** 2 + y[3] ** 2) * jnp.dot(iw, omega)
    symmetric = (y[2] * y[0] + y[3] * y[1]) * jnp.exp(_flat_base_exponent(y, p))
    return jnp.where(p.z == 0, flat, symmetric)
