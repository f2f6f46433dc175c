"""One call: a statistic to a requested accuracy, by the cheapest estimator a pilot predicts.

:func:`to_accuracy` runs a short pilot for each candidate solver (Euler–Maruyama,
weak order ``p = 1``; :class:`~nhsde.PlatenWeak2` with Gaussian increments,
``p = 2``): ``m`` solves at ``h_ℓ = h₀ 2^{−ℓ}``, ``ℓ < m``, on one Brownian path
(and on its reflection, for antithetic paths).  From the per-path values it
reads the per-sample variance ``V`` of the statistic, the level variances
``V_ℓ`` of the multilevel differences, and the weak-error model

    E S(h) = S + C h^p + O(h^{p+1}),   C = −Ŷ_ℓ / (h_ℓ^p (2^p − 1)),   Ŷ_ℓ = S(h_ℓ) − S(h_{ℓ−1})

(Talay & Tubaro 1990; the differences are the extrapolation corrections),
bounded above by ``|C| ≤ (|Ŷ_ℓ| + 2 SE)/(h_ℓ^p (2^p − 1))`` over the two finest
differences.  For a target RMSE ``ε`` it predicts the work (path-steps) of

- plain Monte Carlo at its best ``(h, N)``: ``N = V/(ε² − C²h^{2p})``, work ``N T/h``
  (Glasserman 2004, §1.1.3, the bias–variance split);
- Richardson–Romberg extrapolation (:func:`extrapolate`) at its best ``(h, N)``,
  residual bias ``C' h^{p+1}`` from the difference of two extrapolations, work ``3 N T/h``;
- multilevel Monte Carlo (:func:`multilevel_monte_carlo`): levels until
  ``|C| h_L^p ≤ ε/√2``, ``V_ℓ`` beyond the pilot decaying at the pilot's rate
  ``2^{−β}``, work ``2ε⁻² (Σ_ℓ √(V_ℓ C_ℓ))²`` (Giles 2008) with samples rounded to whole pieces
  (run with this allocation fixed);
- each of these with antithetic pairs (work doubled, the pair's variance);
- a control variate, where :mod:`nhsde.statistics` provides one;
- randomised quasi-Monte Carlo (:func:`quasi_monte_carlo`, Euler, 16 scramblings of a power of two
  paths each), where ``(t1 − t0)/h₀`` is a power of two and the driver is continuous: its variance
  from a pilot of 8 scramblings, its error assumed to fall only as ``N^{−1/2}`` beyond it (so its predicted work
  is an upper bound where it converges faster), Euler's bias bound, and its work converted to Euler
  path-steps by the measured ratio ``κ`` of its seconds per path-step to plain Euler Monte Carlo's;

runs the cheapest whose per-path values fit in memory (``_cost.py``; none fits: a
``ValueError`` with the size) and returns its value, standard error and bias estimate
with the work predicted and done (path-steps, pilot included), the seconds with the
compile time apart, and a report of every alternative.  With ``wrt``
the chosen estimator also returns the statistic's pathwise derivatives in those
parameters with their Monte-Carlo standard errors (per-path tangents; the target
applies to the value, the derivatives come from the same paths).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import diffrax as dfx
import jax
import numpy as np

from .._brownian import BLOCK
from .._ensemble import Save
from .._misc import check_key, check_number, check_span, check_steps, fold_key, is_concrete, split_key
from .._options import AbstractSteps, Batching, FixedSteps
from .._simulate import MAX_PATH_INDEX, stable_step
from .._solvers import solver_needs
from .._system import StochasticSystem
from .._weak import PlatenWeak2
from ._control_variate import control_variate as linearised_control_variate
from ._cost import (
    MAX_REFINEMENTS,
    best_single,
    check_memory,
    compile_clock,
    memory_limit,
    multilevel_plan,
    path_bytes,
    peak_bytes,
    whole_pieces,
)
from ._extrapolation import RUN_PATHS, coupled_paths, coupling_solver, extrapolate, paired_moments, solve_paths
from ._multilevel import MultilevelEstimate, multilevel_monte_carlo
from ._qmc import MAX_DIMENSION, quasi_monte_carlo as randomised_quasi_monte_carlo
from ._sensitivities import check_wrt

__all__ = ["AccuracyAlternative", "AccuracyResult", "to_accuracy"]


@dataclasses.dataclass(frozen=True)
class AccuracyAlternative:
    """One way to reach the target: its predicted work (``cost``, path-steps; ``inf`` where it does not apply).

    ``dt`` is the step (plain Monte Carlo), the coarse step (extrapolation) or ``h₀``
    (multilevel); ``n_paths`` the samples (pairs, with ``antithetic``), per level for multilevel.
    ``kappa``: the cost of one of its path-steps in plain Euler path-steps (measured for quasi-Monte Carlo,
    else 1), so that it predicts ``cost/kappa`` path-steps; ``memory``: the bytes its per-path values take at
    their peak (:mod:`~nhsde.statistics._cost`).
    """

    name: str
    method: str
    solver: str
    antithetic: bool
    cost: float
    dt: float = math.nan
    n_paths: tuple[int, ...] = ()
    bias: float = math.nan
    seconds: float = math.nan
    note: str = ""
    pilot_work: float = 0.0
    kappa: float = 1.0
    memory: float = 0.0
    run: Callable | None = dataclasses.field(default=None, repr=False, compare=False)


@dataclasses.dataclass(frozen=True)
class PilotSummary:
    """What the pilot of one solver measured: values and standard errors per level, variances, the bias model."""

    solver: str
    order: int
    dts: tuple[float, ...]
    values: tuple[float, ...]
    standard_errors: tuple[float, ...]
    variance: float  # per sample, finest level
    antithetic_variance: float  # per pair, finest level (nan without antithetic paths)
    level_variances: tuple[float, ...]
    antithetic_level_variances: tuple[float, ...]
    bias_constant: float  # signed C of E S(h) − S ≈ C h^p, from the finest difference
    bias_bound: float  # upper bound on |C|
    extrapolation_variance: float
    antithetic_extrapolation_variance: float
    extrapolation_constant: float  # signed C' of the extrapolation's bias C' h^{p+1}
    extrapolation_bound: float  # upper bound on |C'|
    work: float
    seconds_per_path_step: float


@dataclasses.dataclass(frozen=True)
class AccuracyResult:
    """The statistic to the requested accuracy: ``value ± standard_error`` with estimated ``bias``.

    ``rmse`` is the absolute target, ``work`` the path-steps done (pilot included,
    ``pilot_work`` of them), ``seconds`` the wall time of the call, ``compile_seconds`` the part of it spent
    tracing and compiling (JAX's compilation events); the chosen estimator's run was predicted to take
    ``predicted_work`` path-steps (and ``predicted_seconds``, with ``cost='seconds'``, else ``nan``) and took
    ``run_work`` path-steps in ``run_seconds`` (compilation included).  ``choice`` the name of the alternative run,
    ``alternatives`` all of them with their predicted work, ``pilot`` one summary
    per solver, ``result`` what the chosen estimator returned.  ``derivative`` and
    ``derivative_se`` ``(len(wrt),)``: the statistic's derivatives in the parameters
    ``wrt`` and their standard errors (empty without ``wrt``).  ``report()`` (also
    ``str``) prints it as a short table.
    """

    statistic: tuple
    value: float
    standard_error: float
    bias: float
    rmse: float
    work: float
    pilot_work: float
    seconds: float
    compile_seconds: float
    predicted_work: float
    predicted_seconds: float
    run_work: float
    run_seconds: float
    choice: str
    reason: str
    alternatives: tuple[AccuracyAlternative, ...]
    pilot: tuple[PilotSummary, ...]
    wrt: tuple[str, ...]
    derivative: np.ndarray
    derivative_se: np.ndarray
    result: object = dataclasses.field(repr=False, compare=False)

    @property
    def estimated_rmse(self) -> float:
        """``√(SE² + bias²)``, the bias taken as 0 where it is not estimated."""
        bias = 0.0 if not math.isfinite(self.bias) else self.bias
        return math.hypot(self.standard_error, bias)

    def report(self) -> str:
        stat = " ".join(self.statistic)
        lines = [
            f"{stat} at target rmse {self.rmse:.3g}: {self.value:.6g} ± {self.standard_error:.2g} "
            f"(bias estimate {self.bias:.2g}); work {self.work:.3g} path-steps, pilot {self.pilot_work:.3g}; "
            f"{self.seconds:.1f} s, {self.compile_seconds:.1f} s of it compiling",
            f"run: predicted {self.predicted_work:.3g} path-steps"
            + (f" in {self.predicted_seconds:.3g} s" if math.isfinite(self.predicted_seconds) else "")
            + f", measured {self.run_work:.3g} in {self.run_seconds:.3g} s",
            *(
                f"  d/d{name} = {d:.6g} ± {se:.2g}"
                for name, d, se in zip(self.wrt, self.derivative, self.derivative_se, strict=True)
            ),
            "pilot (per-sample variance V at the finest pilot step; level variances V_ℓ; bias E S(h) − S ≈ C h^p):",
            f"  {'solver':<22}{'dts':<24}{'V':>11}{'V anti':>11}{'C':>11}{'|C| ≤':>11}  V_ℓ",
        ]
        for p in self.pilot:
            dts = ",".join(f"{h:g}" for h in p.dts)
            lv = " ".join(f"{v:.3g}" for v in p.level_variances)
            lines.append(
                f"  {p.solver:<22}{dts:<24}{p.variance:>11.3g}{p.antithetic_variance:>11.3g}"
                f"{p.bias_constant:>11.3g}{p.bias_bound:>11.3g}  {lv}"
            )
        lines.append("alternatives (predicted work to reach the target):")
        timed = any(math.isfinite(a.seconds) for a in self.alternatives)
        seconds = f"{'seconds':>10}" if timed else ""
        lines.append(f"  {'':<2}{'alternative':<44}{'path-steps':>12}{seconds}{'dt':>10}  n_paths / note")
        for a in self.alternatives:
            mark = "→" if a.name == self.choice else ""
            count = ",".join(map(str, a.n_paths)) if a.n_paths else ""
            detail = "  ".join(s for s in (count, a.note) if s)
            seconds = f"{a.seconds:>10.3g}" if timed else ""
            lines.append(f"  {mark:<2}{a.name:<44}{a.cost:>12.3g}{seconds}{a.dt:>10.3g}  {detail}")
        lines.append(f"chosen: {self.choice}: {self.reason}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.report()


# --- the statistic --------------------------------------------------------------------------------------------


def check_statistic(statistic, names: tuple[str, ...]):
    """``(kind, i, j)`` of ``('mean', a)`` or ``('cov', a, b)`` among ``names``; else a ``ValueError``."""
    ok = isinstance(statistic, tuple) and (
        (len(statistic) == 2 and statistic[0] == "mean") or (len(statistic) == 3 and statistic[0] == "cov")
    )
    if not ok or not all(isinstance(n, str) for n in statistic):
        raise ValueError(f"statistic={statistic!r}; expected ('mean', name) or ('cov', name_a, name_b).")
    missing = [n for n in statistic[1:] if n not in names]
    if missing:
        raise ValueError(f"statistic={statistic!r} names {missing}, which are not saved; available: {names}.")
    return statistic[0], names.index(statistic[1]), names.index(statistic[-1])


def _derivative_of(result, index, wrt: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The statistic's derivatives and their standard errors ``(len(wrt),)`` from an estimator's result."""
    if not wrt:
        return np.zeros(0), np.zeros(0)
    if isinstance(result, MultilevelEstimate):
        d, se = result.d_value, result.d_value_se
    else:
        kind, i, j = index
        r = result.derivatives
        d, se = (
            (r.d_mean[:, -1, i], r.d_mean_se[:, -1, i])
            if kind == "mean"
            else (r.d_cov[:, -1, i, j], r.d_cov_se[:, -1, i, j])
        )
    return np.asarray(d, dtype=float), np.asarray(se, dtype=float)


def _pick(kind, i, j, moments):
    """Value and variance of the statistic at the last save time from ``paired_moments``' output."""
    mean, cov, mean_var, cov_var = moments
    if kind == "mean":
        return float(mean[-1, i]), float(mean_var[-1, i])
    return float(cov[-1, i, j]), float(cov_var[-1, i, j])


# --- candidates -------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Candidate:
    label: str
    solver: str | dfx.AbstractSolver
    order: int


def _candidates(system: StochasticSystem, solver, weak_order) -> tuple[list[_Candidate], list[str]]:
    """The solvers to consider and, for the default set, notes on those that do not apply."""
    if solver is not None:
        coupling_solver(solver)
        solver_needs(solver, system)  # raises naming solver= when it does not apply
        order = 2 if isinstance(solver, PlatenWeak2) else 1
        if weak_order is not None:
            order = check_number("weak_order", weak_order, integer=True, positive=True)
        label = solver if isinstance(solver, str) else type(solver).__name__
        return [_Candidate(str(label), solver, order)], []
    out, notes = [], []
    for label, s, p in (("euler", "euler", 1), ("weak2-gaussian", PlatenWeak2(increments="gaussian"), 2)):
        try:
            solver_needs(s, system)
        except ValueError as e:
            notes.append(f"{label}: {e}")
            continue
        out.append(_Candidate(label, s, p))
    return out, notes


# --- the pilot --------------------------------------------------------------------------------------------------


def _pilot(system, y0, key, cand: _Candidate, *, t0, t1, h0, levels, n_paths, save, anti, batching, kind, i, j, timed):
    dts = tuple(h0 / 2**ell for ell in range(levels))
    steps0 = round((t1 - t0) / h0)
    opts: dict[str, Any] = dict(
        t0=t0, t1=t1, dts=dts, brownian_dt=dts[-1], solver=cand.solver, save=save, batching=batching
    )
    paths, _ = coupled_paths(system, y0, key, n_paths=n_paths, antithetic=anti, **opts)
    jax.block_until_ready(paths)
    n_sys = 2 if anti else 1
    work = float(n_paths * n_sys * sum(steps0 * 2**ell for ell in range(levels)))
    rate = math.nan
    if timed:  # compiled now: time a second run of the same programs
        start = time.perf_counter()
        jax.block_until_ready(coupled_paths(system, y0, fold_key(key, 1), n_paths=n_paths, antithetic=anti, **opts))
        rate = (time.perf_counter() - start) / work  # one run's seconds over one run's work
        work *= 2
    plain, refl = paths[:levels], paths[levels:]
    if not all(np.all(np.isfinite(p)) for p in paths):
        raise ValueError(
            f"dt={h0}: the pilot of solver {cand.label} at steps {dts} gave non-finite values; pass a smaller dt "
            "(the coarsest step, where the solver is stable)."
        )

    def stat(sets, weights):
        value, var = _pick(kind, i, j, paired_moments(sets, weights))
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
    finest = diffs[-2:]  # Ŷ_ℓ for the two finest ℓ
    bounds = [
        (abs(y) + 2 * math.sqrt(var)) / (dts[ell] ** p * scale)
        for ell, (y, var) in zip(range(levels - len(finest), levels), finest)
    ]
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
        bias_bound=max(bounds),
        extrapolation_variance=ex_var,
        antithetic_extrapolation_variance=ex_anti,
        extrapolation_constant=ex_signed,
        extrapolation_bound=ex_bound,
        work=work,
        seconds_per_path_step=rate,
    )


