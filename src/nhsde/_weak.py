"""Platen's explicit order-2.0 weak scheme for Itô SDEs with general noise, and the increments it needs.

Kloeden & Platen, *Numerical Solution of Stochastic Differential Equations*
(1992), here KP.  For ``dX = a(t, X) dt + Σ_j b^j(t, X) dW^j`` (``m`` channels,
non-commutative allowed) one step of ``h`` is KP (15.1.3), with time made explicit:

    X₊ = X + ½(a(t₁, Ῡ) + a) h
         + ¼ Σ_j [b^j(t₁, R^j₊) + b^j(t₁, R^j₋) + 2b^j] ΔŴ^j
         + ¼ Σ_j Σ_{r≠j} [b^j(U^r₊) + b^j(U^r₋) − 2b^j] ΔŴ^j
         + ¼ Σ_j [b^j(t₁, R^j₊) − b^j(t₁, R^j₋)] ((ΔŴ^j)² − h)/√h
         + ¼ Σ_j Σ_{r≠j} [b^j(U^r₊) − b^j(U^r₋)] (ΔŴ^r ΔŴ^j + V_{rj})/√h

    Ῡ = X + a h + Σ_j b^j ΔŴ^j,   R^j_± = X + a h ± b^j √h,   U^r_± = X ± b^r √h,

``a``, ``b`` unmarked at ``(t₀, X)``.  Expanding the supporting values, the step
equals the simplified order-2.0 weak Taylor scheme of KP §14.2 (every Itô–Taylor
term ``a h``, ``b^j ΔW^j``, ``L^{j₁}b^{j₂} I_{(j₁,j₂)}``, ``L^0 a h²/2``,
``(L^0 b^j + L^j a) I_{(j,0)}`` in distribution, with ``I_{(j₁,j₂)}`` replaced by
``½(ΔŴ^{j₁}ΔŴ^{j₂} + V_{j₁j₂})``) up to local terms of order ``h³`` in every
moment, which is the local condition for weak order 2 (KP §14.5).
That needs the increments to satisfy KP's moment conditions: ``E ΔŴ = E ΔŴ³ =
E ΔŴ⁵ = 0``, ``E ΔŴ² = h``, ``E ΔŴ⁴ = 3h²``, and ``V`` two-point (``±h`` with
probability ½ for ``r > j``, ``V_{jr} = −V_{rj}``, ``V_{jj} = −h``) independent of
``ΔŴ``.  Noise classes: any ``m``; scalar, diagonal, commutative, additive and
non-commutative noise alike (for additive noise the differences of ``b``
vanish and the step is KP (15.1.4)).  Deterministically it is Heun's method
(order 2).  Cost per step: 2 drift evaluations and ``4m + 1`` diffusion
evaluations (``2m + 1`` for ``m = 1``); a diffusion that does not depend on the
state is evaluated once.

The increments, over a step of ``n`` base steps of length ``δ`` (``h = nδ``):

- :class:`ThreePointIncrement` (KP §14.2): each base step draws ``ΔŴ_i = ±√(3δ)``
  with probability 1/6 each, 0 with 2/3, from one random 32-bit word (probabilities
  exact to 2·10⁻¹⁰); the step's ``ΔŴ`` is their sum (its odd moments vanish and its
  fourth cumulant is zero, so it meets the moment conditions, but for ``n > 1`` it
  is not three-point).
- :class:`GaussianWeakIncrement`: ``ΔW`` is the sum of Gaussian base increments;
  the sum of Gaussians is Gaussian, so the step has the same law for every ``n``,
  which extrapolation and multilevel Monte Carlo need (the coarse solve must have
  the law of a plain solve at its step).  The normals are ``ndtri`` of uniforms,
  not the Wiener driver's ``jax.random.normal`` draws: XLA on CPU recomputes the
  latter's inverse error function in every fused consumer of ``ΔW``, which made
  a step 2–4× dearer (measured on Chaplygin's ball); so this is a Brownian path
  of its own, not the one Euler–Maruyama sees with the same key.

In both, ``V = n·V₁`` with ``V₁`` the two-point variable of the step's first base
step: exactly two-point at every ``n``.  Both are functions of ``(key, block,
base step)`` alone, so runs stay bitwise independent of chunking and sharding.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar, Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jax.scipy.special import ndtri
from jaxtyping import Array

from ._misc import over_substeps, substeps_span

__all__ = ["GaussianWeakIncrement", "PlatenWeak2", "ThreePointIncrement", "WeakIncrement"]

SIXTH = 2**32 // 6
"""A uniform 32-bit word is below this with probability 1/6 − 1.6·10⁻¹⁰: the three-point threshold."""


def _words(m: int) -> int:
    """32-bit words of the ``m(m − 1)/2`` two-point signs."""
    return max(1, -(-m * (m - 1) // 64))


def _two_point(bits, m: int, h):
    """``V (lanes, m, m)`` from random words ``bits (lanes, _words(m))``: one bit per ``±h`` below the diagonal,
    antisymmetric, ``−h`` on the diagonal."""
    rows, cols = np.tril_indices(m, -1)
    k = np.arange(rows.size)
    ones = (bits[:, k // 32] >> (k % 32).astype(np.uint32)) & 1
    lower = jnp.zeros(bits.shape[:1] + (m, m), h.dtype).at[:, rows, cols].set(jnp.where(ones == 1, h, -h))
    return lower - jnp.swapaxes(lower, -1, -2) - h * jnp.eye(m, dtype=h.dtype)


class WeakIncrement(dfx.AbstractBrownianIncrement):
    """``ΔŴ`` and the two-point matrix ``V`` of a step: what :class:`PlatenWeak2` needs."""

    dt: eqx.AbstractVar[Any]
    W: eqx.AbstractVar[Array]
    V: eqx.AbstractVar[Array]

    @classmethod
    @abc.abstractmethod
    def block_draw(cls, key, k0, dt, shape, substeps: int) -> WeakIncrement:
        """The increments of fixed step ``k0`` (``substeps`` base steps of ``dt``) for ``shape = (lanes, m)``."""


class ThreePointIncrement(WeakIncrement):
    """Three-point ``ΔŴ`` (``±√(3h)`` w.p. 1/6, 0 w.p. 2/3) and two-point ``V`` (KP §14.2); see the module."""

    dt: Any
    W: Array
    V: Array

    @classmethod
    def block_draw(cls, key, k0, dt, shape, substeps: int) -> ThreePointIncrement:
        """Increments of fixed step ``k0`` for ``shape = (lanes, m)``: ``(lanes, m + words)`` random words per base
        step, the first ``m`` compared with :data:`SIXTH` for ``ΔŴ``, the rest the signs of ``V`` (first base step)."""
        lanes, m = shape

        def draw(k):
            return jr.bits(jr.fold_in(key, k), (lanes, m + _words(m)), jnp.uint32)

        def base_step(k, total):
            u = draw(k)[:, :m]
            return total + (u >= np.uint32(2**32 - SIXTH)).astype(dt.dtype) - (u < np.uint32(SIXTH)).astype(dt.dtype)

        steps = over_substeps(base_step, k0, substeps, jnp.zeros(shape, dt.dtype))
        h = substeps_span(substeps, dt)
        w = jnp.sqrt(3 * dt) * steps
        return cls(dt=jnp.broadcast_to(h, (lanes,)), W=w, V=_two_point(draw(k0 * substeps)[:, m:], m, h))


class GaussianWeakIncrement(WeakIncrement):
    """Gaussian ``ΔW`` and two-point ``V``: the same law at every step; see the module."""

    dt: Any
    W: Array
    V: Array

    @classmethod
    def block_draw(cls, key, k0, dt, shape, substeps: int) -> GaussianWeakIncrement:
        """Increments of fixed step ``k0`` for ``shape = (lanes, m)``: per base step ``k`` the normals ``ndtri(u)``,
        ``u`` uniform from ``fold_in(key, k)``; the signs of ``V`` from ``fold_in(fold_in(key, k), 1)``."""
        lanes, m = shape
        tiny = jnp.finfo(dt.dtype).tiny

        def base_step(k, total):
            return total + ndtri(jr.uniform(jr.fold_in(key, k), shape, dt.dtype, minval=tiny))

        w = jnp.sqrt(dt) * over_substeps(base_step, k0, substeps, jnp.zeros(shape, dt.dtype))
        bits = jr.bits(jr.fold_in(jr.fold_in(key, k0 * substeps), 1), (lanes, _words(m)), jnp.uint32)
        h = substeps_span(substeps, dt)
        return cls(dt=jnp.broadcast_to(h, (lanes,)), W=w, V=_two_point(bits, m, h))


class PlatenWeak2(dfx.AbstractItoSolver):
    """Platen's explicit order-2.0 weak scheme, KP (15.1.3), for Itô SDEs with any noise; see the module.

    Weak order 2 for smooth coefficients with polynomial growth (KP §14.5),
    any number of channels, non-commutative noise included.  ``terms`` is
    ``MultiTerm(ODETerm(a), ControlTerm(b, path))`` with a vector state, ``b`` a
    ``(d, m)`` matrix and ``path`` yielding the increment type named by
    ``minimal_levy_area`` when asked for ``use_levy=True``.
    ``increments='three-point'`` (default, ``"weak2"`` in ``SOLVERS``) draws the
    cheap discrete increments; ``'gaussian'`` Gaussian increments, needed where
    solves at different steps must share the law (extrapolation, multilevel Monte
    Carlo).  Not a strong scheme: with three-point increments paths do not converge
    at all, with Gaussian ones at order 0.5 (1 for commutative noise).
    """

    increments: Literal["three-point", "gaussian"] = eqx.field(static=True, default="three-point")
    interpolation_cls: ClassVar = dfx.LocalLinearInterpolation
    term_compatible_contr_kwargs: ClassVar = (dict(), dict(use_levy=True))

    def __check_init__(self):
        if self.increments not in ("three-point", "gaussian"):
            raise ValueError(f"increments={self.increments!r}; allowed: 'three-point', 'gaussian'.")

    @property
    def minimal_levy_area(self) -> type[WeakIncrement]:
        return ThreePointIncrement if self.increments == "three-point" else GaussianWeakIncrement

    @property
    def term_structure(self):
        return dfx.MultiTerm[tuple[dfx.AbstractTerm, dfx.AbstractTerm[Any, self.minimal_levy_area]]]

    def order(self, terms):
        return 2

    def strong_order(self, terms):
        return None if self.increments == "three-point" else 0.5

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        drift, diffusion = terms.terms
        inc = diffusion.contr(t0, t1, use_levy=True)
        if not isinstance(inc, self.minimal_levy_area):
            raise ValueError(
                f"PlatenWeak2(increments={self.increments!r}) needs {self.minimal_levy_area.__name__} increments; "
                f"the Brownian path gave {type(inc).__name__}."
            )
        h = t1 - t0
        sqrt_h = jnp.sqrt(h)
        w, v = inc.W, inc.V
        m = w.shape[0]
        a = drift.vf(t0, y0, args)
        b = diffusion.vf(t0, y0, args)  # (d, m)
        a_h = a * h
        a_end = drift.vf(t1, y0 + a_h + b @ w, args)
        bj = jnp.swapaxes(b, 0, 1)[:, None, :]  # (m, 1, d): column j
        signs = jnp.array([1.0, -1.0], y0.dtype)[None, :, None]
        vmapped = jax.vmap(jax.vmap(diffusion.vf, in_axes=(None, 0, None)), in_axes=(None, 0, None))
        # b at R^j_± (time t₁), column j: (m, 2, d, m) → (2, d, m)
        at_r = vmapped(t1, y0 + a_h + signs * sqrt_h * bj, args)
        col = jnp.arange(m)
        r_plus, r_minus = at_r[col, 0, :, col].T, at_r[col, 1, :, col].T
        y1 = y0 + 0.5 * (a + a_end) * h
        y1 = y1 + 0.25 * (r_plus + r_minus + 2 * b) @ w
        y1 = y1 + 0.25 * (r_plus - r_minus) @ (w**2 - h) / sqrt_h
        if m > 1:
            # b at U^r_± (time t₀): (m_r, 2, d, m_j); only r ≠ j enters
            at_u = vmapped(t0, y0 + signs * sqrt_h * bj, args)
            off = 1.0 - jnp.eye(m, dtype=y0.dtype)
            u_sum = jnp.einsum("rdj,rj->dj", at_u[:, 0] + at_u[:, 1] - 2 * b[None], off)
            y1 = y1 + 0.25 * u_sum @ w
            products = (jnp.outer(w, w) + v) * off  # ΔŴ^r ΔŴ^j + V_rj, r ≠ j
            y1 = y1 + 0.25 * jnp.einsum("rdj,rj->d", at_u[:, 0] - at_u[:, 1], products) / sqrt_h
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


WEAK_INCREMENTS = (ThreePointIncrement, GaussianWeakIncrement)
"""The increment types the counter-based Wiener driver draws for :class:`PlatenWeak2`."""
