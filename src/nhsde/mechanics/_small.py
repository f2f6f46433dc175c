"""Small symmetric positive-definite systems, unrolled: the mass matrices and Schur complements of scenes.

A scene's mass matrix is a few rows wide, and its vector fields run once per path under ``vmap``: there LAPACK's
Cholesky and triangular solves are a library call per batch (on the CPU a loop over the paths), which the compiler
cannot fuse with the arithmetic around them.  Written out entry by entry for the static size, the same
factorisation is plain arithmetic that XLA fuses into the step.  The equations are the textbook ones
(``L_jj = √(a_jj − Σ_k L_jk²)``, ``L_ij = (a_ij − Σ_k L_ik L_jk)/L_jj``, forward and back substitution), so the
result equals LAPACK's to rounding; above :data:`UNROLL_UP_TO` rows LAPACK is used.
"""

from __future__ import annotations

import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import Array

__all__ = ["UNROLL_UP_TO", "cho_solve", "cholesky", "matmul", "psd_factor", "rank_deficient", "solve", "spd_solve"]

UNROLL_UP_TO = 8
"""The largest size factorised entry by entry (the work grows as n³ in the program's size)."""


def matmul(a: Array, b: Array) -> Array:
    """``a @ b`` for small ``a`` (``(m, k)`` or ``(k,)``) and ``b`` (``(k, n)`` or ``(k,)``), as sums of products.

    Under ``vmap`` a product of a few rows is a batched ``dot_general`` per path, which the CPU compiler emits as a
    reduction kernel of its own, with the transposes and copies that feed it; as sums of entrywise products it is
    plain arithmetic fused with its neighbours.  Above :data:`UNROLL_UP_TO` in any dimension, ``a @ b``.
    """
    a_vector, b_vector = a.ndim == 1, b.ndim == 1
    left = a[None, :] if a_vector else a
    right = b[:, None] if b_vector else b
    (m, k), n = left.shape, right.shape[1]
    if max(m, k, n) > UNROLL_UP_TO or not (m and n and k):
        return a @ b
    out = jnp.stack(
        [
            jnp.stack(
                [sum((left[i, l] * right[l, j] for l in range(1, k)), left[i, 0] * right[0, j]) for j in range(n)]
            )
            for i in range(m)
        ]
    )
    if a_vector:
        out = out[0]
    return out[..., 0] if b_vector else out


def cholesky(a: Array) -> Array:
    """The lower Cholesky factor ``L`` of the symmetric positive-definite ``a`` (``(n, n)``), ``a = L Lᵀ``."""
    n = a.shape[-1]
    if n > UNROLL_UP_TO:
        return jnp.linalg.cholesky(a)
    zero = jnp.zeros((), a.dtype)
    rows: list[list[Array]] = [[zero] * n for _ in range(n)]
    for j in range(n):
        diagonal = jnp.sqrt(a[j, j] - sum((rows[j][k] ** 2 for k in range(j)), zero))
        rows[j][j] = diagonal
        for i in range(j + 1, n):
            rows[i][j] = (a[i, j] - sum((rows[i][k] * rows[j][k] for k in range(j)), zero)) / diagonal
    return jnp.stack([jnp.stack(row) for row in rows])


def cho_solve(chol: Array, b: Array) -> Array:
    """``x`` with ``L Lᵀ x = b`` for the factor ``chol = L`` of :func:`cholesky`; ``b`` is ``(n,)`` or ``(n, m)``."""
    n = chol.shape[-1]
    if n > UNROLL_UP_TO:
        return jsl.cho_solve((chol, True), b)
    y: list[Array] = []
    for i in range(n):  # L y = b
        y.append((b[i] - sum((chol[i, k] * y[k] for k in range(i)), jnp.zeros_like(b[i]))) / chol[i, i])
    x: list[Array] = [y[0]] * n
    for i in reversed(range(n)):  # Lᵀ x = y
        x[i] = (y[i] - sum((chol[k, i] * x[k] for k in range(i + 1, n)), jnp.zeros_like(y[i]))) / chol[i, i]
    return jnp.stack(x) if n else b


