"""Convex surfaces of rolling bodies by their inverse Gauss map ``r(γ)``, S2 (1.5).

All vectors are in the body's principal axes with the origin at the centre of
mass.  ``γ`` is the unit normal of the supporting surface at the contact,
pointing into the body (on a horizontal plane: the upward vertical), so the
body's outward normal at the contact point is ``−γ`` and S2 (1.5) reads
``γ = −∇f/|∇f|`` at ``r`` for a body ``f(r) ≤ 0``.  ``contact_point(γ)`` is
``r(γ)``, the vector from the centre of mass to the contact point.

``r`` is extended off the unit sphere as ``r(γ/|γ|)`` (homogeneous of degree 0):
then ``(∂r/∂γ)ᵀγ = 0`` everywhere, which keeps ``γ² = 1`` and ``(ω, γ) = 0``
exact first integrals of the rolling equations in the whole ``(ω, γ)`` space.

On the unit sphere, ``−∂r/∂γ`` restricted to the tangent plane is symmetric and
its eigenvalues are the principal radii of curvature of the body at the contact
(the inverse of the Weingarten map): the surface is convex iff they are ``≥ 0``.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._misc import is_concrete
from .._params import AbstractParameters, parameter
from ..mechanics._small import matmul

__all__ = [
    "AbstractSurface",
    "BodyOfRevolution",
    "Disk",
    "Ellipsoid",
    "ImplicitSurface",
    "Sphere",
    "SphericalCavity",
    "fibonacci_directions",
    "tangent_basis",
]


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` nearly uniform unit vectors (a Fibonacci lattice), away from the poles ``±e₃``."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    s = np.sqrt(1.0 - z**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def tangent_basis(n):
    """Two unit vectors spanning the plane orthogonal to the unit vector ``n``."""
    a = jnp.where(jnp.abs(n[0]) < 0.9, jnp.array([1.0, 0.0, 0.0], n.dtype), jnp.array([0.0, 1.0, 0.0], n.dtype))
    t1 = jnp.cross(n, a)
    t1 = t1 / jnp.linalg.norm(t1)
    return jnp.stack([t1, jnp.cross(n, t1)], axis=1)


class AbstractSurface(AbstractParameters):
    """A convex body surface given by its inverse Gauss map ``r(γ)``, S2 (1.5).

    Subclasses implement ``_contact(n)`` for a unit vector ``n`` (this is how a
    surface is given "as ``r(γ)``"); their geometric parameters are pytree leaves.
    """

    @abc.abstractmethod
    def _contact(self, n) -> jax.Array:
        """``r`` for a unit normal ``n`` (pointing into the body)."""

    def contact_point(self, gamma):
        """``r(γ/|γ|)``: centre of mass → contact point."""
        return self._contact(gamma / jnp.linalg.norm(gamma))

    def curvature_radii(self, gamma):
        """The two principal radii of curvature at the contact point of normal ``γ``."""
        n = gamma / jnp.linalg.norm(gamma)
        jac = jax.jacfwd(self.contact_point)(n)
        t = tangent_basis(n)
        s = -(t.T @ jac @ t)
        return jnp.linalg.eigvalsh(0.5 * (s + s.T))

    def _check_convex(self, directions: np.ndarray, scale) -> None:
        """Raise ``ValueError`` if a radius of curvature is negative at one of ``directions``."""
        radii = np.asarray(jax.jit(jax.vmap(self.curvature_radii))(jnp.asarray(directions)))
        bad = np.min(radii, axis=1) < -1e-9 * float(scale)
        if np.any(~np.isfinite(radii)) or np.any(bad):
            i = int(np.argmax(bad | ~np.isfinite(radii).all(axis=1)))
            raise ValueError(
                f"{type(self).__name__}: the surface is not convex: radii of curvature {radii[i].tolist()} "
                f"at γ = {np.round(directions[i], 4).tolist()}; a rolling body needs radii ≥ 0 everywhere."
            )


class Sphere(AbstractSurface):
    """Ball of radius ``R`` whose centre of mass is displaced by ``offset`` from its centre.

    ``r = −R γ − c`` with ``c`` = ``offset`` = (centre of mass) − (geometric centre),
    S2 §3.4–3.5 (``c = 0``: balanced ball).
    """

    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="radius R")
    offset: jnp.ndarray = parameter(default=(0.0, 0.0, 0.0), doc="c = centre of mass − geometric centre")

    def _contact(self, n):
        return -self.radius * n - self.offset


class SphericalCavity(AbstractSurface):
    """Spherical cavity of radius ``R`` in the body: rolling case S2 Fig. 2c.

    The fixed sphere lies inside the cavity, so the body's surface is concave
    there: ``r = R γ − c``, ``c`` = (centre of mass) − (cavity centre).  Only
    admitted on a sphere of curvature ``k > 1/R``.
    """

    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="cavity radius R")
    offset: jnp.ndarray = parameter(default=(0.0, 0.0, 0.0), doc="c = centre of mass − cavity centre")

    def _contact(self, n):
        return self.radius * n - self.offset


class Ellipsoid(AbstractSurface):
    """Triaxial ellipsoid ``(x, B⁻¹x) = 1`` about its centre, ``B = diag(a²)``, S2 §3.3.

    ``r = −Bγ/√(γ, Bγ) − c``, ``c`` = ``offset`` = (centre of mass) − (centre).

    Arguments:
        semi_axes: ``a₁, a₂, a₃ > 0``.
        offset: ``c`` in the body axes.

    Examples:
        At the pole ``γ = e₃`` the contact point is ``−a₃ e₃`` and the radii of curvature are ``a₁²/a₃``,
        ``a₂²/a₃``:

        >>> import jax.numpy as jnp
        >>> from nhsde import bodies
        >>> surface = bodies.Ellipsoid(semi_axes=(1.0, 2.0, 3.0))
        >>> up = jnp.array([0.0, 0.0, 1.0])
        >>> print(surface.contact_point(up) + 0.0, surface.curvature_radii(up).round(4))
        [ 0.  0. -3.] [0.3333 1.3333]
        >>> body = bodies.RigidBody(mass=2.0, inertia=(1.0, 2.0, 3.0), surface=surface)
        >>> body.inertia.shape
        (3, 3)
    """

    semi_axes: jnp.ndarray = parameter(default=(1.0, 1.0, 1.0), lower=0.0, strict=True, doc="a₁, a₂, a₃")
    offset: jnp.ndarray = parameter(default=(0.0, 0.0, 0.0), doc="c = centre of mass − centre")

    def __check_init__(self):
        if is_concrete(self.semi_axes) and np.shape(self.semi_axes) != (3,):
            raise ValueError(f"Ellipsoid: semi_axes has shape {np.shape(self.semi_axes)}; expected (3,).")

    def _contact(self, n):
        bn = self.semi_axes**2 * n
        return -bn / jnp.sqrt(matmul(n, bn)) - self.offset


class Disk(AbstractSurface):
    """Thin disk of radius ``R`` normal to ``e₃``: ``r = −R γ⊥/|γ⊥| − c``, ``γ⊥ = γ − γ₃e₃``.

    ``c`` = ``offset`` = (centre of mass) − (disk centre).  The Gauss map is
    singular when the disk lies flat (``γ = ±e₃``: a face contact, not a point).
    """

    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="radius R")
    offset: jnp.ndarray = parameter(default=(0.0, 0.0, 0.0), doc="c = centre of mass − disk centre")

    def _contact(self, n):
        perp = n.at[2].set(0.0)
        return -self.radius * perp / jnp.linalg.norm(perp) - self.offset


class BodyOfRevolution(AbstractSurface):
    """Body of revolution about ``e₃`` from its profile: the height ``Z(γ₃)`` of the centre of mass.

    ``Z(u)`` is the height of the centre of mass above a plane on which the body
    rests with ``γ₃ = u = cos θ`` (S0 §5 writes it ``z(θ)``); it is the body's
    support function.  Then S2 (3.1): ``r = (f₁γ₁, f₁γ₂, f₂)`` with

        f₁ = −(Z − uZ'),     f₂ = −(uZ + (1 − u²)Z'),

    smooth through the upright position ``u = ±1`` where Euler angles are singular.
    Principal radii of curvature: ``Z − uZ'`` (parallel) and
    ``Z − uZ' + (1 − u²)Z''`` (meridian); both must be ``≥ 0``.

    ``height(u, shape)`` is a pure function; ``shape`` (an array) holds its
    parameters as pytree leaves.  Example, a ball of radius ``R`` with the centre
    of mass ``c`` below its centre: ``height = lambda u, s: s[0] − s[1]·u``.
    """

    height: Callable = eqx.field(static=True)
    shape: jnp.ndarray = parameter(default=(), doc="parameters of the profile")

    def __init__(self, height: Callable, shape=()):
        if not callable(height):
            raise TypeError(f"BodyOfRevolution: height={height!r} must be a function height(u, shape) -> Z.")
        self.height = height
        self.shape = jnp.asarray(shape)

    def __check_init__(self):
        if not is_concrete(self.shape):
            return
        u = jnp.linspace(-1.0, 1.0, 401)
        z, rho1, rho2 = (np.asarray(a) for a in jax.jit(jax.vmap(self._radii))(u))
        if not np.all(np.isfinite(z)) or np.min(z) <= 0:
            i = int(np.argmin(np.where(np.isfinite(z), z, -np.inf)))
            raise ValueError(
                f"BodyOfRevolution: height Z(u={float(u[i]):.3g}) = {float(z[i]):.4g}; the centre of mass must be "
                "inside the body (Z > 0 for every u in [−1, 1])."
            )
        scale = float(np.max(z))
        for name, rho in (("parallel", rho1), ("meridian", rho2)):
            if np.min(rho) < -1e-9 * scale:
                i = int(np.argmin(rho))
                raise ValueError(
                    f"BodyOfRevolution: the profile is not convex: {name} radius of curvature "
                    f"{float(rho[i]):.4g} < 0 at γ₃ = {float(u[i]):.3g}; a rolling body needs radii ≥ 0."
                )

    def _radii(self, u):
        z, dz = jax.value_and_grad(self.height)(u, self.shape)
        d2z = jax.grad(jax.grad(self.height))(u, self.shape)
        return z, z - u * dz, z - u * dz + (1 - u**2) * d2z

    def _contact(self, n):
        u = n[2]
        z, dz = jax.value_and_grad(self.height)(u, self.shape)
        f1 = -(z - u * dz)
        f2 = -(u * z + (1 - u**2) * dz)
        return jnp.stack([f1 * n[0], f1 * n[1], f2])


class ImplicitSurface(AbstractSurface):
    """Convex body ``f(x, shape) ≤ 0`` (``f`` convex, ``f(0) < 0``): ``r(γ)`` by Newton's method.

    The contact point solves ``∇f(r) + λγ = 0``, ``f(r) = 0``, ``λ > 0`` (S2 (1.5)),
    from the ray point ``r₀ = −sγ`` with ``f(r₀) = 0``.  ``size`` bounds the
    body's extent (start of the ray search).  Derivatives of ``r`` come from two
    Newton steps taken at the converged point (exact to rounding, any order).
    """

    f: Callable = eqx.field(static=True)
    shape: jnp.ndarray = parameter(default=(), doc="parameters of f")
    size: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="bound on |x| over the body")
    iterations: int = eqx.field(static=True, default=40)

    def __init__(self, f: Callable, shape=(), size=1.0, iterations: int = 40):
        if not callable(f):
            raise TypeError(f"ImplicitSurface: f={f!r} must be a function f(x, shape) -> scalar.")
        self.f = f
        self.shape = jnp.asarray(shape)
        self.size = jnp.asarray(size)
        self.iterations = int(iterations)

    def __check_init__(self):
        if not is_concrete(self.shape, self.size):
            return
        inside = float(self.f(jnp.zeros(3), self.shape))
        if not inside < 0:
            raise ValueError(
                f"ImplicitSurface: f(0) = {inside:.4g}; the centre of mass (the origin) must be "
                "inside the body, f(0) < 0."
            )
        dirs = fibonacci_directions(128)
        residual = np.asarray(jax.jit(jax.vmap(self._residual))(jnp.asarray(dirs)))
        if not np.all(residual < 1e-8):
            i = int(np.argmax(np.where(np.isfinite(residual), residual, np.inf)))
            raise ValueError(
                f"ImplicitSurface: Newton's method did not find the contact point for γ = "
                f"{np.round(dirs[i], 4).tolist()} (residual {residual[i]:.3g}); is f convex with f(0) < 0 and size "
                f"= {float(self.size):g} ≥ the body's extent?"
            )
        self._check_convex(dirs, self.size)

    def _newton(self, x, lam, n):
        grad = jax.grad(self.f)(x, self.shape)
        hess = jax.hessian(self.f)(x, self.shape)
        a = jnp.block([[hess, n[:, None]], [grad[None, :], jnp.zeros((1, 1), x.dtype)]])
        rhs = -jnp.concatenate([grad + lam * n, self.f(x, self.shape)[None]])
        step = jnp.linalg.solve(a, rhs)
        return x + step[:3], lam + step[3]

    def _solve(self, n):
        n = jax.lax.stop_gradient(n)

        def ray(_, s):
            phi, dphi = jax.jvp(lambda s: self.f(-s * n, self.shape), (s,), (jnp.ones_like(s),))
            return s - phi / dphi

        s = jax.lax.fori_loop(0, self.iterations, ray, jnp.asarray(self.size, n.dtype))
        x = -s * n
        lam = jnp.linalg.norm(jax.grad(self.f)(x, self.shape))
        return jax.lax.fori_loop(0, self.iterations, lambda _, c: self._newton(c[0], c[1], n), (x, lam))

    def _residual(self, n):
        x, lam = self._solve(n)
        grad = jax.grad(self.f)(x, self.shape)
        return (
            jnp.linalg.norm(grad + lam * n) / jnp.abs(lam)
            + jnp.abs(self.f(x, self.shape))
            + jnp.where(lam > 0, 0.0, 1.0)
        )

    def _contact(self, n):
        x, lam = jax.lax.stop_gradient(self._solve(n))
        x, lam = self._newton(x, lam, n)
        x, lam = self._newton(x, lam, n)
        return x
