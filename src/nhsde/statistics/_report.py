"""What :func:`~nhsde.statistics.to_accuracy` reports: the alternatives it priced, what each pilot measured, and
the result with its estimate, its cost and the prediction it was chosen by."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from ._estimate import AbstractEstimate, AbstractStatistic, Cost

__all__ = ["AccuracyAlternative", "AccuracyResult", "PilotSummary"]


@dataclasses.dataclass(frozen=True)
class AccuracyAlternative:
    """One way to reach the target, as its ``estimator`` plans it: the predicted work (``cost``, path-steps; ``inf``
    where it does not apply or was not priced, with the reason in ``note``).

    ``dt`` is the step (plain Monte Carlo, the control variate, quasi-Monte Carlo), the coarse step
    (extrapolation) or ``h₀`` (multilevel); ``n_paths`` the samples (pairs, with antithetic paths), per level
    for multilevel, whose runs go in pieces of ``piece_paths``.  ``kappa``: the cost of one of its path-steps in
    plain Euler path-steps (measured for quasi-Monte Carlo, else 1), so that it predicts ``cost/kappa``
    path-steps; ``memory``: the bytes its per-path values take at their peak (:mod:`~nhsde.statistics._cost`).
    """

    name: str
    cost: float
    dt: float = math.nan
    n_paths: tuple[int, ...] = ()
    bias: float = math.nan
    seconds: float = math.nan
    note: str = ""
    pilot_work: float = 0.0
    kappa: float = 1.0
    memory: float = 0.0
    piece_paths: int = 0
    estimator: Any = dataclasses.field(default=None, repr=False, compare=False)  # an AbstractEstimator

    @property
    def applies(self) -> bool:
        """Whether it has a plan that reaches the target (a finite predicted work)."""
        return math.isfinite(self.cost)


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
    resolution: float = math.nan  # the statistic's change when every saved value moves one ulp (finest level)


@dataclasses.dataclass(frozen=True)
class AccuracyResult:
    """The statistic to the requested accuracy: ``value()`` is ``(value, standard error)``, with estimated ``bias``.

    ``estimate`` is what the chosen estimator returned, ``rmse`` the absolute target; ``cost`` the work done by
    the whole call (path-steps, pilots included; wall seconds and the seconds spent compiling), ``pilot_cost`` the
    pilots' (path-steps; seconds: everything before the run), ``run_cost`` the chosen run's (its seconds include
    its compilation) against ``predicted``, its predicted path-steps (and seconds where the alternatives were
    ranked by them, else ``nan``).  ``choice`` the name of the alternative run, ``alternatives`` all of them with
    their predicted work, ``pilot`` one summary per solver.  ``derivative()``: the statistic's derivatives in the
    parameters ``wrt`` with their standard errors.  ``report()`` (also ``str``) prints it as a short table.
    """

    statistic: AbstractStatistic
    estimate: AbstractEstimate = dataclasses.field(repr=False, compare=False)
    bias: float
    rmse: float
    cost: Cost
    pilot_cost: Cost
    run_cost: Cost
    predicted: Cost
    choice: str
    reason: str
    alternatives: tuple[AccuracyAlternative, ...]
    pilot: tuple[PilotSummary, ...]

    def value(self, statistic=None) -> tuple[float, float]:
        """``(value, standard error)`` of ``statistic`` (default: the one the target was for; another saved one is
        read from the same run, whose effort was chosen for the target's)."""
        value, se = self.estimate.value(self.statistic if statistic is None else statistic)
        return float(value), float(se)

    def derivative(self, statistic=None) -> tuple[np.ndarray, np.ndarray]:
        """``(derivatives, standard errors)`` ``(len(wrt),)`` of ``statistic`` (as for :meth:`value`) in the
        parameters ``wrt`` (empty without)."""
        if self.estimate.derivatives is None:
            return np.zeros(0), np.zeros(0)
        d, se = self.estimate.derivative(self.statistic if statistic is None else statistic)
        return np.asarray(d, float), np.asarray(se, float)

    @property
    def wrt(self) -> tuple[str, ...]:
        """The parameters of ``derivative()`` (empty without ``wrt``)."""
        return () if self.estimate.derivatives is None else self.estimate.derivatives.wrt

    @property
    def estimated_rmse(self) -> float:
        """``√(SE² + bias²)``, the bias taken as 0 where it is not estimated."""
        bias = 0.0 if not math.isfinite(self.bias) else self.bias
        return math.hypot(self.value()[1], bias)

    def report(self) -> str:
        value, se = self.value()
        cost, run, predicted = self.cost, self.run_cost, self.predicted
        derivatives = zip(self.wrt, *self.derivative(), strict=True) if self.wrt else ()
        lines = [
            f"{self.statistic} at target rmse {self.rmse:.3g}: {value:.6g} ± {se:.2g} "
            f"(bias estimate {self.bias:.2g}); work {cost.path_steps:.3g} path-steps, pilot "
            f"{self.pilot_cost.path_steps:.3g}; {cost.seconds:.1f} s, {cost.compile_seconds:.1f} s of it compiling",
            f"run: predicted {predicted.path_steps:.3g} path-steps"
            + (f" in {predicted.seconds:.3g} s" if math.isfinite(predicted.seconds) else "")
            + f", measured {run.path_steps:.3g} in {run.seconds:.3g} s",
            *(f"  d/d{name} = {d:.6g} ± {e:.2g}" for name, d, e in derivatives),
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