def spd_solve(a: Array, b: Array) -> Array:
    """``x`` with ``a x = b`` for a symmetric positive-definite ``a``."""
    return cho_solve(cholesky(a), b)


def solve(a: Array, b: Array) -> Array:
    """``x`` with ``a x = b`` for a general nonsingular ``a`` (``(n, n)``); ``b`` is ``(n,)`` or ``(n, m)``.

    Gaussian elimination with partial pivoting (the row of largest ``|a_ik|`` at each column, chosen by ``argmax``
    and moved by selection, so the program's shape is static), then back substitution.  Besides fusing, it keeps
    LAPACK's batched ``getrf``/``trsm`` out of vmapped vector fields: on a machine with few cores two of those
    kernels running at once can each wait on the other's share of XLA's CPU thread pool, and never return.
    """
    n = a.shape[-1]
    if n > UNROLL_UP_TO or not n:
        return jnp.linalg.solve(a, b) if n else b
    vector = b.ndim == 1
    augmented = jnp.concatenate([a, b[:, None] if vector else b], axis=1)
    rows = [augmented[i] for i in range(n)]
    for k in range(n):
        below = jnp.stack(rows[k:])
        choice = jnp.argmax(jnp.abs(below[:, k]))
        pivot = below[choice]
        swapped = [jnp.where(choice == i - k, rows[k], rows[i]) for i in range(k + 1, n)]
        rows[k] = pivot
        rows[k + 1 :] = [row - (row[k] / pivot[k]) * pivot for row in swapped]
    x: list[Array] = [rows[0][n:]] * n
    for i in reversed(range(n)):
        x[i] = (rows[i][n:] - sum((rows[i][k] * x[k] for k in range(i + 1, n)), jnp.zeros_like(x[i]))) / rows[i][i]
    out = jnp.stack(x)
    return out[:, 0] if vector else out


def rank_deficient(rows: Array) -> Array:
    """Whether the rows of ``rows`` (``(m, n)``) are linearly dependent, to rounding.

    Cholesky's pivots of the Gram matrix ``G = rows rowsᵀ``: the ``j``-th is the squared distance of row ``j`` from
    the span of the rows before it, ``G_jj`` minus terms no larger than ``G_jj``, so dependent rows give one at
    rounding level (at or below ``16 m ε G_jj``, or not a number) however the rows are scaled.  Unrolled like
    :func:`cholesky`: no SVD under ``vmap``.
    """
    m = rows.shape[0]
    gram = matmul(rows, rows.T)
    if m > UNROLL_UP_TO:
        sv = jnp.linalg.svd(rows, compute_uv=False)
        return sv[-1] <= jnp.sqrt(16 * m * jnp.finfo(rows.dtype).eps) * sv[0]
    pivots = jnp.diagonal(cholesky(gram)) ** 2
    return ~jnp.all(pivots > 16 * m * jnp.finfo(rows.dtype).eps * jnp.diagonal(gram))


def psd_factor(a: Array) -> Array:
    """A lower-triangular ``L`` with ``a = L Lᵀ`` for a symmetric positive *semi*-definite ``a`` (``(n, n)``).

    Cholesky's recursion, with a column set to zero where its pivot vanishes (to rounding, relative to the
    largest diagonal entry): in a semidefinite matrix a zero pivot has a zero column below it.  A Rayleigh
    function's ``∂²R/∂q̇²`` is often singular (friction on some velocities only).
    """
    n = a.shape[-1]
    zero = jnp.zeros((), a.dtype)
    floor = 16 * n * jnp.finfo(a.dtype).eps * jnp.max(jnp.abs(jnp.diagonal(a)))
    rows: list[list[Array]] = [[zero] * n for _ in range(n)]
    for j in range(n):
        pivot = a[j, j] - sum((rows[j][k] ** 2 for k in range(j)), zero)
        live = pivot > floor
        diagonal = jnp.sqrt(jnp.where(live, pivot, 1.0))
        rows[j][j] = jnp.where(live, diagonal, zero)
        for i in range(j + 1, n):
            entry = (a[i, j] - sum((rows[i][k] * rows[j][k] for k in range(j)), zero)) / diagonal
            rows[i][j] = jnp.where(live, entry, zero)
    return jnp.stack([jnp.stack(row) for row in rows])
