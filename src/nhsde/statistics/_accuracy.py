"""One call: a statistic to a requested accuracy, by the cheapest estimator a pilot predicts.

:func:`to_accuracy` runs a short pilot for each candidate solver (Euler–Maruyama,
weak order ``p = 1``; :class:`~nhsde.PlatenWeak2` with Gaussian increments,
``p = 2``; Heun's method, ``p = 1``, for systems in Stratonovich form with
state-dependent noise): ``m`` solves at ``h_ℓ = h₀ 2^{−ℓ}``, ``ℓ < m``, on one Brownian path
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
- multilevel Monte Carlo (:func:`multilevel_monte_carlo`): the number of levels to ``h_L`` that costs least,
  its bias bound ``b_L = |C| h_L^p < ε`` leaving the variance ``ε² − b_L²`` to the samples, ``V_ℓ`` beyond the
  pilot decaying at the pilot's rate ``2^{−β}``, work ``(Σ_ℓ √(V_ℓ C_ℓ))²/(ε² − b_L²)`` (Giles 2008; 2015,
  §2.3) with samples rounded to whole pieces (run with this allocation fixed);
- each of these with antithetic pairs (work doubled, the pair's variance);
- a control variate, where :mod:`nhsde.statistics` provides one;
- randomised quasi-Monte Carlo (:func:`quasi_monte_carlo`, with each solver, 16 scramblings of a power of two
  paths each), where ``(t1 − t0)/h₀`` is a power of two and the driver is continuous: its variance and the
  rate ``N^{−β}`` at which it falls from a pilot at two point counts, its solver's bias bound, its run doubling
  the points until its own standard error meets the target, and its work converted to that solver's plain
  path-steps by the measured ratio ``κ`` of its seconds per path-step to plain Monte Carlo's (multilevel
  quasi-Monte Carlo likewise, level by level, when given);

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
from collections.abc import Sequence

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

from .._brownian import BLOCK
from .._ensemble import Save, SimulationError
from .._misc import check_key, check_number, check_span, fold_key, is_concrete
from .._options import AbstractSteps, Batching, RunOptions, run_options
from .._simulate import stable_step
from .._system import StochasticSystem
from .._weak import PlatenWeak2
from ._cost import check_memory, memory_limit, path_bytes, peak_bytes
from ._estimate import AbstractStatistic, Cost, Stopwatch, as_statistic
from ._estimators import (
    AbstractEstimator,
    ControlVariate,
    Multilevel,
    PlainMonteCarlo,
    Pricing,
    QuasiMonteCarlo,
    Richardson,
)
from ._paths import solved_path_steps
from ._pilot import Candidate, candidate
from ._report import AccuracyAlternative, AccuracyResult
from ._sensitivities import check_wrt
from ._variance_reduction import check_reflectable

__all__ = ["AccuracyAlternative", "AccuracyResult", "default_estimators", "to_accuracy"]

EXPLORE_ABOVE = 256
"""A further pilot runs (by default) only when the best run so far is predicted to take more than this many times
the first pilot's path-steps: below, compiling another pilot costs more than it can save.  Measured
(``benchmarks/RESULTS.md``): the default set's further pilots compiled for 16 s on Chaplygin's ball at 1e-3, while
a run of 256 first pilots' path-steps (the ball's 4.6e5) takes about 30 s there, so an alternative found must
halve the best run to repay it."""

MAX_PILOT_HALVINGS = 10
"""The default coarsest step is halved while the pilot's paths fail, down to ``(t1 − t0)/2^10``."""

MAX_SE_OVER_TARGET = 2.0
"""A run whose standard error exceeds the target this many times (its variance 4× the plan's) is refused, not
returned: its paths went far beyond the pilot's (on Chaplygin's ball at h = 1/4 the linearised control reached 1e17
× the target in 3 of 20 keys, finite all the way); the pilot's variances from 1024 samples are within a few per cent
where the tails are light."""


# --- the estimators ---------------------------------------------------------------------------------------------