# --- the entry point --------------------------------------------------------------------------------------------


def to_accuracy(
    system: StochasticSystem,
    y0,
    key,
    *,
    t1: float,
    statistic: tuple,
    rmse: float | None = None,
    relative_rmse: float | None = None,
    t0: float = 0.0,
    dt: float | None = None,
    steps: AbstractSteps | None = None,
    solver=None,
    weak_order: int | None = None,
    save: Save | None = None,
    antithetic: bool | None = None,
    pilot_paths: int = 1024,
    pilot_levels: int = 3,
    max_path_steps: float = 1e11,
    cost: str = "path-steps",
    control_variate: bool = True,
    quasi_monte_carlo: bool = True,
    batching: Batching | None = None,
    wrt: Sequence[str] | None = None,
) -> AccuracyResult:
    """``statistic`` at ``t1`` to a root-mean-square error ``rmse`` by the estimator a pilot predicts cheapest (module).

    Arguments as :func:`~nhsde.simulate`, and:

    - ``statistic``: ``('mean', name)`` or ``('cov', name_a, name_b)`` at ``t1``; the names
      must be saved (``save.names``, default the statistic's names, of the system's observables).
    - ``rmse``: the absolute target, or ``relative_rmse``: relative to the pilot's ``|value|``.
    - ``dt`` (or ``steps=FixedSteps(dt)``): the coarsest step ``h₀`` considered (default
      ``(t1 − t0)/4``, halved until every solver considered is inside its stability limit on the
      system's declared friction); pilots run at ``h₀ … h₀ 2^{1−pilot_levels}``, every alternative at ``h₀`` or finer.
    - ``solver``: consider only this one (``PlatenWeak2`` needs ``increments='gaussian'``),
      of weak order ``weak_order`` (default 2 for ``PlatenWeak2``, else 1); default: Euler–Maruyama
      and ``PlatenWeak2(increments='gaussian')``, those the system's driver allows.
    - ``antithetic``: ``None`` considers both plain and antithetic paths (Wiener drivers),
      ``True``/``False`` only those.
    - ``pilot_paths``, ``pilot_levels`` (≥ 2; 3 to estimate the extrapolation's bias).
    - ``max_path_steps``: refuse (``ValueError``) when the cheapest predicted work exceeds it; alternatives whose
      per-path values would not fit in the device's memory are passed over (none fits: a ``ValueError`` with the
      size).
    - ``cost``: ``'path-steps'``, or ``'seconds'`` (path-steps times each solver's
      measured seconds per path-step from a second, compiled, pilot run).
    - ``control_variate``: consider a control variate where one is available.
    - ``quasi_monte_carlo``: consider randomised quasi-Monte Carlo (Euler) where it applies: ``(t1 − t0)/dt``
      a power of two, a continuous driver, ``solver`` Euler or the default set.  Its pilot (8 scramblings of
      ``pilot_paths/8`` paths rounded down to a power of two, run twice to time it) predicts its work from its
      variance at the Monte-Carlo rate ``N^{−1/2}``, an upper bound where it converges faster; its work is
      counted in Euler path-steps (times the measured cost ratio ``κ``, in the report's note).
    - ``wrt``: names of scalar parameters (``('eps', 'nu')``): the statistic's derivatives in them with their
      standard errors (``derivative``, ``derivative_se``), from the chosen estimator's per-path tangents.
    """
    t_start, compiled_start = time.perf_counter(), compile_clock()
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if (rmse is None) == (relative_rmse is None):
        raise TypeError(f"rmse={rmse!r}, relative_rmse={relative_rmse!r}: give exactly one of them.")
    if rmse is not None:
        rmse = check_number("rmse", rmse, positive=True)
    else:
        relative_rmse = check_number("relative_rmse", relative_rmse, positive=True)
    if steps is not None:
        if dt is not None:
            raise TypeError(f"dt={dt} and steps={steps!r}: give the coarsest step once.")
        if not isinstance(steps, FixedSteps) or steps.brownian_dt is not None:
            raise ValueError(
                f"steps={steps!r}: the estimators compare solves on fixed step grids h₀ 2^−ℓ; use dt=h₀ or "
                "steps=FixedSteps(h₀) (without brownian_dt)."
            )
        dt = steps.dt
    t0, t1 = check_span(t0, t1)
    candidates, skipped = _candidates(system, solver, weak_order)
    if dt is None:  # the coarsest step: (t1 − t0)/4, halved until every candidate damps the declared friction
        dt = (t1 - t0) / 4
        while not all(stable_step(system, c.solver, dt) for c in candidates) and dt > (t1 - t0) / 2**30:
            dt /= 2
    h0 = check_number("dt", dt, positive=True)
    steps0 = check_steps("dt", t1 - t0, h0)
    if save is not None and not isinstance(save, Save):
        raise TypeError(f"save={save!r}; expected nhsde.Save(...).")
    offered = system.observable_names() if save is None or save.names is None else save.names
    kind, i, j = check_statistic(statistic, offered)
    names = tuple(dict.fromkeys(statistic[1:])) if save is None or save.names is None else save.names
    if save is None or save.names is None:
        kind, i, j = check_statistic(statistic, names)
    n_save = 2 if save is None or save.n is None else save.n
    if steps0 % (n_save - 1):
        raise ValueError(f"save.n={n_save}: n − 1 must divide the {steps0} steps of the coarsest step dt={h0}.")
    save = Save(names=names, n=n_save, paths=True)
    if antithetic is not None and not isinstance(antithetic, bool):
        raise TypeError(f"antithetic={antithetic!r}; expected None, True or False.")
    if antithetic and not system.noise.continuous:
        raise ValueError(
            f"antithetic=True: the driver {type(system.noise).__name__} has jumps, whose law is not symmetric under "
            "W → −W; antithetic paths need a Wiener driver."
        )
    pilot_paths = check_number("pilot_paths", pilot_paths, integer=True)
    if pilot_paths < BLOCK or pilot_paths % BLOCK:
        raise ValueError(f"pilot_paths={pilot_paths}; must be a positive multiple of {BLOCK}.")
    pilot_levels = check_number("pilot_levels", pilot_levels, integer=True)
    if not 2 <= pilot_levels <= 6:
        raise ValueError(f"pilot_levels={pilot_levels}; allowed: 2 … 6.")
    max_path_steps = check_number("max_path_steps", max_path_steps, positive=True)
    if cost not in ("path-steps", "seconds"):
        raise ValueError(f"cost={cost!r}; allowed: 'path-steps', 'seconds'.")
    wrt = () if wrt is None else check_wrt(system, wrt)
    if not is_concrete(system, y0):
        raise TypeError("to_accuracy chooses path counts from a pilot: it needs concrete parameters, not traced ones.")
    key = check_key(key)
    pilot_key, run_key = split_key(key)
    use_anti = system.noise.continuous and antithetic is not False
    timed = cost == "seconds"

    pilots = [
        _pilot(
            system,
            y0,
            fold_key(pilot_key, c),
            cand,
            t0=t0,
            t1=t1,
            h0=h0,
            levels=pilot_levels,
            n_paths=pilot_paths,
            save=save,
            anti=use_anti,
            batching=batching,
            kind=kind,
            i=i,
            j=j,
            timed=timed,
        )
        for c, cand in enumerate(candidates)
    ]
    pilot_work = sum(p.work for p in pilots)
    if rmse is None:
        best = min(pilots, key=lambda p: p.standard_errors[-1])
        value, se = best.values[-1], best.standard_errors[-1]
        if not abs(value) > 2 * se:
            raise ValueError(
                f"relative_rmse={relative_rmse}: the pilot's value {value:.3g} ± {se:.2g} is not distinguishable "
                "from 0; give an absolute rmse= instead."
            )
        assert relative_rmse is not None
        rmse = relative_rmse * abs(value)

    common: dict[str, Any] = dict(
        run=dict(t0=t0, t1=t1, save=save, batching=batching, wrt=wrt or None),
        t0=t0,
        t1=t1,
        save=save,
        target=statistic,
        index=(kind, i, j),
        pilot_paths=pilot_paths,
        pilot_levels=pilot_levels,
    )
    alternatives: list[AccuracyAlternative] = []
    for cand, p in zip(candidates, pilots):
        alternatives += _alternatives(system, y0, run_key, cand, p, rmse, h0, steps0, use_anti, antithetic, common)
    for note in skipped:
        label = note.split(":", 1)[0]
        alternatives.append(AccuracyAlternative(f"any, {label}", "-", label, False, math.inf, note=note))
    if control_variate and (solver is None or solver == "euler" or type(solver) is dfx.Euler):
        alternatives.append(_control_variate_alternative(system, y0, pilot_key, run_key, rmse, h0, steps0, common))
    euler = next((p for c, p in zip(candidates, pilots) if c.solver == "euler" or type(c.solver) is dfx.Euler), None)
    if quasi_monte_carlo and euler is not None:
        alternatives.append(
            _quasi_monte_carlo_alternative(system, y0, pilot_key, run_key, rmse, h0, steps0, euler, common)
        )
    pilot_work += sum(a.pilot_work for a in alternatives)
    per_sample = path_bytes(n_save, len(names), len(wrt))
    alternatives = [dataclasses.replace(a, memory=peak_bytes(_kept_samples(a) * per_sample)) for a in alternatives]
    if timed:
        rates = {p.solver: p.seconds_per_path_step for p in pilots}
        alternatives = [dataclasses.replace(a, seconds=a.cost * rates.get(a.solver, math.nan)) for a in alternatives]
    key_of = (lambda a: a.seconds if math.isfinite(a.seconds) else math.inf) if timed else (lambda a: a.cost)
    ranked = sorted((a for a in alternatives if a.run is not None and math.isfinite(key_of(a))), key=key_of)
    if not ranked:
        raise ValueError(f"rmse={rmse:.3g}: no alternative can reach it from dt={h0}; see the pilot:\n{pilots}")
    fitting = [a for a in ranked if a.memory <= memory_limit()]
    if not fitting:
        check_memory(
            f"rmse={rmse:.3g}: the cheapest way, {ranked[0].name},",
            ranked[0].memory,
            "raise rmse (every alternative keeps its per-path values).",
        )
    ranked = fitting
    chosen = ranked[0]
    if chosen.cost > max_path_steps:
        raise ValueError(
            f"max_path_steps={max_path_steps:.3g}: the cheapest way to rmse={rmse:.3g}, {chosen.name}, is predicted "
            f"to take {chosen.cost:.3g} path-steps; raise max_path_steps or the target."
        )
    unit = "s" if timed else "path-steps"
    reason = f"cheapest predicted work ({key_of(chosen):.3g} {unit})"
    if len(ranked) > 1 and key_of(chosen) > 0:
        reason += f", {key_of(ranked[1]) / key_of(chosen):.2g}× below the next, {ranked[1].name}"
    assert chosen.run is not None
    run_start = time.perf_counter()
    value, se, bias, work, result = chosen.run()
    run_seconds = time.perf_counter() - run_start
    derivative, derivative_se = _derivative_of(result, (kind, i, j), wrt)
    return AccuracyResult(
        statistic=statistic,
        value=float(value),
        standard_error=float(se),
        bias=float(bias),
        rmse=float(rmse),
        work=float(work + pilot_work),
        pilot_work=float(pilot_work),
        seconds=time.perf_counter() - t_start,
        compile_seconds=compile_clock() - compiled_start,
        predicted_work=chosen.cost / chosen.kappa,
        predicted_seconds=chosen.seconds,
        run_work=float(work),
        run_seconds=run_seconds,
        choice=chosen.name,
        reason=reason,
        alternatives=tuple(alternatives),
        pilot=tuple(pilots),
        wrt=wrt,
        derivative=derivative,
        derivative_se=derivative_se,
        result=result,
    )


