"""Invariant measures: the Liouville equation ``div(ρ v) = 0`` by automatic differentiation.

A flow ``ẏ = v(y)`` preserves the measure ``ρ(y) dy`` iff ``div(ρ v) = 0``
(S2 §2).  On an invariant manifold cut out by first integrals (e.g.
``γ² = 1, (ω, γ) = 0``), the residual at points of the manifold decides whether
the measure induced there is invariant, provided those integrals are exact
integrals of the vector field in a neighbourhood (true of
:class:`nhsde.bodies.RollingField`).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._misc import FAST_COMPILE, cast_floats
from ..bodies import tangent_basis
from ._inputs import state_batch

__all__ = ["LiouvilleCheck", "MeasureObstruction", "check_invariant_measure", "divergence", "measure_obstruction"]

# The checks run once per vector field: they are compiled with FAST_COMPILE, for compile time rather than run
# time (about half the compile time of the default optimisation on CPU, for twice a run time of milliseconds).


def divergence(vector_field: Callable, y, params, t=0.0):
    """``div v = Σᵢ ∂vᵢ/∂yᵢ`` at ``y`` for ``v = vector_field(t, y, params)``."""
    return jnp.trace(jax.jacfwd(lambda z: vector_field(t, z, params))(y))


class LiouvilleCheck(eqx.Module):
    """Liouville residuals at each state.

    ``residual = div(ρ v)/ρ`` (units 1/time) and ``relative = |div(ρ v)| / Σᵢ|∂ᵢ(ρ vᵢ)|``
    (dimensionless: the cancellation achieved among the terms of the divergence;
    ``O(1)`` when ``ρ`` is not invariant).
    """

    residual: Float[Array, " n"]
    relative: Float[Array, " n"]

    @property
    def max_relative(self) -> float:
        return float(jnp.max(self.relative))

    @property
    def max_residual(self) -> float:
        return float(jnp.max(jnp.abs(self.residual)))


@partial(jax.jit, static_argnums=(0, 1), compiler_options=FAST_COMPILE)
def _liouville(vector_field, density, states, params, t):
    def one(y):
        rho = density(y, params)
        terms = jnp.diagonal(jax.jacfwd(lambda z: density(z, params) * vector_field(t, z, params))(y))
        return rho, jnp.sum(terms) / rho, jnp.abs(jnp.sum(terms)) / jnp.sum(jnp.abs(terms))

    return jax.vmap(one)(states)


def check_invariant_measure(vector_field: Callable, density: Callable, states, params, t=0.0) -> LiouvilleCheck:
    """Liouville residual ``div(ρ v)`` of the density ``density(y, params)`` at each of ``states``.

    ``vector_field(t, y, params)`` is the flow (e.g. a system's ``drift_fn``);
    ``states`` is ``(n, d)``.  ``ρ`` must be positive and finite at every state.

    Arguments:
        vector_field: the flow ``v(t, y, params)``.
        density: ``ρ(y, params) > 0``, the candidate invariant density.
        states: ``(n, d)`` states at which the Liouville equation ``div(ρ v) = 0`` is checked.
        params: the parameters passed to both.
        t: the time at which ``v`` is evaluated.

    Returns:
        a :class:`LiouvilleCheck` of the residual ``div(ρ v)/ρ`` and its relative size per state.

    Examples:
        A rotation preserves the Gaussian density ``e^{−|y|²/2}``:

        >>> import jax.numpy as jnp
        >>> from nhsde import analysis
        >>> def rotation(t, y, p):
        ...     return jnp.array([y[1], -y[0]])
        >>> def gaussian(y, p):
        ...     return jnp.exp(-0.5 * (y @ y))
        >>> check = analysis.check_invariant_measure(rotation, gaussian, jnp.array([[1.0, 0.5], [0.3, -2.0]]), None)
        >>> check.max_relative
        0.0
    """
    states = state_batch(states)
    params = cast_floats(params, states.dtype)
    rho, residual, relative = _liouville(vector_field, density, states, params, jnp.asarray(t, states.dtype))
    rho = np.asarray(rho)
    if not np.all(np.isfinite(rho) & (rho > 0)):
        i = int(np.argmax(~(np.isfinite(rho) & (rho > 0))))
        raise ValueError(
            f"density={float(rho[i])!r} at state {i} ({np.asarray(states[i]).tolist()}); a density "
            "must be positive and finite."
        )
    return LiouvilleCheck(residual=residual, relative=relative)


class MeasureObstruction(eqx.Module):
    """At each ``γ``: ``gradient`` = the tangent field ``g`` that ``∇ log ρ`` of a density ``ρ(γ)`` must equal,
    ``curl = (γ, rot g)``, and ``residual``: the part of the Liouville equation no ``g`` can cancel
    (relative to ``|a|``; zero by construction on the rubber manifold)."""

    curl: Float[Array, " n"] | None
    gradient: Float[Array, "n 3"]
    residual: Float[Array, " n"]


def _obstruction(vector_field, gamma, params, rubber, with_curl):
    def solve(x):
        n = x / jnp.linalg.norm(x)
        # div v and γ̇ are linear in ω: a = ∇_ω div v and L = ∂γ̇/∂ω from the values at ω = 0, e₁, e₂, e₃
        omegas = jnp.concatenate([jnp.zeros((1, 3), n.dtype), jnp.eye(3, dtype=n.dtype)])
        states = jax.vmap(lambda w: jnp.concatenate([w, n]))(omegas)
        div = jax.vmap(lambda y: divergence(vector_field, y, params))(states)
        a = div[1:] - div[0]
        lin = jax.vmap(lambda y: vector_field(0.0, y, params)[3:6])(states[1:]).T
        t = tangent_basis(n)
        # (a, e) + (g, L e) = 0 for e ⊥ γ (rubber) or every e (classic); g = t c, c ∈ ℝ²
        basis = t if rubber else jnp.concatenate([t, n[:, None]], axis=1)
        lhs, rhs = basis.T @ lin.T @ t, -(basis.T @ a)
        c = jnp.linalg.solve(lhs.T @ lhs, lhs.T @ rhs)  # least squares (exact when rubber: lhs is 2×2)
        return t @ c, jnp.linalg.norm(lhs @ c - rhs) / jnp.linalg.norm(a)

    gradient, residual = solve(gamma)
    if not with_curl:
        return None, gradient, residual
    jac = jax.jacfwd(lambda x: solve(x)[0])(gamma)
    curl = jnp.stack([jac[2, 1] - jac[1, 2], jac[0, 2] - jac[2, 0], jac[1, 0] - jac[0, 1]])
    return jnp.dot(gamma, curl), gradient, residual


def measure_obstruction(
    vector_field: Callable, gammas, params, *, rubber: bool = True, with_curl: bool = True
) -> MeasureObstruction:
    """Whether a rolling field on ``(ω, γ)`` can have an invariant measure ``ρ(γ) dω dγ``: S2 (2.5), (2.21).

    With ``ẏ = v(ω, γ)`` quadratic in ``ω`` (plus an ``ω``-free potential part),
    the Liouville equation for ``ρ(γ)`` reads ``(a, ω) + (∇ log ρ, γ̇) = 0`` with
    ``a = ∇_ω div v`` and ``γ̇ = Lω`` linear in ``ω``, for all ``ω ⊥ γ`` (rubber
    rolling, on ``(ω, γ) = 0``) or all ``ω`` (classic rolling).  This fixes the
    tangential gradient ``g = ∇ log ρ`` pointwise (classic: only if the third
    equation, the ``residual``, vanishes), and a density exists iff ``g`` is a
    gradient on the sphere: its surface curl ``(γ, rot g)`` vanishes (S2 Theorems
    2.2, 2.4; an analytic measure can be taken to depend on ``γ`` only).
    ``with_curl=False`` skips the curl (one derivative order less to compile).
    """
    gammas = state_batch(gammas, "gammas")
    if gammas.shape[1] != 3:
        raise ValueError(f"gammas has shape {gammas.shape}; expected (n, 3) unit vectors.")
    params = cast_floats(params, gammas.dtype)
    return MeasureObstruction(*_obstructions(vector_field, gammas, params, bool(rubber), bool(with_curl)))


@partial(jax.jit, static_argnums=(0, 3, 4), compiler_options=FAST_COMPILE)
def _obstructions(vector_field, gammas, params, rubber, with_curl):
    return jax.vmap(_obstruction, in_axes=(None, 0, None, None, None))(vector_field, gammas, params, rubber, with_curl)