def default_estimators(
    system: StochasticSystem, solver=None, weak_order: int | None = None, antithetic: bool | None = None
) -> tuple[list[AbstractEstimator], list[str]]:
    """The default set (:func:`to_accuracy`) narrowed by ``solver``, ``weak_order`` and ``antithetic``, and notes on
    the default solvers the system's driver does not allow."""
    notes = []
    if solver is not None:
        cand = candidate(solver, weak_order)
        cand.check(system)
        solvers = [(solver, weak_order)]
    else:
        solvers = []
        for s in native_solvers(system) + ("euler", PlatenWeak2(increments="gaussian")):
            try:
                candidate(s).check(system)
            except ValueError as e:
                notes.append(f"{candidate(s).label}: {e}")
                continue
            solvers.append((s, None))
    use_anti = system.noise.continuous and antithetic is not False
    variants = [a for a in (False, True) if (a and use_anti) or (not a and antithetic is not True)]
    estimators: list[AbstractEstimator] = [
        kind(s, w, anti) for s, w in solvers for anti in variants for kind in (PlainMonteCarlo, Richardson, Multilevel)
    ]
    if any(_is_euler(s) for s, _ in solvers):
        estimators.append(ControlVariate())
    estimators += [QuasiMonteCarlo(s, w) for s, w in solvers]
    return estimators, notes


def native_solvers(system: StochasticSystem) -> tuple[str, ...]:
    """Default solvers beyond Euler and weak order 2 for ``system``: Heun's method (``'heun2'``, weak order 1) where
    the system is written in Stratonovich form with state-dependent noise, so that Euler's and weak order 2's
    steps convert it to Itô form (a Jacobian of the diffusion per step; on the body on the vibrating plane a
    weak-order-2 path-step takes 2–3 times a Heun one, ``benchmarks/RESULTS.md``) and Heun's does not."""
    return ("heun2",) if system.interpretation == "stratonovich" and not system.additive_noise else ()


def _below_resolution(rmse: float, relative_rmse, resolution: float, statistic, y0) -> str:
    """Why ``rmse`` is below the ``resolution`` of the state's precision (the first pilot's, :func:`to_accuracy`),
    or ``''``."""
    if rmse >= resolution:
        return ""
    dtype = np.asarray(y0).dtype  # the state's precision, as simulate takes it
    dtype = jax.dtypes.canonicalize_dtype(dtype if np.issubdtype(dtype, np.floating) else jnp.result_type(float))
    named = f"rmse={rmse:.3g}" if relative_rmse is None else f"relative_rmse={relative_rmse} (rmse={rmse:.3g})"
    return (
        f"{named} is below {resolution:.3g}, what {dtype} resolves of {statistic} (the statistic's change when every "
        f"path's value moves by one unit in the last place, {np.finfo(dtype).eps:.3g} relative): no number of paths "
        "estimates it more finely, and the standard error does not show rounding the paths share; raise the target "
        f"to ≥ {resolution:.3g}, or compute in float64 (y0 and parameters as float64, jax_enable_x64)."
    )


def _is_euler(solver) -> bool:
    return (isinstance(solver, str) and solver == "euler") or type(solver) is dfx.Euler