def _kept_samples(a: AccuracyAlternative) -> float:
    """Per-path value sets an alternative's run keeps: one per solve of each sample (quasi-Monte Carlo keeps
    moments only)."""
    pairs = 2 if a.antithetic else 1
    if a.method == "multilevel":
        return pairs * sum(n * (2 if ell else 1) for ell, n in enumerate(a.n_paths))
    solves = {"plain": 1, "extrapolation": 2, "control variate": 2}.get(a.method, 0)
    return pairs * solves * sum(a.n_paths)


def _alternatives(system, y0, key, cand: _Candidate, p: PilotSummary, eps, h0, steps0, use_anti, antithetic, common):
    """Plain Monte Carlo, extrapolation and multilevel for one solver, each plain and antithetic as allowed."""
    out = []
    variants = [a for a in (False, True) if (a and use_anti) or (not a and antithetic is not True)]
    for anti in variants:
        tag = f"{cand.label}{', antithetic' if anti else ''}"
        factor = 2.0 if anti else 1.0
        v = p.antithetic_variance if anti else p.variance
        c, k, n, bias = best_single(v, p.bias_bound, p.order, eps, h0, steps0, factor)
        h = h0 / 2**k if k >= 0 else math.nan
        out.append(
            AccuracyAlternative(
                f"plain MC, {tag}",
                "plain",
                cand.label,
                anti,
                c,
                dt=h,
                n_paths=(n,) if n else (),
                bias=p.bias_constant * h**p.order if k >= 0 else math.nan,
                note="" if k >= 0 else "bias bound above the target at every step",
                run=_runner_plain(system, y0, key, cand, h, n, anti, p, common) if k >= 0 else None,
            )
        )
        ve = p.antithetic_extrapolation_variance if anti else p.extrapolation_variance
        c, k, n, _ = best_single(ve, p.extrapolation_bound, p.order + 1, eps, h0, steps0, 3 * factor)
        h = h0 / 2**k if k >= 0 else math.nan
        bias = p.extrapolation_constant * h ** (p.order + 1)
        note = "" if k >= 0 else ("needs pilot_levels ≥ 3" if not math.isfinite(ve + p.extrapolation_bound) else "")
        out.append(
            AccuracyAlternative(
                f"extrapolation, {tag}",
                "extrapolation",
                cand.label,
                anti,
                c,
                dt=h,
                n_paths=(n,) if n else (),
                bias=bias,
                note=note,
                run=_runner_extrapolation(system, y0, key, cand, h, n, anti, bias, common) if k >= 0 else None,
            )
        )
        lv = p.antithetic_level_variances if anti else p.level_variances
        c, counts, piece, n_levels = multilevel_plan(
            lv, p.bias_bound, p.order, eps, steps0, h0, anti, common["pilot_paths"]
        )
        out.append(
            AccuracyAlternative(
                f"multilevel, {tag}",
                "multilevel",
                cand.label,
                anti,
                c,
                dt=h0,
                n_paths=counts,
                note=f"{n_levels} levels" if n_levels else "too many levels",
                run=_runner_multilevel(system, y0, key, cand, h0, counts, piece, anti, common) if n_levels else None,
            )
        )
    return out


