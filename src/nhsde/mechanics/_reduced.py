"""Routes (a) and (b): the reduced Voronets equations and their Hamiltonian form, S0 (1.7)–(1.15).

All in the independent velocities ``q̇'`` (momenta ``p'``) after eliminating
``q̇'' = B' q̇' + B''``; ``T* = T(q, Ψ q̇' + b, t)`` is the kinetic energy after
elimination (the star of S0).  Every derivative is taken by JAX autodiff.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import _small as small
from ._elimination import Elimination
from ._multipliers import lagrange_terms
from ._spec import MechanicalSpec

__all__ = ["hamilton", "hamilton_velocity", "hamiltonian", "maggi", "momentum", "reduced_noise", "voronets"]


def _one(t):
    return jnp.ones((), t.dtype)


def _velocity(spec, elim, pi, p, w):
    """``(q, t) ↦ Ψ(q, t) q̇' + b(q, t)``: the full velocity."""

    def fn(q, t):
        psi, b, _, _ = elim.velocity_basis(spec, q, pi, t, p)
        return psi @ w + b

    return fn


def _t_star(spec, elim, pi, p):
    """``T*(q, q̇', t)``."""
    return lambda q, w, t: spec.kinetic(q, _velocity(spec, elim, pi, p, w)(q, t), pi, t, p)


def _combine(elim, b_prime, g):
    """``g_s + Σ_i B'_is g_i``: a covector on q projected on the independent displacements."""
    return g[elim.ind] + b_prime.T @ g[elim.dep]


def _nonholonomic(spec, elim, q, w, v, psi, pi, t, p):
    """The last term of S0 (1.8): ``Σ_i (∂T/∂q̇_i)* [Ḃ'_is − ∂Λ_i/∂q_s − Σ_κ B'_κs ∂Λ_i/∂q_κ]``.

    ``Λ = B' q̇' + B''`` at fixed ``q̇'``; ``Ḃ'`` is the derivative along the motion.
    """
    if not elim.dependent:
        return jnp.zeros_like(w)
    (bp_q, bp_t), (bpp_q, _) = jax.jacfwd(lambda q, t: elim.velocity_basis(spec, q, pi, t, p)[2:], argnums=(0, 1))(q, t)
    b_prime_dot = bp_q @ v + bp_t
    jac_lambda = jnp.einsum("isk,s->ik", bp_q, w) + bpp_q
    p_dependent = jax.grad(spec.kinetic, argnums=1)(q, v, pi, t, p)[elim.dep]
    return (b_prime_dot - jac_lambda @ psi).T @ p_dependent


def voronets(spec: MechanicalSpec, elim: Elimination, q, w, pi, t, p):
    """``(G, F, q̇)`` of the reduced equations ``G q̈' = F + Φ V``, S0 (1.8), (1.12).

    ``G = ∂²T*/∂q̇'²`` and ``F`` collects
    ``−d/dt(∂T*/∂q̇')|_{q̈'=0} + ∂(T*−Π)/∂q' + B'ᵀ ∂(T*−Π)/∂q'' − ∂R*/∂q̇' + Q¹' + B'ᵀQ¹''``
    and the nonholonomic term; ``Φ`` is :func:`reduced_noise`.
    """
    t_star = _t_star(spec, elim, pi, p)
    psi, b, b_prime, _ = elim.velocity_basis(spec, q, pi, t, p)
    v = psi @ w + b
    g = jax.hessian(lambda w: spec.kinetic(q, psi @ w + b, pi, t, p))(w)
    (grad_t, _), (_, d_momentum) = jax.jvp(lambda q, t: jax.grad(t_star, argnums=(0, 1))(q, w, t), (q, t), (v, _one(t)))
    grad_l = grad_t - jax.grad(spec.potential_energy)(q, pi, t, p)
    grad_r = jax.grad(lambda w: spec.rayleigh(q, psi @ w + b, pi, t, p))(w)
    rhs = (
        -d_momentum
        + _combine(elim, b_prime, grad_l)
        - grad_r
        + psi.T @ spec.disturbing_force(q, v, pi, t, p)
        + _nonholonomic(spec, elim, q, w, v, psi, pi, t, p)
    )
    return g, rhs, v


