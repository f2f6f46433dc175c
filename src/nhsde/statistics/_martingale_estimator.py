"""The martingale control variate as an estimator to a target: priced from a pilot like the others, chosen by
:func:`~nhsde.statistics.to_accuracy` where it is given (``estimators=[MartingaleControlVariate(), …]``), callable
on its own.  The whole estimator is this file and one export line."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import diffrax as dfx

from .._ensemble import SimulationError
from .._misc import fold_key
from ._cost import best_single
from ._estimate import AbstractEstimate
from ._estimators import AbstractEstimator, Pricing
from ._martingale import martingale_control_variate
from ._report import AccuracyAlternative


@dataclasses.dataclass(frozen=True)
class MartingaleControlVariate(AbstractEstimator):
    """:func:`~nhsde.statistics.martingale_control_variate` to a target RMSE, with ``solver`` (``'euler'``,
    ``'weak2'`` or :class:`~nhsde.PlatenWeak2`), ``basis`` and ``time_degree`` as there.

    Pilot: the control's mean is zero for the discretisation itself, so the estimate's bias is its solver's,
    ``E S(h) − S ≈ C h^p``, bounded from the solver's plain pilot.  Its variance per path comes from its own pilot
    at the finest pilot step; the cost of one path-step of its run (``κ``, in plain ones: the state and the fitted
    combinations) from the difference of two more calls, compiled, with ``n`` and ``3n`` run paths (each with its
    fit), against the plain pilot's seconds per path-step, and that of its fit (the state and all ``K`` controls,
    several times a run's) from what remains.  The plan takes the cheapest ``h₀ 2^{−k}`` and paths
    ``N = V/(ε² − (|C| h^p)²)``; its work counts the fit's paths too.
    """

    solver: str | dfx.AbstractSolver = "euler"
    weak_order: int | None = None
    antithetic: bool = dataclasses.field(default=False, init=False)
    basis: Any = "quadratic"
    time_degree: int = 2
    method: str = dataclasses.field(default="martingale control variate", init=False, repr=False)

    @property
    def own_pilot(self) -> bool:
        return True

    def _solve(self, pricing: Pricing, key, n_paths: int, dt: float, wrt=None) -> AbstractEstimate:
        return martingale_control_variate(
            pricing.system,
            pricing.y0,
            key,
            pricing.statistic,
            n_paths=n_paths,
            run=pricing.run_at(dt, self.solver, keep_paths=False),
            basis=self.basis,
            time_degree=self.time_degree,
            wrt=wrt,
        )

    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        n_pilot = pricing.pilot_paths
        h = pricing.h0 / 2 ** (pricing.pilot_levels - 1)
        steps = pricing.steps0 * 2 ** (pricing.pilot_levels - 1)
        try:
            plain = pricing.pilot(self.candidate)
            first = self._solve(pricing, fold_key(pricing.pilot_key, 97), n_pilot, h)
            work, seconds = first.cost.path_steps, []
            for fold, n in ((96, n_pilot), (95, 3 * n_pilot)):  # compiled now: run paths n and 3n, one fit each
                start = time.perf_counter()
                timed = self._solve(pricing, fold_key(pricing.pilot_key, fold), n, h)
                seconds.append(time.perf_counter() - start)
                work += timed.cost.path_steps
            pricing.time_pilot(self.candidate)
        except (ValueError, TypeError, NotImplementedError, SimulationError) as e:
            return self.row(f"does not apply: {e}")
        se = float(first.value(pricing.statistic)[1])
        rate = pricing.pilots[self.candidate.label].seconds_per_path_step
        fit_paths = first.cost.path_steps / steps - n_pilot  # the fit's own paths, run with every estimate
        # the run's path-step (the fitted combinations only) from the difference of the two timed calls, at least a
        # plain one; the fit's (all the controls) from what remains of the first
        kappa = max((seconds[1] - seconds[0]) / (2 * n_pilot * steps) / rate, 1.0)
        kappa_fit = max(seconds[0] / rate - kappa * n_pilot * steps, 0.0) / (fit_paths * steps)
        if not (math.isfinite(se) and math.isfinite(kappa) and math.isfinite(kappa_fit)):
            return self.row("non-finite pilot", work)
        p = self.candidate.order
        c, k, n, _ = best_single(se**2 * n_pilot, plain.bias_bound, p, pricing.rmse, pricing.h0, pricing.steps0, kappa)
        if k < 0:
            return self.row("no step reaches the target", work)
        h_run = pricing.h0 / 2**k
        cost = c + fit_paths * pricing.steps0 * 2**k * kappa_fit
        return AccuracyAlternative(
            self.name,
            cost,
            dt=h_run,
            n_paths=(n,),
            bias=plain.bias_constant * h_run**p,
            note=f"κ = {kappa:.3g} per run path-step, {kappa_fit:.3g} per fit path-step ({fit_paths:.0f} paths)",
            pilot_work=work,
            kappa=kappa,
            estimator=self,
        )

    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        return self._solve(pricing, pricing.run_key, plan.n_paths[0], plan.dt, wrt=pricing.tangents), plan.bias

    def kept_samples(self, plan: AccuracyAlternative) -> float:
        return 2 * super().kept_samples(plan)  # each path's saved values and its control's (at least as many)