def _statistic_of(run_result, statistic_index):
    """``(value, standard error)`` of the statistic at the last save time (read on the host: no program)."""
    kind, i, j = statistic_index
    if kind == "mean":
        return np.asarray(run_result.mean)[-1, i], np.asarray(run_result.mean_se)[-1, i]
    return np.asarray(run_result.cov)[-1, i, j], np.asarray(run_result.cov_se)[-1, i, j]


def _runner_plain(system, y0, key, cand, h, n, anti, p: PilotSummary, common):
    def run():
        n_total, piece = whole_pieces(n)
        res = multilevel_monte_carlo(
            system,
            y0,
            key,
            n_paths=(n_total,),
            dt=h,
            solver=cand.solver,
            antithetic=anti,
            piece_paths=piece,
            target=common["target"],
            **common["run"],
        )
        return res.value, res.standard_error, p.bias_constant * h**p.order, res.cost, res

    return run


def _runner_extrapolation(system, y0, key, cand, h, n, anti, bias, common):
    def run():
        res = extrapolate(
            system,
            y0,
            key,
            n_paths=n,
            dt=h,
            solver=cand.solver,
            order=cand.order,
            antithetic=anti,
            **common["run"],
        )
        value, se = _statistic_of(res, common["index"])
        steps = round((common["t1"] - common["t0"]) / h)
        return value, se, bias, n * 3 * steps * (2 if anti else 1), res

    return run