def maggi(spec: MechanicalSpec, elim: Elimination, q, w, pi, t, p):
    """``(G, F, q̇)`` for servo-constraints: ``Ψ_δᵀ (M q̈ + h) = Ψ_δᵀ Q² V`` with ``q̈ = Ψ q̈' + γ``.

    d'Alembert–Lagrange over the displacements of S1 (3.2) (``δq = Ψ_δ δq'``)
    while the velocities obey the servo-constraints (``q̇ = Ψ q̇' + b``): Beghin's
    equations; for ideal constraints ``Ψ_δ = Ψ`` and they are the Voronets equations.
    """
    psi, b, _, _ = elim.velocity_basis(spec, q, pi, t, p)
    v, gamma = jax.jvp(_velocity(spec, elim, pi, p, w), (q, t), (psi @ w + b, _one(t)))
    psi_d = elim.displacement_basis(spec, q, pi, t, p)
    mass, h = lagrange_terms(spec, q, v, pi, t, p)
    return psi_d.T @ mass @ psi, -psi_d.T @ (mass @ gamma + h), v


def reduced_noise(spec: MechanicalSpec, elim: Elimination, q, v, pi, t, p):
    """``(G, Φ)``: ``G = Ψ_δᵀ M Ψ`` (``= ∂²T*/∂q̇'²`` for ideal constraints) and ``Φ = Ψ_δᵀ Q²``."""
    psi = elim.velocity_basis(spec, q, pi, t, p)[0]
    psi_d = psi if spec.servo is None else elim.displacement_basis(spec, q, pi, t, p)
    return psi_d.T @ spec.inertia(q, pi, t, p) @ psi, psi_d.T @ spec.random_force(q, v, pi, t, p)


def momentum(spec: MechanicalSpec, elim: Elimination, q, w, pi, t, p):
    """``p' = ∂T*/∂q̇'`` (S0 (1.13))."""
    return jax.grad(_t_star(spec, elim, pi, p), argnums=1)(q, w, t)


def hamiltonian(spec: MechanicalSpec, elim: Elimination, pi, p):
    """``H(q, p', t) = p'·q̇' − L*``, ``L* = T* − Π``, by the Legendre transform of S0 (1.13).

    ``T*`` is quadratic in ``q̇'``: ``p' = G q̇' + G₁`` inverts by a Cholesky solve.
    """
    t_star = _t_star(spec, elim, pi, p)

    def ham(q, z, t):
        zero = jnp.zeros_like(z)
        g = jax.hessian(t_star, argnums=1)(q, zero, t)
        g1 = jax.grad(t_star, argnums=1)(q, zero, t)
        w = small.spd_solve(g, z - g1)
        return z @ w - t_star(q, w, t) + spec.potential_energy(q, pi, t, p)

    return ham


def hamilton_velocity(spec: MechanicalSpec, elim: Elimination, q, z, pi, t, p):
    """``q̇``: ``q̇' = ∂H/∂p' ≡ Y``, ``q̇'' = B' Y + B'' ≡ Λ`` (1.13)–(1.14)."""
    w = jax.grad(hamiltonian(spec, elim, pi, p), argnums=1)(q, z, t)
    psi, b, _, _ = elim.velocity_basis(spec, q, pi, t, p)
    return psi @ w + b


def hamilton(spec: MechanicalSpec, elim: Elimination, q, z, pi, t, p):
    """``(U, q̇)``: ``ṗ' = U + U'' V`` with ``U'' = Ψᵀ Q²`` (1.13)–(1.14).

    ``U = −∂H/∂q' − B'ᵀ ∂H/∂q'' − ∂R*/∂q̇' + Ψᵀ Q¹`` plus the nonholonomic term
    of (1.8) (``∂L*/∂q = −∂H/∂q`` at fixed momenta).
    """
    grad_q, w = jax.grad(hamiltonian(spec, elim, pi, p), argnums=(0, 1))(q, z, t)
    psi, b, b_prime, _ = elim.velocity_basis(spec, q, pi, t, p)
    v = psi @ w + b
    grad_r = jax.grad(lambda w: spec.rayleigh(q, psi @ w + b, pi, t, p))(w)
    u = (
        -_combine(elim, b_prime, grad_q)
        - grad_r
        + psi.T @ spec.disturbing_force(q, v, pi, t, p)
        + _nonholonomic(spec, elim, q, w, v, psi, pi, t, p)
    )
    return u, v
