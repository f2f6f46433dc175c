"""The pilot of :func:`~nhsde.statistics.to_accuracy`: per candidate solver, ``m`` solves at ``h_ℓ = h₀ 2^{−ℓ}`` on
one Brownian path (and on its reflection), read into the per-sample and level variances and the weak-error model
``E S(h) = S + C h^p`` (the :mod:`._accuracy` module)."""

from __future__ import annotations

import dataclasses
import math
import time

import diffrax as dfx
import jax
import numpy as np

from .._misc import check_number, fold_key
from .._options import RunOptions
from .._solvers import solver_needs
from .._system import StochasticSystem
from .._weak import PlatenWeak2
from ._estimate import AbstractStatistic
from ._paths import coupled_paths, coupling_solver, paired_moments
from ._report import PilotSummary

__all__ = ["Candidate", "candidate", "level_bias_bound", "pick_moments", "pilot_rate", "resolution", "run_pilot"]


# --- the statistic --------------------------------------------------------------------------------------------


def resolution(statistic: AbstractStatistic, names: tuple[str, ...], paths) -> float:
    """The statistic's change, to first order, when each per-path value ``z_i`` of ``paths`` ``(N, n, k)`` moves by
    one unit in the last place of its precision, ``eps·|z_i|``: ``eps Σ_i |∂Ŝ/∂z_i| |z_i|``, for a mean
    ``eps·mean|z|``, for a covariance ``eps Σ_i (|a_i − ā| |b_i| + |a_i| |b_i − b̄|)/(N − 1)``.  No number of paths
    resolves the statistic more finely: a rounding error the paths share (every path's, where they differ less than
    an ulp) averages to itself, and the standard error does not see it."""
    eps = float(np.finfo(paths.dtype).eps)
    z = np.asarray(paths, np.float64)
    n = z.shape[0]
    size, centred = np.abs(z), np.abs(z - z.mean(axis=0))
    cross = np.einsum("pni,pnj->nij", centred, size)
    return eps * float(statistic.pick(names, size.mean(axis=0), (cross + np.swapaxes(cross, -1, -2)) / (n - 1)))


def pick_moments(statistic: AbstractStatistic, names: tuple[str, ...], moments) -> tuple[float, float]:
    """Value and variance of the statistic at the last save time from ``paired_moments``' output."""
    mean, cov, mean_var, cov_var = moments
    return float(statistic.pick(names, mean, cov)), float(statistic.pick(names, mean_var, cov_var))


# --- candidates -------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A solver an estimator runs, with its weak order ``order`` and its name ``label`` in the report."""

    label: str
    solver: str | dfx.AbstractSolver
    order: int

    def check(self, system: StochasticSystem) -> None:
        """Raise ``ValueError`` naming ``solver=`` where the system's driver does not allow it."""
        solver_needs(self.solver, system)

    def converts(self, system: StochasticSystem) -> bool:
        """Whether each step converts ``system`` to the solver's calculus: its drift corrected by
        ``½ Σ_j (∂b_j/∂Z) b_j`` (S0 §2, Remark), a Jacobian of the diffusion per step; never for additive noise."""
        needs = solver_needs(self.solver, system)
        return not system.additive_noise and needs.interpretation not in ("any", system.interpretation)


def candidate(solver: str | dfx.AbstractSolver, weak_order: int | None = None) -> Candidate:
    """``solver`` as a :class:`Candidate`: weak order ``weak_order`` (default 2 for :class:`~nhsde.PlatenWeak2`, else
    1); refused where solves at several steps on one Brownian path do not have the law of plain ones."""
    coupling_solver(solver)
    order = 2 if isinstance(solver, PlatenWeak2) else 1
    if weak_order is not None:
        order = check_number("weak_order", weak_order, integer=True, positive=True)
    if isinstance(solver, str):
        label = solver
    elif isinstance(solver, PlatenWeak2):
        label = f"weak2-{solver.increments}"
    else:
        label = type(solver).__name__
    return Candidate(label, solver, order)


# --- the pilot --------------------------------------------------------------------------------------------------


def _pilot_paths(system, y0, key, run: RunOptions, *, levels: int, n_paths: int, anti: bool):
    """The pilot's per-path values (``coupled_paths`` at ``run``'s step ``h0`` and its halvings) and its work in
    path-steps."""
    dts = tuple(run.dt / 2**ell for ell in range(levels))
    paths, _ = coupled_paths(system, y0, key, run, dts=dts, brownian_dt=dts[-1], n_paths=n_paths, antithetic=anti)
    jax.block_until_ready(paths)
    return paths, float(n_paths * (2 if anti else 1) * sum(run.n_steps * 2**ell for ell in range(levels)))