def _runner_multilevel(system, y0, key, cand, h0, counts, piece, anti, common):
    """The pilot's allocation, fixed: samples independent of the choice (an adaptive allocation from its own
    samples stops early on low estimates of a variance, biasing a covariance low)."""

    def run():
        res = multilevel_monte_carlo(
            system,
            y0,
            key,
            n_paths=counts,
            dt=h0,
            solver=cand.solver,
            weak_order=cand.order,
            antithetic=anti,
            piece_paths=piece,
            target=common["target"],
            **common["run"],
        )
        return res.value, res.standard_error, res.bias, res.cost, res

    return run


def _control_variate_alternative(system, y0, pilot_key, run_key, eps, h0, steps0, common) -> AccuracyAlternative:
    """The control variate of :func:`~nhsde.statistics.control_variate` (Euler).  Pilot: it at the two finest pilot
    steps on one Brownian path; its variance per path at the finest, its bias ``C h`` bounded by
    ``(|ΔŶ| + 2(SE_a + SE_b))/h_b`` (Euler, ``p = 1``)."""
    name = "control variate, euler"
    kind, i, j = common["index"]
    opts = dict(t0=common["t0"], t1=common["t1"], batching=common["run"]["batching"])
    save = Save(names=common["save"].names, n=common["save"].n)
    n_pilot, levels = common["pilot_paths"], common["pilot_levels"]
    h_a, h_b = h0 / 2 ** (levels - 2), h0 / 2 ** (levels - 1)
    key = fold_key(pilot_key, 99)
    try:
        runs = [
            linearised_control_variate(
                system, y0, key, n_paths=n_pilot, steps=FixedSteps(h, brownian_dt=h_b), save=save, **opts
            )
            for h in (h_a, h_b)
        ]
    except (ValueError, TypeError, NotImplementedError) as e:
        return AccuracyAlternative(name, "control variate", "euler", False, math.inf, note=f"does not apply: {e}")
    (va, sa), (vb, sb) = (tuple(float(x) for x in _statistic_of(r, (kind, i, j))) for r in runs)
    if not all(math.isfinite(x) for x in (va, sa, vb, sb)):
        return AccuracyAlternative(name, "control variate", "euler", False, math.inf, note="non-finite pilot")
    work = sum(float(r.cost) for r in runs)
    variance = sb**2 * n_pilot
    bound = (abs(vb - va) + 2 * (sa + sb)) / h_b
    per_path_step = float(runs[1].cost) / n_pilot / (steps0 * 2 ** (levels - 1))
    c, k, n, _ = best_single(variance, bound, 1, eps, h0, steps0, per_path_step)
    if k < 0:
        return AccuracyAlternative(
            name, "control variate", "euler", False, math.inf, note="no step reaches the target", pilot_work=work
        )
    h = h0 / 2**k
    bias = -(vb - va) / h_b * h  # E Ŷ(h) − S ≈ C h with C = −ΔŶ/h_b (p = 1)

    def run():
        res = linearised_control_variate(
            system, y0, run_key, n_paths=n, dt=h, save=save, wrt=common["run"]["wrt"], **opts
        )
        value, se = _statistic_of(res, (kind, i, j))
        return value, se, bias, float(res.cost), res

    return AccuracyAlternative(
        name, "control variate", "euler", False, c, dt=h, n_paths=(n,), bias=bias, run=run, pilot_work=work
    )


