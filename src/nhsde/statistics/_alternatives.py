"""The alternatives :func:`~nhsde.statistics.to_accuracy` prices from its pilot (plain Monte Carlo, extrapolation,
multilevel, each plain and antithetic; the control variate; randomised quasi-Monte Carlo), each with the run that
returns its estimate and its bias (the :mod:`._accuracy` module)."""

from __future__ import annotations

import math
import time
from typing import Any

import jax

from .._brownian import BLOCK
from .._ensemble import Save, SimulationError
from .._misc import fold_key
from .._options import FixedSteps
from .._simulate import MAX_PATH_INDEX
from ._control_variate import control_variate as linearised_control_variate
from ._cost import (
    MAX_REFINEMENTS,
    best_single,
    multilevel_plan,
    whole_pieces,
)
from ._extrapolation import extrapolate
from ._multilevel import multilevel_monte_carlo
from ._paths import RUN_PATHS, solve_paths
from ._pilot import Candidate
from ._qmc import MAX_DIMENSION, quasi_monte_carlo as randomised_quasi_monte_carlo
from ._report import AccuracyAlternative, PilotSummary

__all__ = ["control_variate_alternative", "kept_samples", "quasi_monte_carlo_alternative", "solver_alternatives"]


def kept_samples(a: AccuracyAlternative) -> float:
    """Per-path value sets an alternative's run keeps: one per solve of each sample (quasi-Monte Carlo keeps
    moments only)."""
    pairs = 2 if a.antithetic else 1
    if a.method == "multilevel":
        return pairs * sum(n * (2 if ell else 1) for ell, n in enumerate(a.n_paths))
    solves = {"plain": 1, "extrapolation": 2, "control variate": 2}.get(a.method, 0)
    return pairs * solves * sum(a.n_paths)


def solver_alternatives(
    system, y0, key, cand: Candidate, p: PilotSummary, eps, h0, steps0, use_anti, antithetic, common
):
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
            statistic=common["statistic"],
            **common["run"],
        )
        return res, p.bias_constant * h**p.order

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
        return res, bias

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
            statistic=common["statistic"],
            **common["run"],
        )
        return res, res.bias

    return run


def control_variate_alternative(system, y0, pilot_key, run_key, eps, h0, steps0, common) -> AccuracyAlternative:
    """The control variate of :func:`~nhsde.statistics.control_variate` (Euler).  Pilot: it at the two finest pilot
    steps on one Brownian path; its variance per path at the finest, its bias ``C h`` bounded by
    ``(|ΔŶ| + 2(SE_a + SE_b))/h_b`` (Euler, ``p = 1``)."""
    name = "control variate, euler"
    statistic = common["statistic"]
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
    except (ValueError, TypeError, NotImplementedError, SimulationError) as e:  # paths blowing up: not at this step
        return AccuracyAlternative(name, "control variate", "euler", False, math.inf, note=f"does not apply: {e}")
    (va, sa), (vb, sb) = (tuple(float(x) for x in r.value(statistic)) for r in runs)
    if not all(math.isfinite(x) for x in (va, sa, vb, sb)):
        return AccuracyAlternative(name, "control variate", "euler", False, math.inf, note="non-finite pilot")
    work = sum(r.cost.path_steps for r in runs)
    variance = sb**2 * n_pilot
    bound = (abs(vb - va) + 2 * (sa + sb)) / h_b
    per_path_step = runs[1].cost.path_steps / n_pilot / (steps0 * 2 ** (levels - 1))
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
        return res, bias

    return AccuracyAlternative(
        name, "control variate", "euler", False, c, dt=h, n_paths=(n,), bias=bias, run=run, pilot_work=work
    )


QMC_PILOT_REPLICATES = 8
QMC_REPLICATES = 16


def quasi_monte_carlo_alternative(
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
    statistic = common["statistic"]
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
        _, seconds = pilot(fold_key(key, 1))  # compiled now: time a second run
    except (ValueError, TypeError, SimulationError) as e:  # paths blowing up: not at this step
        return skip(f"does not apply: {str(e).splitlines()[0][:200]}")
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
    value, se = (float(x) for x in res.value(statistic))
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
        return res, bias

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