def level_bias_bound(terms, variances, h0: float, p: int) -> float:
    """``|C|`` bounded from the two finest level terms ``Ŷ_ℓ = S(h_ℓ) − S(h_{ℓ−1}) ≈ −C h_ℓ^p (2^p − 1)`` (``terms``
    for ``ℓ = 1 … L``, squared standard errors ``variances``): ``max_ℓ (|Ŷ_ℓ| + 2 SE_ℓ)/(h_ℓ^p (2^p − 1))``."""
    levels = len(terms)
    return max(
        (abs(y) + 2 * math.sqrt(max(var, 0.0))) / ((h0 / 2**ell) ** p * (2**p - 1))
        for ell, y, var in zip(range(1, levels + 1), terms, variances)
        if ell >= levels - 1
    )


def pilot_rate(system, y0, key, run: RunOptions, **options) -> tuple[float, float]:
    """``(seconds per path-step, path-steps)`` of one more run of a pilot (``run_pilot``'s ``run`` and
    ``options``), compiled by the pilot: its programs' own speed, for comparing solvers whose path-steps cost
    differently."""
    start = time.perf_counter()
    _, work = _pilot_paths(system, y0, fold_key(key, 1), run, **options)
    return (time.perf_counter() - start) / work, work


def run_pilot(system, y0, key, cand: Candidate, run: RunOptions, *, statistic, timed, **options):
    paths, work = _pilot_paths(system, y0, key, run, **options)
    levels, n_paths, anti, h0 = options["levels"], options["n_paths"], options["anti"], run.dt
    assert run.save is not None and run.save.names is not None
    names = run.save.names
    dts = tuple(h0 / 2**ell for ell in range(levels))
    rate = math.nan
    if timed:  # compiled now: time a second run of the same programs
        rate, more = pilot_rate(system, y0, key, run, **options)
        work += more
    plain, refl = paths[:levels], paths[levels:]
    if not all(np.all(np.isfinite(p)) for p in paths):
        raise ValueError(
            f"dt={h0}: the pilot of solver {cand.label} at steps {dts} gave non-finite values; pass a smaller dt "
            "(the coarsest step, where the solver is stable)."
        )

    def stat(sets, weights):
        value, var = pick_moments(statistic, names, paired_moments(sets, weights))
        return value, max(var, 0.0)

    def anti_stat(ells, weights):  # the pair average of the combination: weights halved on both sets
        if not anti:
            return math.nan, math.nan
        sets = [plain[e] for e in ells] + [refl[e] for e in ells]
        return stat(sets, [0.5 * w for w in weights] * 2)

    singles = [stat([plain[ell]], [1.0]) for ell in range(levels)]
    values = tuple(v for v, _ in singles)
    ses = tuple(math.sqrt(var) for _, var in singles)
    diffs = [stat([plain[ell], plain[ell - 1]], [1.0, -1.0]) for ell in range(1, levels)]
    level_vars = (singles[0][1] * n_paths,) + tuple(var * n_paths for _, var in diffs)
    anti_levels = (anti_stat([0], [1.0])[1] * n_paths,) + tuple(
        anti_stat([ell, ell - 1], [1.0, -1.0])[1] * n_paths for ell in range(1, levels)
    )
    p = cand.order
    scale = 2**p - 1
    y_fine = diffs[-1][0]
    c_signed = -y_fine / (dts[-1] ** p * scale)
    # extrapolation: variance of the finest pair's combination, residual bias from two extrapolations
    c = 1 / scale
    ex_var = stat([plain[-2], plain[-1]], [-c, 1 + c])[1] * n_paths
    ex_anti = anti_stat([levels - 2, levels - 1], [-c, 1 + c])[1] * n_paths
    if levels >= 3:
        # E_ℓ − E_{ℓ−1} = (2^p S_ℓ − (2^p + 1) S_{ℓ−1} + S_{ℓ−2}) / (2^p − 1) ≈ C' h_{ℓ−1}^{p+1} (1 − 2^{p+1})
        d, dvar = stat([plain[-1], plain[-2], plain[-3]], [2**p * c, -(2**p + 1) * c, c])
        ex_bound = (abs(d) + 2 * math.sqrt(dvar)) / (dts[-2] ** (p + 1) * (2 ** (p + 1) - 1))
        ex_signed = -d / (dts[-2] ** (p + 1) * (2 ** (p + 1) - 1))
    else:
        ex_bound = ex_signed = math.nan
    return PilotSummary(
        solver=cand.label,
        order=p,
        dts=dts,
        values=values,
        standard_errors=ses,
        variance=singles[-1][1] * n_paths,
        antithetic_variance=anti_stat([levels - 1], [1.0])[1] * n_paths,
        level_variances=level_vars,
        antithetic_level_variances=anti_levels,
        bias_constant=c_signed,
        bias_bound=level_bias_bound([y for y, _ in diffs], [var for _, var in diffs], dts[0], p),
        extrapolation_variance=ex_var,
        antithetic_extrapolation_variance=ex_anti,
        extrapolation_constant=ex_signed,
        extrapolation_bound=ex_bound,
        work=work,
        seconds_per_path_step=rate,
        resolution=resolution(statistic, names, plain[-1]),
    )