QMC_PILOT_REPLICATES = 8
QMC_REPLICATES = 16


def _quasi_monte_carlo_alternative(
    system, y0, pilot_key, run_key, eps, h0, steps0, euler: PilotSummary, common
) -> AccuracyAlternative:
    """Randomised quasi-Monte Carlo (:func:`~nhsde.statistics.quasi_monte_carlo`, Euler, ``p = 1``).

    Pilot: 8 scramblings of ``n_q`` paths (``pilot_paths/8`` rounded down to a power of two, ≥ 64) at the finest pilot
    step ``h_b``, run twice (the second, compiled, timed).  Its variance per path-equivalent
    ``V_q = SE² · 8 n_q`` is assumed to fall only as ``1/N`` beyond the pilot, the Monte-Carlo rate: the
    predicted work is an upper bound where quasi-Monte Carlo converges faster (``N^{−0.7} … N^{−1}`` on smooth
    statistics), and the run's standard error comes out below the prediction.  The bias is Euler's: its pilot's
    bound ``|C| h`` and signed estimate ``C h`` (the scrambled points give every path the law of a Monte-Carlo
    path, so the scheme's bias is unchanged).  Work in Euler path-steps: its path-steps times ``κ``, the
    measured seconds per path-step over those of a compiled plain Euler :func:`~nhsde.simulate` of the same
    paths and step, timed here in either cost mode (its work is counted in the pilot's); with
    ``cost='seconds'`` its seconds are then, as every Euler alternative's, its Euler path-steps times the Euler
    pilot's seconds per path-step.  Steps ``h₀ 2^{−k}`` only while ``steps × channels`` stays within the Sobol'
    dimensions; the run takes 16 scramblings of a power of two ≥ 64 paths each."""
    name, method, label = "quasi-Monte Carlo, euler", "quasi-Monte Carlo", euler.solver
    kind, i, j = common["index"]
    opts: dict[str, Any] = dict(t0=common["t0"], t1=common["t1"], batching=common["run"]["batching"])
    save = Save(names=common["save"].names, n=common["save"].n)
    levels = common["pilot_levels"]
    h_b, steps_b = h0 / 2 ** (levels - 1), steps0 * 2 ** (levels - 1)
    r_pilot = QMC_PILOT_REPLICATES  # n_q paths each, the other pilots' paths in all
    n_q = max(BLOCK, 1 << ((common["pilot_paths"] // r_pilot).bit_length() - 1))

    def skip(note, work=0.0):
        return AccuracyAlternative(name, method, label, False, math.inf, note=note, pilot_work=work)

    if steps0 & (steps0 - 1):
        return skip(f"does not apply: (t1 − t0)/dt = {steps0} steps, not a power of two")
    if not system.noise.continuous:
        return skip(f"does not apply: the driver {type(system.noise).__name__} has jumps")
    key = fold_key(pilot_key, 98)

    def pilot(k):
        start = time.perf_counter()
        res = randomised_quasi_monte_carlo(system, y0, k, n_paths=n_q, replicates=r_pilot, dt=h_b, save=save, **opts)
        jax.block_until_ready((res.mean, res.cov, res.mean_se, res.cov_se))
        return res, time.perf_counter() - start

    try:
        res, _ = pilot(key)
    except (ValueError, TypeError) as e:
        return skip(f"does not apply: {e}")
    _, seconds = pilot(fold_key(key, 1))  # compiled now: time a second run
    path_steps = r_pilot * n_q * steps_b
    rate = seconds / path_steps
    # κ against plain Euler Monte Carlo at the same step, in the compiled program the Euler alternatives run (the
    # Euler pilot compiled it), in either cost mode: with cost='seconds' every Euler alternative's seconds are its
    # Euler path-steps times the Euler pilot's rate, so QMC's must be too, via its path-steps × κ
    n_ref = RUN_PATHS * math.ceil(path_steps / steps_b / RUN_PATHS)
    reference = dict(steps=FixedSteps(h_b, brownian_dt=h_b), solver="euler", save=common["save"], **opts)
    start = time.perf_counter()
    jax.block_until_ready(solve_paths(system, y0, fold_key(key, 2), first_path=0, n_paths=n_ref, **reference))
    euler_rate = (time.perf_counter() - start) / (n_ref * steps_b)
    reference_work = float(n_ref * steps_b)
    kappa = rate / euler_rate if euler_rate > 0 else math.nan
    work = 2 * path_steps + reference_work
    value, se = (float(x) for x in _statistic_of(res, (kind, i, j)))
    if not all(math.isfinite(x) for x in (value, se, kappa)):
        return skip("non-finite pilot", work)
    variance = se**2 * r_pilot * n_q
    max_k = max(-1, math.floor(math.log2(MAX_DIMENSION / (steps0 * system.noise_dim))))

    def per_replicate(n: float) -> int:  # a power of two ≥ 64
        return max(BLOCK, 1 << max(0, math.ceil(math.log2(max(n, 1.0) / QMC_REPLICATES))))

    cost, k, n_total, _ = best_single(
        variance,
        euler.bias_bound,
        1,
        eps,
        h0,
        steps0,
        kappa,
        min(max_k, MAX_REFINEMENTS),
        lambda n: QMC_REPLICATES * per_replicate(n),
    )
    if k < 0:
        return skip("no step reaches the target within the Sobol' dimensions", work)
    h = h0 / 2**k
    per = n_total // QMC_REPLICATES
    if per > MAX_PATH_INDEX // 2:
        return skip(
            f"needs {per:.3g} paths per scrambling, more than the {MAX_PATH_INDEX // 2 + 1} a key indexes", work
        )
    bias = euler.bias_constant * h  # E S(h) − S ≈ C h (p = 1), Euler's

    def run():
        res = randomised_quasi_monte_carlo(
            system,
            y0,
            run_key,
            n_paths=per,
            replicates=QMC_REPLICATES,
            dt=h,
            save=save,
            wrt=common["run"]["wrt"],
            **opts,
        )
        value, se = _statistic_of(res, (kind, i, j))
        return value, se, bias, float(res.n_paths) * steps0 * 2**k, res

    return AccuracyAlternative(
        name,
        method,
        label,
        False,
        cost,
        dt=h,
        n_paths=(QMC_REPLICATES * per,),
        bias=bias,
        note=f"{QMC_REPLICATES} × {per} paths, κ = {kappa:.3g}",
        run=run,
        pilot_work=work,
        kappa=kappa,
    )
