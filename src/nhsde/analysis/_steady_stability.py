"""Stability of the steady motions of a Chaplygin system (S4 Theorem 4.1) and where it changes (Remark 4.6).

The stability of a steady motion in ``r, ṙ, ṡ`` is decided by the ``2k`` roots
of ``det(A0 μ² + (G0 + D0) μ + (C0 + E0)) = 0`` (4.19), the Routh pencil
(:func:`~nhsde.analysis.routh_pencil`); the ``m`` further zero roots belong to
the family.  Two independent routes give the roots: the pencil, from the
linearisation of (4.5) written from ``Θ``, ``Ω``, ``V``, and the eigenvalues of
the Jacobian of :mod:`nhsde.mechanics`' reduced (Voronets) drift on
``(r, ṙ, ṡ)``.  Along a path in the family parameter the verdict changes at an
Andronov–Hopf point or where a real root passes through zero.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

from ._chaplygin import ChaplyginSystem
from ._routh import routh_pencil
from ._stability import Stability, classify, linear_stability
from ._steady import SteadyMotions, steady_motions

__all__ = ["StabilityBoundary", "SteadyStability", "stability_boundary", "steady_stability"]


class SteadyStability(eqx.Module):
    """Linear stability of one steady motion (S4 Theorem 4.1).

    ``A0, G0, D0, C0, E0``: the Routh pencil (4.17)–(4.19) (``G0`` skew, ``D0``
    symmetric in ``μ``; ``C0`` symmetric, ``E0`` skew); ``routh``: its ``2k`` roots,
    classified (zero roots beyond the ``m`` separated ones belong to a larger
    family); ``drift``: the eigenvalues of the library's reduced drift, the
    independent route (``None`` if not asked for); ``verdict`` from ``routh``; ``linearisation``: ``(W, V, U)``
    of (4.5) about the motion, the blocks of ``Δ(μ)`` (4.23) (:func:`delta_matrix`).
    """

    A0: Float[Array, "k k"]
    G0: Float[Array, "k k"]
    D0: Float[Array, "k k"]
    C0: Float[Array, "k k"]
    E0: Float[Array, "k k"]
    routh: Stability
    drift: Stability | None
    linearisation: tuple[Array, Array, Array]

    @property
    def verdict(self) -> str:
        return self.routh.verdict

    @property
    def roots(self) -> Complex[Array, " n"]:
        return self.routh.roots


def steady_stability(
    system: ChaplyginSystem, motions: SteadyMotions, index: int = 0, *, drift: bool = True, rtol: float = 1e-8
) -> SteadyStability:
    """Stability of ``motions[index]`` by the roots of S4 (4.19) and (``drift=True``) the reduced drift's Jacobian.

    Arguments:
        system: the :class:`ChaplyginSystem` of ``motions``.
        motions: steady motions from :func:`steady_motions`.
        index: which of them.
        drift: also classify the Jacobian of the reduced drift (an independent route, :func:`linear_stability`).
        rtol: relative tolerance of the classification (:func:`classify`).

    Returns:
        a :class:`SteadyStability`: the Routh pencil ``A0``, ``G0``, ``D0``, ``C0``, ``E0`` of (4.19), its roots'
        :class:`Stability` (``routh``), the reduced drift's (``drift``) and the ``verdict``.
    """
    r, sdot = motions[index]
    w, v, u = (a[index] for a in motions.linearisation)
    linear = (w, v, u)
    a0, b0, k0 = (np.asarray(a) for a in routh_pencil(w, v, u, system.k))
    kk = system.k
    companion = np.block([[np.zeros((kk, kk)), np.eye(kk)], [-np.linalg.solve(a0, k0), -np.linalg.solve(a0, b0)]])
    scale = float(np.linalg.norm(companion, 2)) or 1.0
    routh = classify(np.linalg.eigvals(companion), motions.family_dimension[index] - system.m, rtol, scale)
    check = None
    if drift:
        state = system.steady_state(r, sdot)
        check = linear_stability(
            system.reduced_field, state, system.spec.params, n_family=motions.family_dimension[index], rtol=rtol
        )
    sym = lambda a: jnp.asarray(0.5 * (a + a.T))
    skew = lambda a: jnp.asarray(0.5 * (a - a.T))
    return SteadyStability(jnp.asarray(a0), skew(b0), sym(b0), sym(k0), skew(k0), routh, check, linear)


class StabilityBoundary(eqx.Module):
    """Where the verdict changes along a path in the family parameter.

    ``kind``: ``"Andronov–Hopf"`` when the critical roots are a complex pair
    crossing the imaginary axis (S4 Remark 4.6), ``"real root through zero"``
    otherwise; ``critical_roots``: the roots nearest the imaginary axis there;
    ``verdicts``: on the two sides.
    """

    parameter: dict = eqx.field(static=True)
    critical_roots: Complex[Array, " c"]
    kind: str = eqx.field(static=True)
    verdicts: tuple[str, str] = eqx.field(static=True)


def stability_boundary(
    system: ChaplyginSystem,
    start: dict,
    stop: dict,
    guess: dict | None = None,
    *,
    xtol: float = 1e-14,
    rtol: float = 1e-8,
) -> StabilityBoundary:
    """Bisect the segment ``start → stop`` of family parameters for the change of verdict.

    Between "asymptotically stable" and "unstable" the sign of the largest real
    part of the roots of (4.19) is bisected (it crosses zero transversally at an
    Andronov–Hopf point); otherwise the verdict itself.  ``xtol`` is relative to
    the segment.  ``ValueError`` if both ends have the same verdict.
    """
    if set(start) != set(stop):
        raise ValueError(f"start fixes {sorted(start)} but stop fixes {sorted(stop)}; fix the same names.")
    a = {n: float(v) for n, v in start.items()}
    b = {n: float(stop[n]) for n in a}
    guess = dict(guess or {})

    def at(lam):
        family = {n: a[n] + lam * (b[n] - a[n]) for n in a}
        motions = steady_motions(system, family, guess)
        u = np.concatenate([motions.positions[0], motions.velocities[0]])
        guess.update((n, u[i]) for i, n in enumerate(system.unknowns) if n not in family)  # continuation
        return family, steady_stability(system, motions, drift=False, rtol=rtol)

    first, last = at(0.0)[1], at(1.0)[1]
    ends = (first.verdict, last.verdict)
    scale = max(float(np.max(np.abs(np.asarray(s.routh.eigenvalues)))) for s in (first, last)) or 1.0
    if ends[0] == ends[1]:
        raise ValueError(f"the verdict is {ends[0]!r} at both start={start} and stop={stop}; no boundary to bisect.")
    signed = set(ends) == {"asymptotically stable", "unstable"}

    def on_stop_side(stability):
        if signed:
            return (float(stability.routh.growth_rate) > 0.0) == (ends[1] == "unstable")
        return stability.verdict == ends[1]

    lo, hi = 0.0, 1.0
    while hi - lo > xtol:
        mid = 0.5 * (lo + hi)
        if on_stop_side(at(mid)[1]):
            hi = mid
        else:
            lo = mid
    family, stability = at(0.5 * (lo + hi))
    roots = np.asarray(stability.routh.roots)
    order = np.argsort(np.abs(np.real(roots)), kind="stable")
    critical = roots[order[:2]] if roots.size > 1 else roots
    hopf = bool(np.min(np.abs(np.imag(critical))) > np.sqrt(rtol) * scale)
    return StabilityBoundary(family, jnp.asarray(critical), "Andronov–Hopf" if hopf else "real root through zero", ends)
