"""Solvers nhsde adds to diffrax's.

:class:`ExponentialEuler` treats the stiff linear part ``A`` of the drift
``a(Z) = A Z + N(Z)`` (viscous friction) exactly:

    Z_{n+1} = e^{Ah} Z_n + h φ₁(Ah) N(Z_n) + φ₁(Ah) b(Z_n) ΔW_n,   φ₁(x) = (e^x − 1)/x,

so a dissipative ``A`` stays stable for any ``ε·h`` (Euler–Maruyama needs
``2ε h < 2`` per friction channel).  It is exact for the deterministic linear
flow, keeps the fixed point ``−A⁻¹N`` of a constant forcing, has strong order 1
for additive noise (0.5 in general), and reduces to Euler–Maruyama as ``A → 0``.  Stable is not exact: for
``u̇ = −2εu + σV`` its stationary variance is
``σ²(1 − e^{−2εh})/(4ε²h(1 + e^{−2εh}))``, which is ``σ²/(4ε)·(1 + O(ε²h²))``
for small ``εh`` and ``≈ σ²/(4ε²h)`` (too small) once ``εh ≫ 1``.
``e^{Ah}`` and ``hφ₁(Ah)`` come from one matrix exponential of
``[[A h, h I], [0, 0]]``; they depend on the parameters only, so under ``vmap``
over paths they are computed once per step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import jax.numpy as jnp
from jax.scipy.linalg import expm

__all__ = ["ExponentialEuler"]


class ExponentialEuler(dfx.AbstractItoSolver):
    """Exponential Euler–Maruyama for ``dZ = (A Z + N(Z)) dt + b(Z) dW`` (Itô).

    ``linear(params) -> A`` gives the linear part of the drift; the drift term's
    vector field is the full drift ``A Z + N(Z)``.
    """

    linear: Callable
    term_structure: ClassVar = dfx.MultiTerm[tuple[dfx.AbstractTerm, dfx.AbstractTerm]]
    interpolation_cls: ClassVar = dfx.LocalLinearInterpolation

    def order(self, terms):
        return 1

    def strong_order(self, terms):
        return 0.5

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        drift, diffusion = terms.terms
        h = t1 - t0
        a = self.linear(args).astype(y0.dtype)
        d = y0.shape[0]
        block = jnp.block([[a * h, h * jnp.eye(d, dtype=y0.dtype)], [jnp.zeros((d, 2 * d), y0.dtype)]])
        e = expm(block)
        propagator, h_phi = e[:d, :d], e[:d, d:]
        nonlinear = drift.vf(t0, y0, args) - a @ y0
        noise = diffusion.vf_prod(t0, y0, args, diffusion.contr(t0, t1))
        y1 = propagator @ y0 + h_phi @ (nonlinear + noise / h)
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
