"""The Routh pencil of a steady motion of a Chaplygin system, S4 (4.17)–(4.23), from its linearisation.

Linearised about a steady motion ``r = r0``, ``ṡ = ṡ0``, the equations (4.5) read
``W δẍ + V δẋ + U δx = 0`` (rows and columns ``r`` then ``s``).  The ``s`` rows
carry a factor ``μ``; eliminating ``δṡ`` leaves the ``k × k`` pencil
``A0 μ² + (G0 + D0) μ + (C0 + E0)`` of (4.19), the Schur complement of the matrix
``Δ(μ)`` of (4.23).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["delta_matrix", "routh_pencil"]


def routh_pencil(w, v, u, k: int):
    """``(A0, G0 + D0, C0 + E0)`` of S4 (4.17)–(4.19): the Schur complement of ``Δ(μ)`` (4.23) on ``r``.

    From the linearisation ``(W, V, U)`` (rows/columns ``r`` then ``s``, the first ``k``
    positional): ``A0 = W_rr − W_rs W_ss⁻¹ W_sr``,
    ``G0 + D0 = V_rr − W_rs W_ss⁻¹ V_sr − V_rs W_ss⁻¹ W_sr``, ``C0 + E0 = U_rr − V_rs W_ss⁻¹ V_sr``
    (eliminate ``δṡ = −W_ss⁻¹(W_sr μ + V_sr) δr`` from the ``s`` rows, which carry a factor ``μ``).
    """
    wrs, wsr, vrs, vsr = w[:k, k:], w[k:, :k], v[:k, k:], v[k:, :k]
    solve = lambda b: jnp.linalg.solve(w[k:, k:], b)
    a0 = w[:k, :k] - wrs @ solve(wsr)
    b0 = v[:k, :k] - wrs @ solve(vsr) - vrs @ solve(wsr)
    k0 = u[:k, :k] - vrs @ solve(vsr)
    return a0, b0, k0


def delta_matrix(mu, w, v, u, k: int):
    """``Δ(μ) = [[W_rr μ² + V_rr μ + U_rr, W_rs μ + V_rs], [W_sr μ + V_sr, W_ss]]`` of S4 (4.23).

    ``det Δ(μ) = det W_ss · det(A0μ² + (G0 + D0)μ + (C0 + E0))``: its roots are those of (4.19).
    """
    w, v, u = (jnp.asarray(a) for a in (w, v, u))
    dtype = jax.lax.complex(w[0, 0], w[0, 0]).dtype
    mu, w, v, u = jnp.asarray(mu, dtype), w.astype(dtype), v.astype(dtype), u.astype(dtype)
    top = jnp.concatenate([w[:k, :k] * mu**2 + v[:k, :k] * mu + u[:k, :k], w[:k, k:] * mu + v[:k, k:]], axis=1)
    bottom = jnp.concatenate([w[k:, :k] * mu + v[k:, :k], w[k:, k:]], axis=1)
    return jnp.concatenate([top, bottom])