def price(
    estimators: Sequence[AbstractEstimator], pricing: Pricing, first: Candidate, explore: bool
) -> list[AccuracyAlternative]:
    """Every estimator's plan, those of the first pilot's solver first; a further pilot (another solver's, or an
    estimator's own) only while :func:`to_accuracy`'s exploration rule allows it."""
    alternatives: list[AccuracyAlternative] = []
    first_work = pricing.pilots[first.label].work
    failed: dict[str, str] = {}  # solver label → why its pilot failed

    def rank(e: AbstractEstimator) -> int:
        """Those reading the first pilot, then those of its solver with pilots of their own, then the others."""
        return 2 if e.candidate.label != first.label else 1 if e.own_pilot else 0

    for e in sorted(estimators, key=rank):  # stable: otherwise in the given order
        label = e.candidate.label
        reason = e.applies(pricing)
        if reason is not None:
            alternatives.append(e.row(reason))
            continue
        if label in failed:
            alternatives.append(e.row(failed[label]))
            continue
        best = min((a.cost for a in alternatives if a.applies), default=math.inf)
        further = e.own_pilot or label not in pricing.pilots
        if further and not (explore or best > EXPLORE_ABOVE * first_work):
            note = (
                f"not priced: the best run so far is predicted at {best:.2g} path-steps, less than {EXPLORE_ABOVE}× "
                f"the first pilot's {first_work:.2g} (another pilot compiles a program); explore=True prices it"
            )
            alternatives.append(e.row(note))
            continue
        try:
            alternatives.append(e.predict(pricing))
        except (SimulationError, ValueError) as err:  # this solver's paths blow up at h0 (another's did not)
            failed[label] = f"does not apply at dt={pricing.h0:g}: its pilot failed: {str(err).splitlines()[0][:160]}"
            alternatives.append(e.row(failed[label]))
    return alternatives


# --- the entry point --------------------------------------------------------------------------------------------


