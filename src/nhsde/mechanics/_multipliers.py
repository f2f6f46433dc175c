"""Routes (c) and (d) in all coordinates: multipliers (S1 (2.3)) and Gauss's principle (S1 (2.10)).

Both return accelerations that are affine in the applied force, so the same
solve gives the drift (deterministic force, constraint target) and, column by
column, the response to the random forces ``Q² V`` (target zero): the noise
enters the accelerations through the constrained inverse inertia.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import _small as small
from ._spec import MechanicalSpec

__all__ = [
    "compulsion_terms",
    "constraint_target",
    "gauss",
    "gauss_noise",
    "lagrange_terms",
    "multiplier_noise",
    "multipliers",
]


def _one(t):
    return jnp.ones((), t.dtype)


def lagrange_terms(spec: MechanicalSpec, q, v, pi, t, p):
    """``(M, h)`` of Lagrange's equations ``M q̈ + h = Q² V + reactions``.

    ``h = d/dt(∂T/∂q̇)|_{q̈=0} − ∂T/∂q − (Q¹ − ∂Π/∂q − ∂R/∂q̇)`` (S0 (1.6)).
    """
    (grad_q, _), (_, d_momentum) = jax.jvp(
        lambda q, t: jax.grad(spec.kinetic, argnums=(0, 1))(q, v, pi, t, p), (q, t), (v, _one(t))
    )  # one reverse pass of T gives ∂T/∂q and, along the motion, d/dt(∂T/∂q̇)
    h = d_momentum - grad_q - spec.applied_force(q, v, pi, t, p)
    return spec.inertia(q, pi, t, p), h


def constraint_target(spec: MechanicalSpec, q, v, pi, t, p, rate):
    """``r`` in ``(A; C) q̈ = r``: S1 (1.5) with Baumgarte stabilisation at ``rate`` κ.

    ``r = −d/dt((A; C) q̇ + (A0; C0))|_{q̈=0} − 2κ c − κ² f`` with ``c`` the velocity
    residual and ``f`` the holonomic residual; on the constraint manifold the
    stabilisation vanishes.
    """

    def residual(q, t):
        return spec.constraint_residual(q, v, pi, t, p)

    c, dc = jax.jvp(residual, (q, t), (v, _one(t)))
    if not rate:
        return -dc
    f = jnp.concatenate([spec.holonomic_residual(q, pi, t, p), jnp.zeros(spec.n_servo, q.dtype)])
    return -dc - 2 * rate * c - rate**2 * f


def _with_reactions(spec: MechanicalSpec, q, pi, t, p):
    """``solve(force, r) -> (q̈, λ)`` of ``M q̈ = force + Dᵀλ``, ``(A; C) q̈ = r`` (Schur complement ``(A; C) M⁻¹ Dᵀ``).

    The reactions act along the displacement rows ``D = (A; realisation)``; with
    ideal constraints only, ``D = A``.
    """
    rows, _ = spec.velocity_constraints(q, pi, t, p)
    react = spec.displacement_constraints(q, pi, t, p)
    chol = small.cholesky(spec.inertia(q, pi, t, p))

    def inverse_mass(x):
        return small.cho_solve(chol, x)

    response = inverse_mass(react.T)
    schur = small.matmul(rows, response)

    def solve(force, target):  # force (n,) and target (m,), or one column per channel: (n, l) and (m, l)
        free = inverse_mass(force)
        if rows.shape[0] == 0:
            return free, jnp.zeros((0, *free.shape[1:]), free.dtype)
        if spec.servo is None:  # D = A: the Schur complement A M⁻¹ Aᵀ is symmetric positive definite
            lam = small.spd_solve(schur, target - small.matmul(rows, free))
        else:
            lam = small.solve(schur, target - small.matmul(rows, free))
        return free + small.matmul(response, lam), lam

    return solve


def multipliers(spec: MechanicalSpec, q, v, pi, t, p, rate=0.0):
    """``(q̈, λ)`` of Lagrange's equations with multipliers ``M q̈ + h = Dᵀλ`` (S1 (2.3)), drift part."""
    _, h = lagrange_terms(spec, q, v, pi, t, p)
    return _with_reactions(spec, q, pi, t, p)(-h, constraint_target(spec, q, v, pi, t, p, rate))


def multiplier_noise(spec: MechanicalSpec, q, v, pi, t, p):
    """``(q̈_V, λ_V)``: the parts of ``q̈`` and ``λ`` proportional to ``V``, one column per channel."""
    force = spec.random_force(q, v, pi, t, p)
    return _with_reactions(spec, q, pi, t, p)(force, jnp.zeros((spec.n_ideal + spec.n_servo, force.shape[1]), q.dtype))


