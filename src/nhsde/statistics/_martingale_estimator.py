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
    ``E S(h) − S ≈ C h^p``, bounded from the solver's plain pilot.  Its variance per path and the cost of one of its
    path-steps in plain ones (``κ``: the augmented state, measured) come from its own pilot at the finest pilot
    step, run twice (the second timed, against the plain pilot's seconds per path-step).  The plan takes the
    cheapest ``h₀ 2^{−k}`` and paths ``N = V/(ε² − (|C| h^p)²)``; its work counts the fit's paths too.
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
            start = time.perf_counter()
            timed = self._solve(pricing, fold_key(pricing.pilot_key, 96), n_pilot, h)  # compiled now
            seconds = time.perf_counter() - start
            pricing.time_pilot(self.candidate)
        except (ValueError, TypeError, NotImplementedError, SimulationError) as e:
            return self.row(f"does not apply: {e}")
        work = first.cost.path_steps + timed.cost.path_steps
        se = float(first.value(pricing.statistic)[1])
        kappa = seconds / timed.cost.path_steps / pricing.pilots[self.candidate.label].seconds_per_path_step
        if not (math.isfinite(se) and math.isfinite(kappa) and kappa > 0):
            return self.row("non-finite pilot", work)
        fit_paths = first.cost.path_steps / steps - n_pilot  # the fit's own paths, run with every estimate
        p = self.candidate.order
        c, k, n, _ = best_single(se**2 * n_pilot, plain.bias_bound, p, pricing.rmse, pricing.h0, pricing.steps0, kappa)
        if k < 0:
            return self.row("no step reaches the target", work)
        h_run = pricing.h0 / 2**k
        cost = c + fit_paths * pricing.steps0 * 2**k * kappa
        return AccuracyAlternative(
            self.name,
            cost,
            dt=h_run,
            n_paths=(n,),
            bias=plain.bias_constant * h_run**p,
            pilot_work=work,
            kappa=kappa,
            estimator=self,
        )

    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        return self._solve(pricing, pricing.run_key, plan.n_paths[0], plan.dt, wrt=pricing.tangents), plan.bias

    def kept_samples(self, plan: AccuracyAlternative) -> float:
        return 2 * super().kept_samples(plan)  # each path's saved values and its control's (at least as many)
