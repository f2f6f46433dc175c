"""Ding's equations of constrained systems in state space (S3), and their singularity.

Positions ``q`` and velocities ``v`` are independent state variables; the
constraints ``Φ(q, v, t) = A(q, t) v + A0(q, t) = 0`` are finite relations in state
space.  The state-space d'Alembert principle (S3 (13)), written for a Lagrangian
with momenta ``p = ∂T/∂v``, reads

    (ṗ − ∂pᵀ/∂q (q̇ − v) − ∂T/∂q − F)·δq − (q̇ − v)ᵀ ∂²T/∂v² δv = 0,

with ``∂Φ/∂q δq + ∂Φ/∂v δv = 0`` (S3 (9)).  With multipliers (S3 (25)) the
unknowns ``(q̇, v̇, λ)`` solve a square system of size ``2n + g`` whose matrix is
antisymmetric; on a parametrisation ``ξ`` of the constraint manifold (S3 (31),
here ``ξ = (q, v')`` from the Voronets elimination) the equations become
``M_αβ ξ̇_β = K_α`` (S3 (38)) with ``M`` antisymmetric of size ``S = 2n − g``.
Their rank is ``S − g + rank C`` with ``C = {Φ_r, Φ_s}`` the constraints' brackets
in the state-space symplectic form, so ``rank M ≤ S − g`` when the brackets
vanish — always for one constraint (S3 §4.2): the system is singular and needs
extra conditions.  Geometric constraints, for which ``∂Φ/∂v = 0``, give ``q̇ = v``
and Lagrange's equations of the first kind.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _small as small
from ._elimination import Elimination, make_elimination
from ._spec import MechanicalSpec

__all__ = ["SingularStateSpaceError", "StateSpace", "StateSpaceReport", "state_space"]


class SingularStateSpaceError(ValueError):
    """The state-space equations do not determine the motion (S3 §4.2); ``report`` says why."""

    def __init__(self, report: StateSpaceReport):
        super().__init__(
            f"the state-space equations are singular: rank M_αβ = {report.rank_generalised} < S = {report.S} "
            f"(g = {report.g} constraints, rank of their brackets {report.rank_brackets}); "
            "supplementary conditions are needed (S3 §4.2)."
        )
        self.report = report


@dataclasses.dataclass(frozen=True)
class StateSpaceReport:
    """Dimensions and ranks of the state-space equations at one state."""

    S: int  # dimension of the constraint manifold, 2n − g
    g: int  # number of constraints
    rank_generalised: int  # rank of M_αβ (S3 (38))
    rank_multiplier: int  # rank of the (2n + g) multiplier system (S3 (25))
    rank_brackets: int  # rank of C = {Φ_r, Φ_s}
    singular_values: tuple[float, ...]  # of M_αβ

    @property
    def singular(self) -> bool:
        return self.rank_generalised < self.S


def _rank(a) -> int:
    sv = np.linalg.svd(np.asarray(a, dtype=float), compute_uv=False)
    return int(np.sum(sv > 1e-9 * sv[0])) if sv.size and sv[0] > 0 else 0


class StateSpace(eqx.Module):
    """S3's multiplier equations (25) and generalised-state equations (38) of a spec."""

    spec: MechanicalSpec
    elimination: Elimination

    def _parts(self, q, v, t):
        spec, p = self.spec, self.spec.params
        pi = jnp.zeros(spec.k, q.dtype)

        def momentum(q, v, t):
            return jax.grad(spec.kinetic, argnums=1)(q, v, pi, t, p)

        p_q, p_t = jax.jacfwd(momentum, argnums=(0, 2))(q, v, t)
        force = jax.grad(spec.kinetic)(q, v, pi, t, p) + spec.applied_force(q, v, pi, t, p) - p_q.T @ v - p_t
        phi_q, phi_t = jax.jacfwd(lambda q, t: spec.constraint_residual(q, v, pi, t, p), argnums=(0, 1))(q, t)
        phi_v, _ = spec.velocity_constraints(q, pi, t, p)
        return p_q - p_q.T, spec.inertia(q, pi, t, p), force, phi_q, phi_v, phi_t

    @eqx.filter_jit
    def multiplier_system(self, q, v, t=0.0):
        """``(matrix, rhs)`` of S3 (25) in the unknowns ``(q̇, v̇, λ)``; the matrix is antisymmetric."""
        q = jnp.asarray(q)
        v, t = jnp.asarray(v, q.dtype), jnp.asarray(t, q.dtype)
        gyro, mass, force, phi_q, phi_v, phi_t = self._parts(q, v, t)
        n, g = q.shape[0], phi_v.shape[0]
        zero_n, zero_g = jnp.zeros((n, n), q.dtype), jnp.zeros((g, g), q.dtype)
        matrix = jnp.block([[gyro, mass, -phi_q.T], [-mass, zero_n, -phi_v.T], [phi_q, phi_v, zero_g]])
        return matrix, jnp.concatenate([force, -mass @ v, -phi_t])

    def manifold_point(self, xi, t=0.0):
        """``(q, v)`` of the manifold coordinates ``ξ = (q, v')``."""
        spec, n = self.spec, self.spec.n
        xi = jnp.asarray(xi)
        q, w = xi[:n], xi[n:]
        psi, b, _, _ = self.elimination.velocity_basis(
            spec, q, jnp.zeros(spec.k, q.dtype), jnp.asarray(t, q.dtype), spec.params
        )
        return q, psi @ w + b

    @eqx.filter_jit
    def generalised_system(self, xi, t=0.0):
        """``(M, K)`` of S3 (38): ``M_αβ ξ̇_β = K_α`` on the constraint manifold, ``M`` antisymmetric."""
        xi = jnp.asarray(xi)
        t = jnp.asarray(t, xi.dtype)

        def residual(xi_dot):
            (q, v), (q_dot, v_dot) = jax.jvp(self.manifold_point, (xi, t), (xi_dot, jnp.ones((), t.dtype)))
            gyro, mass, force, _, _, _ = self._parts(q, v, t)
            e_q = gyro @ q_dot + mass @ v_dot - force
            e_v = mass @ (q_dot - v)
            jac_q, jac_v = jax.jacfwd(self.manifold_point)(xi, t)
            return jac_q.T @ e_q - jac_v.T @ e_v

        zero = jnp.zeros_like(xi)
        return jax.jacfwd(residual)(zero), -residual(zero)

    def report(self, q, v, t=0.0) -> StateSpaceReport:
        """Ranks of (25) and (38) at the state ``(q, v)`` (on the constraints)."""
        q = jnp.asarray(q)
        v = jnp.asarray(v, q.dtype)
        matrix, _ = self.multiplier_system(q, v, t)
        n = self.spec.n
        g = matrix.shape[0] - 2 * n
        xi = jnp.concatenate([q, v[self.elimination.ind]])
        m_gen, _ = self.generalised_system(xi, t)
        omega, border = np.asarray(matrix[: 2 * n, : 2 * n]), np.asarray(matrix[2 * n :, : 2 * n])
        brackets = border @ np.linalg.solve(omega, border.T)
        return StateSpaceReport(
            S=2 * n - g,
            g=g,
            rank_generalised=_rank(m_gen),
            rank_multiplier=_rank(matrix),
            rank_brackets=_rank(brackets) if g else 0,
            singular_values=tuple(np.linalg.svd(np.asarray(m_gen), compute_uv=False).tolist()),
        )

    def velocity(self, xi, t=0.0):
        """``ξ̇`` from S3 (38) when ``M`` has full rank; else :class:`SingularStateSpaceError`."""
        q, v = self.manifold_point(xi, t)
        report = self.report(q, v, t)
        if report.singular:
            raise SingularStateSpaceError(report)
        m_gen, k = self.generalised_system(xi, t)
        return small.solve(m_gen, k)


def state_space(spec: MechanicalSpec, *, dependent=None, reference=None) -> StateSpace:
    """S3's state-space formulation of ``spec``; the manifold is parametrised by ``(q, v')``.

    Only deterministic, ideal specs: the random parameters and servo-constraints
    have no place in S3's principle.
    """
    if not isinstance(spec, MechanicalSpec):
        raise TypeError(f"spec={type(spec).__name__}; expected a MechanicalSpec.")
    if spec.k or spec.servo is not None:
        raise ValueError(
            "state_space: S3 treats deterministic systems with ideal constraints; this spec has "
            f"random parameters {spec.random_parameters} or servo-constraints."
        )
    return StateSpace(spec, make_elimination(spec, dependent, reference))