def compulsion_terms(spec: MechanicalSpec, q, v, pi, t, p):
    """``(M_N, F)`` with the compulsion ``Z(q̈) = ½ (q̈ − M_N⁻¹F)ᵀ M_N (q̈ − M_N⁻¹F)`` + const.

    From Nielsen's form ``∂Ṫ/∂q̇ − 2 ∂T/∂q = M_N q̈ + n₀`` (``Ṫ`` the derivative of
    ``T`` along ``(q̇, q̈)``): ``F = Q¹ − ∂Π/∂q − ∂R/∂q̇ − n₀``, the generalised-coordinate
    form of S1 (2.10), ``Z = ½ Σ m_i (ẍ_i − X_i/m_i)²``.
    """

    def t_dot(v, a):
        return jax.jvp(lambda q, v, t: spec.kinetic(q, v, pi, t, p), (q, v, t), (v, a, _one(t)))[1]

    def nielsen(a):
        return jax.grad(t_dot)(v, a) - 2 * jax.grad(spec.kinetic)(q, v, pi, t, p)

    zero = jnp.zeros_like(v)
    return jax.jacfwd(nielsen)(zero), spec.applied_force(q, v, pi, t, p) - nielsen(zero)


def _least_compulsion(spec: MechanicalSpec, mass, q, pi, t, p):
    """``solve(F, r_A, r_C) -> q̈``: the minimiser of the compulsion over ``A q̈ = r_A`` (S1 (2.10)).

    Udwadia–Kalaba form of the minimiser: with ``M_N = L Lᵀ``,
    ``q̈ = a + L⁻ᵀ (A L⁻ᵀ)⁺ (r_A − A a)``, ``a = M_N⁻¹ F`` (Moore–Penrose inverse).  The rows ``A`` have full rank
    (checked at the initial state), so ``(A L⁻ᵀ)⁺ = L⁻¹Aᵀ (A M_N⁻¹ Aᵀ)⁻¹`` and
    ``q̈ = a + M_N⁻¹Aᵀ (A M_N⁻¹ Aᵀ)⁻¹ (r_A − A a)``: small unrolled factorisations, no SVD.
    Servo-constraints (S1 §3): their reactions ``realisationᵀ μ`` join the force
    and ``μ`` is fixed by ``C q̈ = r_C``.
    """
    a_rows, _ = spec.ideal_constraints(q, pi, t, p)
    c_rows, _, d_rows = spec.servo_constraints(q, pi, t, p)
    chol = small.cholesky(mass)
    inverse_rows = small.cho_solve(chol, a_rows.T)  # M_N⁻¹ Aᵀ
    schur = small.matmul(a_rows, inverse_rows)

    def least(f, t_a):
        free = small.cho_solve(chol, f)
        if not spec.n_ideal:
            return free
        return free + small.matmul(inverse_rows, small.spd_solve(schur, t_a - small.matmul(a_rows, free)))

    if spec.servo is None:
        return lambda f, t_a, t_c: least(f, t_a)
    response = jax.vmap(least, in_axes=(0, None), out_axes=1)(d_rows, jnp.zeros(spec.n_ideal, q.dtype))

    def solve(f, t_a, t_c):
        acc = least(f, t_a)
        mu = small.solve(small.matmul(c_rows, response), t_c - small.matmul(c_rows, acc))
        return acc + small.matmul(response, mu)

    return solve


def gauss(spec: MechanicalSpec, q, v, pi, t, p, rate=0.0):
    """``q̈`` of least compulsion, drift part (S1 (2.10))."""
    mass, force = compulsion_terms(spec, q, v, pi, t, p)
    target = constraint_target(spec, q, v, pi, t, p, rate)
    return _least_compulsion(spec, mass, q, pi, t, p)(force, target[: spec.n_ideal], target[spec.n_ideal :])


def gauss_noise(spec: MechanicalSpec, q, v, pi, t, p):
    """``q̈_V``: least-compulsion response to the random forces ``Q² V``, one column per channel."""
    mass, _ = compulsion_terms(spec, q, v, pi, t, p)
    solve = _least_compulsion(spec, mass, q, pi, t, p)
    t_a, t_c = jnp.zeros(spec.n_ideal, q.dtype), jnp.zeros(spec.n_servo, q.dtype)
    return jax.vmap(solve, in_axes=(1, None, None), out_axes=1)(spec.random_force(q, v, pi, t, p), t_a, t_c)
