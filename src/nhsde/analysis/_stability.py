"""Linear stability of a steady state of any vector field ``ẏ = f(t, y, params)``.

A steady motion of a Chaplygin system lies in a family (S4 (4.9)): the
linearisation has ``n_family`` zero eigenvalues along the family and the first
integrals, and the remaining roots decide stability "in part of the variables"
(S4 Theorem 4.1): all ``Re μ < 0`` → asymptotically stable transversally to the
family; some ``Re μ > 0`` → unstable; all ``Re μ ≈ 0`` → neutral (the linear test
is inconclusive).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

from .._misc import FAST_COMPILE
from ._inputs import require_float64

__all__ = ["Stability", "classify", "jacobian", "linear_stability"]


def jacobian(field: Callable, state, params, t=0.0) -> Float[Array, "n n"]:
    """``∂f/∂y`` at ``state`` for ``f = field(t, y, params)`` (forward-mode autodiff)."""
    return jax.jacfwd(lambda y: field(t, y, params))(jnp.asarray(state))


@eqx.filter_jit(compiler_options=FAST_COMPILE)  # pyright: ignore[reportCallIssue]  (jit options untyped)
def _value_and_jacobian(field, state, params, t):
    return field(t, state, params), jacobian(field, state, params, t)


class Stability(eqx.Module):
    """The spectrum of a linearisation about a steady state in a family of steady states.

    ``eigenvalues``: all, sorted by real part descending; ``family_roots``: the
    ``n_family`` of smallest modulus (the family and its first integrals);
    ``roots``: the others; ``growth_rate = max Re(roots)``; ``verdict`` one of
    "asymptotically stable" (transversally to the family, S4 Theorem 4.1),
    "neutral" (none with ``Re μ`` above the tolerance of :func:`classify`, some within it:
    marginal, the linear test is inconclusive) or "unstable"; ``residual``: ``|f(state)|`` when a vector field was
    given.
    """

    eigenvalues: Complex[Array, " n"]
    family_roots: Complex[Array, " n_family"]
    roots: Complex[Array, " n_roots"]
    growth_rate: Float[Array, ""]
    verdict: str = eqx.field(static=True)
    residual: Float[Array, ""] | None = None


def classify(eigenvalues, n_family: int, rtol: float, scale: float | None = None) -> Stability:
    """Split ``eigenvalues`` into family and transverse roots and classify them (see :class:`Stability`).

    ``scale`` is the size of the matrix the eigenvalues came from, ``‖J‖₂`` (default:
    the largest modulus; 1 if all vanish).  The family roots must be below
    ``sqrt(rtol)·scale``: zero roots are defective (Jordan blocks) in general, and
    rounding moves a double zero by ``O(sqrt(eps))``.  The verdict compares real parts
    with ``rtol·ρ + 10⁴·eps·scale``, ``ρ`` the largest modulus: relative to the
    spectrum, not to ``‖J‖₂``, which a badly scaled (non-normal) ``J`` makes far larger.
    """
    eig = np.asarray(eigenvalues)
    n = eig.shape[0]
    if not 0 <= n_family < n:
        raise ValueError(f"n_family={n_family} must satisfy 0 <= n_family < {n} (the number of eigenvalues).")
    radius = float(np.max(np.abs(eig))) or 1.0
    scale = radius if scale is None else scale
    tol = rtol * radius + 1e4 * np.finfo(eig.dtype).eps * scale
    by_modulus = np.argsort(np.abs(eig), kind="stable")
    family, rest = eig[by_modulus[:n_family]], eig[by_modulus[n_family:]]
    if n_family and np.max(np.abs(family)) > np.sqrt(rtol) * scale:
        raise ValueError(
            f"the {n_family} smallest eigenvalues {np.array2string(family, precision=3)} are not ≈ 0 "
            f"(tolerance sqrt(rtol)*scale = {np.sqrt(rtol) * scale:.3e}): the state is not in a "
            f"{n_family}-parameter family of steady states, or n_family is wrong."
        )
    rest = rest[np.argsort(-np.real(rest), kind="stable")]
    growth = float(np.max(np.real(rest)))
    if growth > tol:
        verdict = "unstable"
    elif np.all(np.real(rest) < -tol):
        verdict = "asymptotically stable"
    else:
        verdict = "neutral"
    return Stability(
        eigenvalues=jnp.asarray(eig[np.argsort(-np.real(eig), kind="stable")]),
        family_roots=jnp.asarray(family),
        roots=jnp.asarray(rest),
        growth_rate=jnp.asarray(np.float64(growth)),
        verdict=verdict,
    )


def linear_stability(field: Callable, state, params, *, n_family: int, t=0.0, rtol: float = 1e-8) -> Stability:
    """Eigenvalues of ``∂f/∂y`` at a steady ``state`` of ``ẏ = f(t, y, params)``, classified.

    ``n_family`` eigenvalues of smallest modulus belong to the family of steady
    states and the first integrals (S4 Theorem 4.1, the m zero roots of (4.19));
    the others decide the verdict.  Raises ``ValueError`` if ``|f(state)|`` is not
    ≈ 0 (relative to ``|∂f/∂y|·|state|``) or the ``n_family`` smallest eigenvalues
    are not ≈ 0 (see :func:`classify`).

    Arguments:
        field: the vector field ``f(t, y, params)``.
        state: the steady state ``(n,)``, float64.
        params: the field's parameters.
        n_family: the number of zero roots that belong to the family of steady states and first integrals.
        t: the time at which ``f`` is evaluated.
        rtol: relative tolerance of the steadiness check and of the verdict.

    Returns:
        a :class:`Stability`: sorted ``eigenvalues``, ``family_roots``, ``roots``, ``growth_rate``, ``verdict``
        and ``residual = |f(state)|``.

    Examples:
        A damped pendulum ``θ̈ = −(g/l) sin θ − 0.1 θ̇`` at rest (no family: ``n_family=0``):

        >>> import jax.numpy as jnp
        >>> from nhsde import analysis
        >>> def pendulum(t, y, g_over_l):
        ...     return jnp.array([y[1], -g_over_l * jnp.sin(y[0]) - 0.1 * y[1]])
        >>> result = analysis.linear_stability(pendulum, jnp.zeros(2), 4.0, n_family=0)
        >>> result.verdict
        'asymptotically stable'
        >>> print(result.eigenvalues.round(3))
        [-0.05+1.999j -0.05-1.999j]
    """
    state = jnp.asarray(state)
    require_float64("state", state)
    value, jac = (np.asarray(a) for a in _value_and_jacobian(field, state, params, jnp.asarray(t, state.dtype)))
    if not np.all(np.isfinite(jac)):
        raise ValueError(f"the Jacobian at state={np.asarray(state)} is not finite.")
    residual = float(np.linalg.norm(value))
    scale = float(np.linalg.norm(jac, 2)) or 1.0
    allowed = rtol * scale * max(float(np.linalg.norm(np.asarray(state))), 1.0)
    if not residual <= allowed:
        raise ValueError(
            f"state={np.asarray(state)} is not a steady state of the field: |f(state)| = {residual:.3e} exceeds "
            f"rtol*|∂f/∂y|*max(|state|, 1) = {allowed:.3e} (rtol={rtol})."
        )
    result = classify(np.linalg.eigvals(jac), n_family, rtol, scale)
    return eqx.tree_at(lambda s: s.residual, result, jnp.asarray(np.float64(residual)), is_leaf=lambda x: x is None)
