"""Families of steady motions of a conservative Chaplygin system: the solutions of S4 (4.9), §4.2.

On a :class:`~nhsde.analysis.ChaplyginSystem` with pseudo-cyclic ``s`` and
positional ``r``, the motions ``r = r0``, ``ṙ = 0``, ``ṡ = ṡ0`` solve

    ∂/∂r ½ Θ_ss ṡ·ṡ + (Ω_rss ṡ)ṡ − ∂V/∂r = 0     (4.9)

and form families of dimension ``m`` in general position (4.10); fixing ``m`` of
the ``k + m`` constants leaves ``k`` equations for the others, solved here by
Newton's method, vmapped over the family parameter.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._misc import FAST_COMPILE
from ._chaplygin import ChaplyginSystem

__all__ = ["SteadyMotions", "steady_motions"]

_NEWTON_STEPS = 50
_CHUNK = 8  # family values solved per compiled, vmapped Newton call


class SteadyMotions(eqx.Module):
    """Steady motions ``r = r0, ṙ = 0, ṡ = ṡ0`` solving S4 (4.9), one row per family parameter value.

    ``family_dimension`` is ``k + m − rank ∂(4.9)/∂(r, ṡ)``: the dimension of the
    family through each motion (``m`` in general position, S4 (4.10));
    ``linearisation``: ``(W, V, U)`` of (4.5) about each motion (rows/columns ``r``
    then ``s``), the blocks of ``Δ(μ)`` (4.23).
    """

    positions: Float[Array, "batch k"]
    velocities: Float[Array, "batch m"]
    residual: Float[Array, " batch"]
    linearisation: tuple[Array, Array, Array]
    family_dimension: tuple[int, ...] = eqx.field(static=True)

    def __getitem__(self, i) -> tuple:
        return self.positions[i], self.velocities[i]


def _evaluate(system, p, fixed_slots, free_slots, fixed, free):
    """At the unknowns ``free``: (4.9), the size of its terms, ``∂(4.9)/∂(r, ṡ) = −[U_rr, V_rs]``,
    the size of the terms' derivatives, the linearisation ``(W, V, U)`` and ``(r, ṡ)``.

    (4.9) ``∂/∂r ½ Θ_ss ṡ·ṡ + (Ω_rss ṡ)ṡ − ∂V/∂r = 0`` is minus the ``r`` rows of (4.5)
    at ``ṙ = 0``, ``ẍ = 0`` (``Θ̇ẋ = 0`` there since ``Θ`` does not depend on ``s``).
    """
    k = system.k
    u = jnp.zeros(k + system.m, free.dtype).at[fixed_slots].set(fixed).at[free_slots].set(free)
    terms, (du, dv, dw) = system.expansion(u[:k], u[k:], p)
    parts_jac = -jnp.concatenate([du[:, :k, :k], dv[:, :k, k:]], axis=2)
    linear = tuple(jnp.sum(a, axis=0) for a in (dw, dv, du))
    return (
        -jnp.sum(terms[:, :k], axis=0),
        jnp.sum(jnp.abs(terms[:, :k]), axis=0),
        jnp.sum(parts_jac, axis=0),
        jnp.sum(jnp.abs(parts_jac), axis=0),
        linear,
        u,
    )


def _rank_cut(jac_size):
    """Singular values below this are cancellation noise: the terms of (4.9) cancel identically there."""
    return 1e3 * jnp.finfo(jac_size.dtype).eps * jnp.max(jac_size, initial=0.0)


def _converged(res, size):
    return jnp.max(jnp.abs(res), initial=0.0) <= 1e3 * jnp.finfo(res.dtype).eps * jnp.max(size, initial=0.0)


@eqx.filter_jit(compiler_options=FAST_COMPILE)  # pyright: ignore[reportCallIssue]  (jit options untyped)
def _solve(system, p, fixed_slots, free_slots, fixed, free):
    """Newton's method with minimum-norm steps (the family may be wider than ``m``), vmapped over rows.

    Each step evaluates (4.9) and the linearisation once and stops when (4.9)
    vanishes to rounding; the result reported is the last point evaluated.
    """

    def one(fixed, free):
        def step(carry):
            free, i = carry[0], carry[-1]
            res, size, jac, jac_size, linear, u = _evaluate(system, p, fixed_slots, free_slots, fixed, free)
            left, sv, right = jnp.linalg.svd(jac[:, free_slots], full_matrices=False)
            inverse = jnp.where(sv > _rank_cut(jac_size), 1.0 / jnp.where(sv > 0, sv, 1.0), 0.0)
            done = _converged(res, size)
            free = jnp.where(done, free, free - right.T @ (inverse * (left.T @ res)))
            return free, res, size, jac, jac_size, linear, u, i + 1

        def more(carry):
            return (carry[-1] == 0) | ((carry[-1] < _NEWTON_STEPS) & ~_converged(carry[1], carry[2]))

        init = jax.eval_shape(lambda z: _evaluate(system, p, fixed_slots, free_slots, fixed, z), free)
        init = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), init)
        _, res, size, jac, jac_size, linear, u, _ = jax.lax.while_loop(more, step, (free, *init, jnp.zeros((), int)))
        return u, jnp.max(jnp.abs(res), initial=0.0), jnp.max(size, initial=0.0), jac, _rank_cut(jac_size), linear

    return jax.vmap(one)(fixed, free)


def _values(system, family: dict, what: str):
    names = system.unknowns
    unknown = [n for n in family if n not in names]
    if unknown:
        raise ValueError(f"{what} names {unknown}; allowed: {names} (positions r, velocities ṡ as '<s>_dot').")
    values = {n: np.atleast_1d(np.asarray(v, float)) for n, v in family.items()}
    return values


def steady_motions(system: ChaplyginSystem, family: dict, guess: dict | None = None) -> SteadyMotions:
    """Solve S4 (4.9) for steady motions by Newton's method, vmapped over the family parameter.

    ``family`` fixes ``m`` of the ``k + m`` constants :attr:`ChaplyginSystem.unknowns`
    (default choice in S4 (4.11): the velocities ``ṡ``), each a scalar or a 1-d
    array of values; the other ``k`` are found from ``guess`` (default: the
    reference ``r``, ``ṡ = 1``).  ``ValueError`` names a parameter value at which
    (4.9) has no solution near the guess (outside the family's domain).

    Arguments:
        system: a :class:`ChaplyginSystem` (from :func:`chaplygin_system`).
        family: ``name → value(s)`` for ``m`` of :attr:`ChaplyginSystem.unknowns`, e.g. ``{"x_dot": 1.5}``.
        guess: ``name → value`` starting points of the other ``k`` unknowns.

    Returns:
        a :class:`SteadyMotions`: ``positions`` ``r``, ``velocities`` ``ṡ``, the ``residual`` of (4.9) and the
        ``linearisation`` ``(W, V, U)`` that :func:`steady_stability` reads, one row per family value.
    """
    names, p = system.unknowns, system.spec.params
    fixed = _values(system, family, "family")
    if len(fixed) != system.m:
        raise ValueError(f"family fixes {sorted(fixed)}; give exactly m = {system.m} of {names} (S4 (4.10)).")
    start = _values(system, guess or {}, "guess")
    batch = np.broadcast_shapes(*(v.shape for v in fixed.values()))
    if len(batch) != 1:
        raise ValueError(
            f"family values have shapes {[v.shape for v in fixed.values()]}; expected scalars or 1-d arrays."
        )
    fixed_slots = np.array([names.index(n) for n in fixed], int)
    free_slots = np.array([i for i in range(len(names)) if i not in fixed_slots], int)
    default = np.concatenate([np.asarray(system.reference)[list(system.positional)], np.ones(system.m)])
    free0 = np.stack([np.broadcast_to(start.get(names[i], default[i]), batch) for i in free_slots], axis=-1)
    values = np.stack([np.broadcast_to(v, batch) for v in fixed.values()], axis=-1)
    # fixed-size chunks: one compilation serves every batch size
    pad = -batch[0] % _CHUNK
    values_p, free_p = (np.concatenate([a, np.repeat(a[-1:], pad, axis=0)]) for a in (values, free0))
    chunks = [
        _solve(
            system,
            p,
            fixed_slots,
            free_slots,
            jnp.asarray(values_p[i : i + _CHUNK]),
            jnp.asarray(free_p[i : i + _CHUNK]),
        )
        for i in range(0, len(values_p), _CHUNK)
    ]
    u, res, scale, full, cut, linear = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[: batch[0]], *chunks)
    u, res, scale, full, cut = (np.asarray(a) for a in (u, res, scale, full, cut))
    for i in range(batch[0]):
        if not (np.all(np.isfinite(u[i])) and res[i] <= 1e3 * np.finfo(res.dtype).eps * scale[i]):
            given = ", ".join(f"{n}={v[i]:.6g}" for n, v in zip(fixed, values.T))
            raise ValueError(
                f"no steady motion with {given}: Newton's method on S4 (4.9) from "
                f"{dict(zip([names[j] for j in free_slots], free0[i].tolist()))} ended at residual {res[i]:.3g} "
                f"(terms of size {scale[i]:.3g}); this value lies outside the family's domain (no real solution "
                "nearby)."
            )
    dims = []
    for i in range(batch[0]):
        dims.append(len(names) - int(np.sum(np.linalg.svd(full[i], compute_uv=False) > cut[i])))
    k = system.k
    return SteadyMotions(jnp.asarray(u[:, :k]), jnp.asarray(u[:, k:]), jnp.asarray(res), linear, tuple(dims))