def to_accuracy(
    system: StochasticSystem,
    y0,
    key,
    *,
    statistic: AbstractStatistic | tuple,
    t1: float | None = None,
    rmse: float | None = None,
    relative_rmse: float | None = None,
    t0: float | None = None,
    dt: float | None = None,
    steps: AbstractSteps | None = None,
    solver=None,
    weak_order: int | None = None,
    save: Save | None = None,
    antithetic: bool | None = None,
    pilot_paths: int = 1024,
    pilot_levels: int = 3,
    max_path_steps: float = 1e11,
    cost: str = "auto",
    estimators: Sequence[AbstractEstimator] | None = None,
    explore: bool = False,
    batching: Batching | None = None,
    run: RunOptions | None = None,
    wrt: Sequence[str] | None = None,
) -> AccuracyResult:
    """``statistic`` at ``t1`` to a root-mean-square error ``rmse`` by the estimator a pilot predicts cheapest (module).

    Arguments as :func:`~nhsde.simulate` (``run=`` or its keywords: with ``run=``, its steps are the coarsest step
    and its solver the one considered, unless ``estimators=`` name theirs), and:

    - ``statistic``: ``('mean', name)`` or ``('cov', name_a, name_b)`` at ``t1``; the names
      must be saved (``save.names``, default the statistic's names, of the system's observables).
    - ``rmse``: the absolute target, or ``relative_rmse``: relative to the pilot's ``|value|``.  A target below what
      the state's precision resolves is refused (``ValueError``): below ``eps Σ_i |∂Ŝ/∂z_i| |z_i|`` on the first
      pilot's finest paths, the statistic's change when every path's saved value ``z_i`` moves by one unit in the
      last place (``eps`` of ``y0``'s dtype: 1.2e-7 in float32, 2.2e-16 in float64; for a mean ``eps·mean|z|``).
      Rounding the paths share does not average out and no standard error shows it (float32 paths of
      ``dx = 10⁻⁸ dt`` from 1 all stay at 1: standard error 0, error 10⁻⁸), so a standard error of 0 is reported as
      meeting only a target the precision resolves.
    - ``dt`` (or ``steps=FixedSteps(dt)``): the coarsest step ``h₀`` considered (default
      ``(t1 − t0)/4``, halved until the first pilot's solver is inside its stability limit on the system's
      declared friction (another solver unstable there does not apply), and again while the pilot's paths fail
      there, down to ``(t1 − t0)/2^10``, their
      work counted; if no alternative reaches the target or fits in memory there (a pilot path grown huge
      without overflowing inflates the bias bound), or the chosen run's paths fail, every alternative is priced
      again from half that step, once); pilots run at ``h₀ … h₀ 2^{1−pilot_levels}``, every alternative at ``h₀``
      or finer.
    - ``estimators``: the estimators to choose among (:class:`PlainMonteCarlo`, :class:`Richardson`,
      :class:`Multilevel`, each with its solver and plain or antithetic paths; :class:`ControlVariate`,
      :class:`QuasiMonteCarlo`, :class:`MultilevelQuasiMonteCarlo`, :class:`MartingaleControlVariate`).  Default:
      each of the first three for Euler–Maruyama and
      ``PlatenWeak2(increments='gaussian')`` (those the system's driver allows), and Heun's method (``'heun2'``)
      where the system is in Stratonovich form with state-dependent noise (:func:`native_solvers`), plain and
      antithetic (Wiener drivers), then the control variate (Euler) and quasi-Monte Carlo with each solver (its
      antithetic form only when given: at equal work it gains only on statistics odd in ``W``; multilevel
      quasi-Monte Carlo only when given: its pilot, priced from the default coarsest step, predicted more work
      than extrapolation on Chaplygin's ball at 1e-3 and its own pilot cost more time than it saved); ``solver``,
      ``weak_order`` and ``antithetic`` narrow that default set:
    - ``solver``: consider only this one (``PlatenWeak2`` needs ``increments='gaussian'``),
      of weak order ``weak_order`` (default 2 for ``PlatenWeak2``, else 1).
    - ``antithetic``: ``None`` considers both plain and antithetic paths (Wiener drivers),
      ``True``/``False`` only those.
    - ``pilot_paths``, ``pilot_levels`` (≥ 2; 3 to estimate the extrapolation's bias).
    - ``max_path_steps``: refuse (``ValueError``) when the cheapest predicted work exceeds it; alternatives whose
      per-path values would not fit in the device's memory are passed over (none fits: a ``ValueError`` with the
      size).
    - ``cost``: what the alternatives are ranked by: ``'path-steps'``, ``'seconds'`` (path-steps times each
      solver's measured seconds per path-step from a second, compiled, run of its pilot), or ``'auto'`` (default):
      path-steps where every priced alternative has one solver, seconds where several solvers were priced (their
      path-steps cost differently: on the body on the vibrating plane a weak-order-2 path-step takes 2–3 Heun
      ones), each priced solver's pilot then timed once more.  The exploration rule counts path-steps either way.
    - Quasi-Monte Carlo applies where ``(t1 − t0)/dt`` is a power of two and the driver is continuous.  Its pilot
      (16 scramblings of ``pilot_paths/16`` points rounded down to a power of two, then twice as many, timed)
      predicts its points from the rate at which its variance fell between the two counts (:class:`QuasiMonteCarlo`);
      its work is counted in its solver's plain path-steps (times the measured cost ratio ``κ``, in the report's
      note).
    - ``explore``: price every alternative.  By default (``False``) the first solver's pilot (among the estimators'
      solvers that step the system in its own calculus, where one does, the highest weak order) prices the
      estimators of that solver, and a further pilot (another
      solver's, the control variate's, quasi-Monte Carlo's) runs only when the best run so far is predicted to take
      more than :data:`EXPLORE_ABOVE` times the first pilot's path-steps (the rule counts work, not seconds, so a key
      gives the same choice on any machine and with any cache): a loose target is answered after one compiled
      program, a tight one after all.  Alternatives not priced are listed with the reason; a further solver whose
      pilot fails at the step is listed as not applying.
    - ``wrt``: names of scalar parameters (``('eps', 'nu')``): the statistic's derivatives in them with their
      standard errors (``derivative()``), from the chosen estimator's per-path tangents.
    """
    if run is not None:  # the run's options as the keywords they stand for (its solver: the one considered)
        run_options("to_accuracy", run, t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, batching=batching)
        t0, t1, steps, save, batching = run.t0, run.t1, run.steps, run.save, run.batching
        solver = run.solver if estimators is None else None  # (estimators= carry their own)
    return _to_accuracy(
        system,
        y0,
        key,
        statistic=statistic,
        t1=t1,
        rmse=rmse,
        relative_rmse=relative_rmse,
        t0=t0,
        dt=dt,
        steps=steps,
        solver=solver,
        weak_order=weak_order,
        save=save,
        antithetic=antithetic,
        pilot_paths=pilot_paths,
        pilot_levels=pilot_levels,
        max_path_steps=max_path_steps,
        cost=cost,
        estimators=estimators,
        explore=explore,
        batching=batching,
        wrt=wrt,
        own_step=False,
    )


def _to_accuracy(
    system,
    y0,
    key,
    *,
    statistic,
    t1,
    rmse,
    relative_rmse,
    t0,
    dt,
    steps,
    solver,
    weak_order,
    save,
    antithetic,
    pilot_paths,
    pilot_levels,
    max_path_steps,
    cost,
    estimators,
    explore,
    batching,
    wrt,
    own_step: bool,
) -> AccuracyResult:
    """:func:`to_accuracy`'s stages; ``own_step``: this call retries from half the coarsest step of an attempt that
    chose it itself (so its step may be halved again where paths fail)."""
    call = dict(locals())  # the arguments, for a retry from a finer coarsest step
    watch = Stopwatch()
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if (rmse is None) == (relative_rmse is None):
        raise TypeError(f"rmse={rmse!r}, relative_rmse={relative_rmse!r}: give exactly one of them.")
    if rmse is not None:
        rmse = check_number("rmse", rmse, positive=True)
    else:
        relative_rmse = check_number("relative_rmse", relative_rmse, positive=True)
    if antithetic is not None and not isinstance(antithetic, bool):
        raise TypeError(f"antithetic={antithetic!r}; expected None, True or False.")
    if antithetic:
        check_reflectable(system.noise, "antithetic=True")
    if estimators is None:
        estimators, skipped = default_estimators(system, solver, weak_order, antithetic)
    else:
        given = dict(solver=solver, weak_order=weak_order, antithetic=antithetic)
        if any(v is not None for v in given.values()):
            named = ", ".join(f"{k}={v!r}" for k, v in given.items() if v is not None)
            raise TypeError(f"{named} and estimators=: give the solvers and antithetic paths in the estimators.")
        estimators, skipped = tuple(estimators), []
        if not estimators or not all(isinstance(e, AbstractEstimator) for e in estimators):
            raise TypeError(
                f"estimators={estimators!r}; expected a non-empty sequence of nhsde.statistics estimators "
                "(nhsde.statistics.AbstractEstimator instances, e.g. PlainMonteCarlo(), Multilevel())."
            )
        for e in estimators:
            e.check(system)
    candidates = list({e.candidate.label: e.candidate for e in estimators}.values())
    # the first pilot: a solver that steps the system in its own calculus (no conversion each step), then the
    # highest weak order: the solver most alternatives choose
    first_solver = max(candidates, key=lambda c: (not c.converts(system), c.order))
    default_step = dt is None and steps is None
    own_step = default_step or own_step  # halved where paths fail: the default or its retry's half
    if default_step:  # the coarsest step: (t1 − t0)/4, halved until the first pilot's solver damps the friction
        if t1 is None:
            raise TypeError("to_accuracy needs t1 (or run=nhsde.RunOptions(...)).")
        # (another solver unstable there is listed as not applying: its pilot refuses the step)
        t0, t1 = check_span(0.0 if t0 is None else t0, t1)
        dt = (t1 - t0) / 4
        while not stable_step(system, first_solver.solver, dt) and dt > (t1 - t0) / 2**30:
            dt /= 2
    run = run_options(
        "to_accuracy", t0=t0, t1=t1, dt=dt, steps=steps, solver=first_solver.solver, save=save, batching=batching
    )
    h0, steps0 = run.dt, run.n_steps
    statistic = as_statistic(statistic)
    statistic.check(system.observable_names() if save is None or save.names is None else save.names)
    names = statistic.names if save is None or save.names is None else save.names
    n_save = 2 if save is None or save.n is None else save.n
    if steps0 % (n_save - 1):
        raise ValueError(f"save.n={n_save}: n − 1 must divide the {steps0} steps of the coarsest step dt={h0}.")
    save = Save(names=names, n=n_save, paths=True)
    run = dataclasses.replace(run, save=save)
    pilot_paths = check_number("pilot_paths", pilot_paths, integer=True)
    if pilot_paths < BLOCK or pilot_paths % BLOCK:
        raise ValueError(f"pilot_paths={pilot_paths}; must be a positive multiple of {BLOCK}.")
    pilot_levels = check_number("pilot_levels", pilot_levels, integer=True)
    if not 2 <= pilot_levels <= 6:
        raise ValueError(f"pilot_levels={pilot_levels}; allowed: 2 … 6.")
    max_path_steps = check_number("max_path_steps", max_path_steps, positive=True)
    if cost not in ("auto", "path-steps", "seconds"):
        raise ValueError(f"cost={cost!r}; allowed: 'auto', 'path-steps', 'seconds'.")
    wrt = () if wrt is None else check_wrt(system, wrt)
    if not is_concrete(system, y0):
        raise TypeError("to_accuracy chooses path counts from a pilot: it needs concrete parameters, not traced ones.")
    key = check_key(key)
    pilot_key, run_key = fold_key(key, 0), fold_key(key, 1)  # one program, the pilots' own (a split: another)
    pricing = Pricing(
        system=system,
        y0=y0,
        pilot_key=pilot_key,
        run_key=run_key,
        rmse=math.nan,
        run=run,
        statistic=statistic,
        pilot_paths=pilot_paths,
        pilot_levels=pilot_levels,
        wrt=wrt,
        timed=cost == "seconds",
        pilot_keys={c.label: i for i, c in enumerate(candidates)},
        antithetic_pilots=frozenset(e.candidate.label for e in estimators if e.antithetic),
    )
    failed_work = 0.0  # the default coarsest step is halved while the pilot's paths fail there (a nonlinear blow-up)
    while True:
        try:
            first = pricing.pilot(first_solver)
            break
        except (SimulationError, ValueError) as e:
            blown_up = isinstance(e, SimulationError) or "non-finite values" in str(e)
            if not (own_step and blown_up and pricing.steps0 < 2**MAX_PILOT_HALVINGS):
                raise
            anti = first_solver.label in pricing.antithetic_pilots
            failed_work += pilot_paths * (2 if anti else 1) * pricing.steps0 * (2**pilot_levels - 1)
            pricing.run = pricing.run.at(pricing.h0 / 2)
    h0 = pricing.h0
    if rmse is None:
        value, se = first.values[-1], first.standard_errors[-1]
        if not abs(value) > 2 * se:
            raise ValueError(
                f"relative_rmse={relative_rmse}: the pilot's value {value:.3g} ± {se:.2g} is not distinguishable "
                "from 0; give an absolute rmse= instead."
            )
        assert relative_rmse is not None
        rmse = relative_rmse * abs(value)
    floor = _below_resolution(rmse, relative_rmse, first.resolution, statistic, y0)
    retry = own_step and pricing.steps0 < 2**MAX_PILOT_HALVINGS
    if floor and not retry:  # (with a retry, a pilot grown huge can still be priced again from half the step)
        raise ValueError(floor)
    pricing.rmse = rmse
    alternatives = price(estimators, pricing, first_solver, explore)
    alternatives += [AccuracyAlternative(f"any, {note.split(':', 1)[0]}", math.inf, note=note) for note in skipped]
    # solvers' path-steps cost differently (weak order 2's is 2–3 Euler ones, a converting step more): where
    # alternatives of several solvers were priced, they are ranked by seconds, each solver's pilot timed once more
    priced = {a.estimator.candidate.label: a.estimator.candidate for a in alternatives if a.applies}
    timed = pricing.timed or (cost == "auto" and len(priced) > 1)
    if timed:
        for cand in priced.values():
            pricing.time_pilot(cand)
    pilots = [pricing.pilots[c.label] for c in candidates if c.label in pricing.pilots]  # in the estimators' order
    pilot_work = sum(p.work for p in pilots) + failed_work
    pilot_work += sum(a.pilot_work for a in alternatives)
    per_sample = path_bytes(n_save, len(names), len(wrt))
    alternatives = [
        dataclasses.replace(a, memory=peak_bytes(a.estimator.kept_samples(a) * per_sample)) if a.applies else a
        for a in alternatives
    ]
    if timed:
        rates = {p.solver: p.seconds_per_path_step for p in pilots}
        alternatives = [
            dataclasses.replace(a, seconds=a.cost * rates.get(a.estimator.candidate.label, math.nan))
            if a.applies
            else a
            for a in alternatives
        ]
    key_of = (lambda a: a.seconds if math.isfinite(a.seconds) else math.inf) if timed else (lambda a: a.cost)
    ranked = sorted((a for a in alternatives if a.applies and math.isfinite(key_of(a))), key=key_of)

    def from_half_step(failure: str, work: float) -> AccuracyResult:
        """Every alternative priced again from half the step (a pilot path that grew huge without overflowing
        inflates the bias bound; a rare path blows up in the run), this attempt's work counted."""
        failed = watch.cost(work)
        again = _to_accuracy(**{**call, "dt": h0 / 2, "steps": None, "own_step": True})
        return dataclasses.replace(
            again,
            cost=again.cost + failed,
            pilot_cost=again.pilot_cost + failed,  # the failed attempt, its seconds too, went before the run
            reason=f"{again.reason}; at dt={h0:g} {failure}, so every alternative was priced again from dt={h0 / 2:g}",
        )

    if not ranked:
        if retry:
            return from_half_step("no alternative reached the target", pilot_work)
        if floor:
            raise ValueError(floor)
        notes = "\n".join(f"  {a.name}: {a.note or 'no plan'}" for a in alternatives)
        raise ValueError(f"rmse={rmse:.3g}: no alternative can reach it from dt={h0}:\n{notes}\nthe pilot:\n{pilots}")
    if floor:  # never run to a target the precision does not resolve: its standard error could read 0
        raise ValueError(floor)
    fitting = [a for a in ranked if a.memory <= memory_limit()]
    if not fitting:
        if retry:
            return from_half_step(f"no alternative fitted in memory (the cheapest, {ranked[0].name})", pilot_work)
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
    pilot_cost = watch.cost(pilot_work)  # everything before the run: the pilots, their pricing and timing
    run_watch = Stopwatch()
    solved_before = solved_path_steps()
    try:
        estimate, bias = chosen.estimator.run(pricing, chosen)
    except SimulationError as e:  # a rare path blew up at a step the pilot's paths survived: from half the step
        if not retry:
            raise
        # this attempt's work: the pilots and the run's solves up to the one that failed
        solved = solved_path_steps() - solved_before
        return from_half_step(f"{chosen.name} failed ({str(e).splitlines()[0][:120]})", pilot_work + solved)
    se = float(estimate.value(statistic)[1])
    if not se <= MAX_SE_OVER_TARGET * rmse:  # a statistic the plan did not foresee: never returned as meeting it
        failure = (
            f"{chosen.name}'s run reached a standard error of {se:.3g}, {se / rmse:.3g}× the target (paths far "
            "beyond the pilot's)"
        )
        if retry:
            return from_half_step(failure, pilot_work + estimate.cost.path_steps)
        raise ValueError(f"rmse={rmse:.3g}, dt={h0}: {failure}; pass a smaller dt.")
    run_cost = run_watch.cost(estimate.cost.path_steps)
    return AccuracyResult(
        statistic=statistic,
        estimate=estimate,
        bias=float(bias),
        rmse=float(rmse),
        cost=watch.cost(run_cost.path_steps + pilot_work),
        pilot_cost=pilot_cost,
        run_cost=run_cost,
        predicted=Cost(chosen.cost / chosen.kappa, chosen.seconds),
        choice=chosen.name,
        reason=reason,
        alternatives=tuple(alternatives),
        pilot=tuple(pilots),
    )
