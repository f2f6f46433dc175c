"""The estimators :func:`~nhsde.statistics.to_accuracy` chooses among, as objects: each is checked against the
system once (``check``), says where it does not apply (``applies``), predicts its work to the target from a pilot
(``predict``: an :class:`AccuracyAlternative`, a plan without closures) and runs that plan (``run``).

- :class:`PlainMonteCarlo`, :class:`Richardson` (Richardson–Romberg extrapolation) and :class:`Multilevel` read the
  pilot of their solver (``m`` solves at ``h₀ 2^{−ℓ}`` on one Brownian path, :mod:`._pilot`), plain or antithetic;
- :class:`ControlVariate` (the linearised system driven by the same increments, Euler–Maruyama) and
  :class:`QuasiMonteCarlo` (scrambled Sobol' points, with its solver) run pilots of their own.

The work models are those of the :mod:`._accuracy` module (``_cost.py``).
"""

from __future__ import annotations

import abc
import dataclasses
import math
import time
from typing import Any, ClassVar, NamedTuple

import diffrax as dfx
import jax

from .._brownian import BLOCK
from .._ensemble import Save, SimulationError
from .._misc import fold_key
from .._options import RunOptions
from .._system import StochasticSystem
from ._control_variate import control_variate as linearised_control_variate
from ._cost import MAX_REFINEMENTS, allocate, best_single, bias, level_cost, multilevel_plan, whole_pieces
from ._estimate import AbstractEstimate, AbstractStatistic
from ._extrapolation import extrapolate
from ._martingale import check_martingale_solver
from ._multilevel import MultilevelEstimate, multilevel_monte_carlo
from ._multilevel_qmc import RUN_LIMIT, quasi_monte_carlo_to_variance
from ._paths import KEY_PATHS, RUN_PATHS, solve_paths
from ._pilot import Candidate, candidate, level_bias_bound, pilot_rate, run_pilot
from ._qmc import MAX_DIMENSION
from ._report import AccuracyAlternative, PilotSummary
from ._variance_reduction import check_reflectable

__all__ = [
    "AbstractEstimator",
    "ControlPilot",
    "ControlVariate",
    "Multilevel",
    "MultilevelQuasiMonteCarlo",
    "PlainMonteCarlo",
    "Pricing",
    "QuasiMonteCarlo",
    "Richardson",
]


@dataclasses.dataclass(frozen=True)
class ControlPilot:
    """What the controlled pilot of one solver measured (:meth:`Pricing.control_pilot`): the multilevel estimator
    with the control (``Y − βC``) at ``pilot_paths`` samples on each pilot level, its level variances ``V_ℓ`` and
    the bias model ``E[Y(h) − β(C(h) − E C)] − S ≈ C h^p`` of its level terms, bounded as the solver's pilot does,
    and ``kappa``: the seconds of its path-steps over those of the solver's plain pilot (one more run of each
    compiled program, at least 1: a controlled path-step does a plain one's work and also takes the drift's
    Jacobian-vector product, on Chaplygin's ball and the body 1.6–2× a plain one)."""

    level_variances: tuple[float, ...]
    bias_bound: float
    bias_constant: float
    kappa: float


@dataclasses.dataclass
class Pricing:
    """What every estimator prices from and runs with: the system, the target ``rmse``, the run options ``run`` at the
    coarsest step ``h0`` (``steps0`` steps; its ``save`` keeps the paths), and the pilots of the solvers (run once
    each, on demand, :meth:`pilot`)."""

    system: StochasticSystem
    y0: Any
    pilot_key: Any
    run_key: Any
    rmse: float
    run: RunOptions
    statistic: AbstractStatistic
    pilot_paths: int
    pilot_levels: int
    wrt: tuple[str, ...]
    timed: bool
    pilot_keys: dict[str, int]  # per solver label, the index its pilot key is folded with
    antithetic_pilots: frozenset[str]  # the solver labels whose pilots also run the reflected paths
    pilots: dict[str, PilotSummary] = dataclasses.field(default_factory=dict)
    control_pilots: dict[tuple[str, bool, str], ControlPilot] = dataclasses.field(default_factory=dict)

    @property
    def h0(self) -> float:
        return self.run.dt

    @property
    def steps0(self) -> int:
        return self.run.n_steps

    def run_with(self, solver) -> RunOptions:
        """The run options with ``solver``."""
        return dataclasses.replace(self.run, solver=solver)

    def pilot(self, cand: Candidate) -> PilotSummary:
        """The pilot of ``cand`` at ``h0`` (run on first use; raises where its paths fail)."""
        if cand.label not in self.pilots:
            self.pilots[cand.label] = run_pilot(
                self.system,
                self.y0,
                self._pilot_key(cand),
                cand,
                self.run_with(cand.solver),
                statistic=self.statistic,
                timed=self.timed,
                **self._pilot_options(cand),
            )
        return self.pilots[cand.label]

    def control_pilot(self, cand: Candidate, antithetic: bool, control: str = "mean") -> tuple[ControlPilot, float]:
        """The pilot of ``cand`` with ``control`` (``'mean'``: the linearised system, ``'martingale'``; a
        :class:`ControlPilot`, run on first use, raises where its paths fail) and the path-steps it took now (0 when
        it had run)."""
        label = (cand.label, antithetic, control)
        if label in self.control_pilots:
            return self.control_pilots[label], 0.0

        def run(fold: int) -> MultilevelEstimate:
            return multilevel_monte_carlo(
                self.system,
                self.y0,
                fold_key(self._pilot_key(cand), fold),
                n_paths=(self.pilot_paths,) * self.pilot_levels,
                run=self.run_at(self.h0, cand.solver),
                weak_order=cand.order,
                antithetic=antithetic,
                control=control,
                piece_paths=self.pilot_paths,
                statistic=self.statistic,
            )

        res = run(96)
        start = time.perf_counter()
        timed = run(95)  # compiled now: its seconds per path-step against the plain pilot's
        rate = (time.perf_counter() - start) / timed.cost.path_steps
        self.pilot(cand)
        self.time_pilot(cand)
        variances = tuple(float(v) for v in res.level_variances)
        terms = [float(m) for m in res.level_means[1:]]
        h_fine = self.h0 / 2 ** (self.pilot_levels - 1)
        p = cand.order
        pilot = ControlPilot(
            variances,
            level_bias_bound(terms, [v / self.pilot_paths for v in variances[1:]], self.h0, p),
            -terms[-1] / (h_fine**p * (2**p - 1)),  # Ŷ_L ≈ −C h_L^p (2^p − 1)
            max(rate / self.pilots[cand.label].seconds_per_path_step, 1.0),  # below 1 is timing noise
        )
        self.control_pilots[label] = pilot
        return pilot, res.cost.path_steps + timed.cost.path_steps

    def time_pilot(self, cand: Candidate) -> None:
        """Give ``cand``'s pilot its measured seconds per path-step (one more run of its compiled programs, its work
        added to the pilot's), where it has none."""
        pilot = self.pilots[cand.label]
        if math.isnan(pilot.seconds_per_path_step):
            rate, work = pilot_rate(
                self.system, self.y0, self._pilot_key(cand), self.run_with(cand.solver), **self._pilot_options(cand)
            )
            self.pilots[cand.label] = dataclasses.replace(pilot, seconds_per_path_step=rate, work=pilot.work + work)

    def _pilot_key(self, cand: Candidate):
        return fold_key(self.pilot_key, self.pilot_keys[cand.label])

    def _pilot_options(self, cand: Candidate) -> dict[str, Any]:
        return dict(levels=self.pilot_levels, n_paths=self.pilot_paths, anti=cand.label in self.antithetic_pilots)

    def run_at(self, dt: float, solver, *, brownian_dt: float | None = None, keep_paths: bool = True) -> RunOptions:
        """The question's run at steps ``dt`` (on a Brownian path of base step ``brownian_dt``) with ``solver``;
        ``save`` without per-path values where the estimator keeps none."""
        save = self.run.save
        assert save is not None
        save = save if keep_paths else Save(names=save.names, n=save.n)
        return dataclasses.replace(self.run.at(dt, brownian_dt), solver=solver, save=save)

    @property
    def tangents(self) -> tuple[str, ...] | None:
        """The parameters a run differentiates in (``None``: none)."""
        return self.wrt or None


class AbstractEstimator(abc.ABC):
    """One way to reach a target RMSE (module).  ``solver`` and ``weak_order`` (default 2 for
    :class:`~nhsde.PlatenWeak2`, else 1) fix the pilot it reads; ``antithetic`` runs reflected pairs."""

    solver: str | dfx.AbstractSolver
    weak_order: int | None
    antithetic: bool
    control: bool | str = False  # the linearised system as a control variate inside it (where it has the field)
    method: str  # its name in the report

    def __call__(
        self,
        system: StochasticSystem,
        y0,
        key,
        statistic,
        *,
        rmse: float | None = None,
        relative_rmse: float | None = None,
        run: RunOptions | None = None,
        wrt=None,
        **options,
    ):
        """This estimator to a target: a pilot predicts its plan (steps, levels, paths) for ``rmse`` (or
        ``relative_rmse``) of ``statistic`` at ``t1``, then it runs the plan (:func:`~nhsde.statistics.to_accuracy`
        with ``estimators=[self]``: the same result, report and checks).  The run's options as ``run=`` or
        :func:`~nhsde.simulate`'s keywords (``t1``, ``dt`` the coarsest step, …); ``options`` also takes
        ``to_accuracy``'s ``pilot_paths``, ``pilot_levels`` and ``max_path_steps``.  Returns an
        :class:`~nhsde.statistics.AccuracyResult`."""
        from ._accuracy import to_accuracy

        return to_accuracy(
            system,
            y0,
            key,
            statistic=statistic,
            rmse=rmse,
            relative_rmse=relative_rmse,
            run=run,
            wrt=wrt,
            estimators=(self,),
            **options,
        )

    @property
    def candidate(self) -> Candidate:
        """The solver whose pilot this estimator reads."""
        return candidate(self.solver, self.weak_order)

    @property
    def name(self) -> str:
        control = {False: "", "martingale": ", martingale control"}.get(self.control, ", control variate")
        extras = (", antithetic" if self.antithetic else "") + control
        return f"{self.method}, {self.candidate.label}{extras}"

    @property
    def copies(self) -> int:
        """Solves per sample (per point): the reflected paths and the control each double them."""
        return (2 if self.antithetic else 1) * (2 if self.control else 1)

    @property
    def own_pilot(self) -> bool:
        """Whether pricing runs a pilot of its own (beyond its solver's)."""
        return False

    def check(self, system: StochasticSystem) -> None:
        """Raise ``ValueError`` naming the estimator where it cannot run on ``system`` at all."""
        self.candidate.check(system)
        if self.antithetic:
            check_reflectable(system.noise, repr(self))
        if self.control and not system.noise.continuous:
            raise ValueError(f"{self!r}: the control variate needs a Wiener driver here (a Gaussian control).")
        if self.control == "martingale":
            check_martingale_solver(self.solver)

    def applies(self, pricing: Pricing) -> str | None:
        """Why it does not apply at this step (``None`` where it does)."""
        return None

    @abc.abstractmethod
    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        """Its cheapest plan to ``pricing.rmse`` and that plan's predicted work (``inf`` where none reaches it)."""

    @abc.abstractmethod
    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        """The estimate of ``plan`` and its bias estimate."""

    def kept_samples(self, plan: AccuracyAlternative) -> float:
        """Per-path value sets its run keeps at their peak: one per solve of each sample."""
        return self.copies * sum(plan.n_paths)

    def row(self, note: str, pilot_work: float = 0.0) -> AccuracyAlternative:
        """A report row for a plan it cannot make, with the reason."""
        return AccuracyAlternative(self.name, math.inf, note=note, pilot_work=pilot_work, estimator=self)


def _variances(pilot: PilotSummary, antithetic: bool):
    return (
        (pilot.antithetic_variance, pilot.antithetic_extrapolation_variance, pilot.antithetic_level_variances)
        if antithetic
        else (pilot.variance, pilot.extrapolation_variance, pilot.level_variances)
    )


@dataclasses.dataclass(frozen=True)
class PlainMonteCarlo(AbstractEstimator):
    """Plain Monte Carlo at its best ``(h, N)``: ``N = V/(ε² − C²h^{2p})``, work ``N T/h`` (Glasserman 2004,
    §1.1.3), run as one level of :func:`~nhsde.statistics.multilevel_monte_carlo`."""

    solver: str | dfx.AbstractSolver = "euler"
    weak_order: int | None = None
    antithetic: bool = False
    method: str = dataclasses.field(default="plain MC", init=False, repr=False)

    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        p = pricing.pilot(self.candidate)
        factor = 2.0 if self.antithetic else 1.0
        c, k, n, _ = best_single(
            _variances(p, self.antithetic)[0], p.bias_bound, p.order, pricing.rmse, pricing.h0, pricing.steps0, factor
        )
        if k < 0:
            return self.row("bias bound above the target at every step")
        h = pricing.h0 / 2**k
        bias = p.bias_constant * h**p.order
        return AccuracyAlternative(self.name, c, dt=h, n_paths=(n,) if n else (), bias=bias, estimator=self)

    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        n_total, piece = whole_pieces(plan.n_paths[0])
        res = multilevel_monte_carlo(
            pricing.system,
            pricing.y0,
            pricing.run_key,
            n_paths=(n_total,),
            run=pricing.run_at(plan.dt, self.solver),
            antithetic=self.antithetic,
            piece_paths=piece,
            statistic=pricing.statistic,
            wrt=pricing.tangents,
        )
        return res, plan.bias


@dataclasses.dataclass(frozen=True)
class Richardson(AbstractEstimator):
    """Richardson–Romberg extrapolation (:func:`~nhsde.statistics.extrapolate`) at its best ``(h, N)``: residual bias
    ``C' h^{p+1}`` from the difference of two extrapolations, work ``3 N T/h`` (Talay & Tubaro 1990)."""

    solver: str | dfx.AbstractSolver = "euler"
    weak_order: int | None = None
    antithetic: bool = False
    method: str = dataclasses.field(default="extrapolation", init=False, repr=False)

    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        p = pricing.pilot(self.candidate)
        variance = _variances(p, self.antithetic)[1]
        factor = 3 * (2.0 if self.antithetic else 1.0)
        c, k, n, _ = best_single(
            variance, p.extrapolation_bound, p.order + 1, pricing.rmse, pricing.h0, pricing.steps0, factor
        )
        if k < 0:
            finite = math.isfinite(variance + p.extrapolation_bound)
            return self.row("" if finite else "needs pilot_levels ≥ 3")
        h = pricing.h0 / 2**k
        bias = p.extrapolation_constant * h ** (p.order + 1)
        return AccuracyAlternative(self.name, c, dt=h, n_paths=(n,) if n else (), bias=bias, estimator=self)

    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        res = extrapolate(
            pricing.system,
            pricing.y0,
            pricing.run_key,
            n_paths=plan.n_paths[0],
            run=pricing.run_at(plan.dt, self.solver),
            order=self.candidate.order,
            antithetic=self.antithetic,
            wrt=pricing.tangents,
        )
        return res, plan.bias

    def kept_samples(self, plan: AccuracyAlternative) -> float:
        return 2 * super().kept_samples(plan)  # the coarse and the fine solve


@dataclasses.dataclass(frozen=True)
class Multilevel(AbstractEstimator):
    """Multilevel Monte Carlo (:func:`~nhsde.statistics.multilevel_monte_carlo`, Giles 2008): the number of levels
    whose bias bound ``b = |C| h_L^p < ε`` costs least with the variance ``ε² − b²`` (:func:`._cost.multilevel_plan`),
    ``V_ℓ`` beyond the pilot decaying at its rate, ``N_ℓ ∝ √(V_ℓ/C_ℓ)``, in whole pieces; run
    with that allocation fixed (an allocation adapted from its own samples stops early on low variance estimates,
    biasing a covariance low).  ``control``: ``True``: every level also solves the linearised system as a control
    variate (``control='mean'``); ``'martingale'``: every level's paths carry the martingale control of the mean
    (Euler or weak order 2); either priced from its controlled pilot (:class:`ControlPilot`)."""

    solver: str | dfx.AbstractSolver = "euler"
    weak_order: int | None = None
    antithetic: bool = False
    control: bool | str = False
    method: str = dataclasses.field(default="multilevel", init=False, repr=False)

    def __post_init__(self):
        if self.control not in (False, True, "martingale"):
            raise ValueError(f"control={self.control!r}; allowed: False, True (the linearised system) or 'martingale'.")

    @property
    def own_pilot(self) -> bool:
        return bool(self.control)

    @property
    def control_kind(self) -> str | None:
        """The ``control=`` of :func:`~nhsde.statistics.multilevel_monte_carlo`."""
        return "martingale" if self.control == "martingale" else "mean" if self.control else None

    def _levels(self, pricing: Pricing) -> tuple[tuple[float, ...], float, float, float]:
        """``(V_ℓ, |C| bound, κ, pilot work done now)``: the solver's pilot (``κ = 1``), or with the control the
        controlled one."""
        kind = self.control_kind
        if kind is None:
            p = pricing.pilot(self.candidate)
            return _variances(p, self.antithetic)[2], p.bias_bound, 1.0, 0.0
        pilot, work = pricing.control_pilot(self.candidate, self.antithetic, kind)
        return pilot.level_variances, pilot.bias_bound, pilot.kappa, work

    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        try:
            variances, bound, kappa, work = self._levels(pricing)
        except SimulationError as e:  # the control's pilot paths blow up at this step
            return self.row(f"does not apply: {str(e).splitlines()[0][:160]}")
        c, counts, piece, n_levels = multilevel_plan(
            variances,
            bound,
            self.candidate.order,
            pricing.rmse,
            pricing.steps0,
            pricing.h0,
            self.antithetic,
            pricing.pilot_paths,
            control=bool(self.control),
        )
        note = f"{n_levels} levels" if n_levels else "too many levels"
        return AccuracyAlternative(
            self.name,
            c * kappa,
            dt=pricing.h0,
            n_paths=counts,
            note=note + (f", κ = {kappa:.3g}" if self.control else ""),
            piece_paths=piece,
            pilot_work=work,
            kappa=kappa,
            estimator=self,
        )

    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        res = multilevel_monte_carlo(
            pricing.system,
            pricing.y0,
            pricing.run_key,
            n_paths=plan.n_paths,
            run=pricing.run_at(plan.dt, self.solver),
            weak_order=self.candidate.order,
            antithetic=self.antithetic,
            control=self.control_kind,
            piece_paths=plan.piece_paths,
            statistic=pricing.statistic,
            wrt=pricing.tangents,
        )
        return res, float(res.bias)

    def kept_samples(self, plan: AccuracyAlternative) -> float:
        return self.copies * sum(n * (2 if ell else 1) for ell, n in enumerate(plan.n_paths))


@dataclasses.dataclass(frozen=True)
class ControlVariate(AbstractEstimator):
    """The control variate of :func:`~nhsde.statistics.control_variate` (Euler).  Pilot: it at the two finest pilot
    steps on one Brownian path; its variance per path at the finest, its bias ``C h`` bounded by
    ``(|ΔŶ| + 2(SE_a + SE_b))/h_b`` (``p = 1``)."""

    solver: str = dataclasses.field(default="euler", init=False)
    weak_order: int | None = dataclasses.field(default=None, init=False)
    antithetic: bool = dataclasses.field(default=False, init=False)
    method: str = dataclasses.field(default="control variate", init=False, repr=False)

    @property
    def own_pilot(self) -> bool:
        return True

    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        n_pilot, levels = pricing.pilot_paths, pricing.pilot_levels
        h_a, h_b = pricing.h0 / 2 ** (levels - 2), pricing.h0 / 2 ** (levels - 1)
        try:
            runs = [
                linearised_control_variate(
                    pricing.system,
                    pricing.y0,
                    fold_key(pricing.pilot_key, 99),
                    n_paths=n_pilot,
                    run=pricing.run_at(h, self.solver, brownian_dt=h_b, keep_paths=False),
                )
                for h in (h_a, h_b)
            ]
        except (ValueError, TypeError, NotImplementedError, SimulationError) as e:  # paths blowing up at this step
            return self.row(f"does not apply: {e}")
        (va, sa), (vb, sb) = (tuple(float(x) for x in r.value(pricing.statistic)) for r in runs)
        if not all(math.isfinite(x) for x in (va, sa, vb, sb)):
            return self.row("non-finite pilot")
        work = sum(r.cost.path_steps for r in runs)
        bound = (abs(vb - va) + 2 * (sa + sb)) / h_b
        per_path_step = runs[1].cost.path_steps / n_pilot / (pricing.steps0 * 2 ** (levels - 1))
        c, k, n, _ = best_single(sb**2 * n_pilot, bound, 1, pricing.rmse, pricing.h0, pricing.steps0, per_path_step)
        if k < 0:
            return self.row("no step reaches the target", work)
        h = pricing.h0 / 2**k
        bias = -(vb - va) / h_b * h  # E Ŷ(h) − S ≈ C h with C = −ΔŶ/h_b (p = 1)
        return AccuracyAlternative(self.name, c, dt=h, n_paths=(n,), bias=bias, pilot_work=work, estimator=self)

    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        res = linearised_control_variate(
            pricing.system,
            pricing.y0,
            pricing.run_key,
            n_paths=plan.n_paths[0],
            run=pricing.run_at(plan.dt, self.solver, keep_paths=False),
            wrt=pricing.tangents,
        )
        return res, plan.bias

    def kept_samples(self, plan: AccuracyAlternative) -> float:
        return 2 * super().kept_samples(plan)  # the system and its control


QMC_REPLICATES = 16
"""Scramblings of quasi-Monte Carlo, in its pilot and its run (one compiled program for both)."""
QMC_FINER = 2
"""Halvings of the pilot's finest step that quasi-Monte Carlo's pilot program covers, so that a run at a finer step
than the pilot's (tighter targets) compiles nothing new."""
QMC_MARGIN = 1 + math.sqrt(2 / (QMC_REPLICATES - 1))
"""A run's variance target is its budget over this: one standard error of a 16-scramblings variance estimate."""


def _power_of_two(points: float) -> int:
    """Points per scrambling: a power of two ≥ 64 (a net), at least ``points``."""
    return max(BLOCK, 1 << max(0, math.ceil(math.log2(max(points, 1.0)))))


@dataclasses.dataclass(frozen=True)
class _QmcPilot:
    """Quasi-Monte Carlo's pilot: the estimates at ``n_q`` and ``2 n_q`` points per scrambling on each level, the
    measured cost ratio ``κ`` and the pilot's work (path-steps, the plain reference run included)."""

    first: MultilevelEstimate
    second: MultilevelEstimate
    n_q: int
    kappa: float
    work: float

    def rates(self, statistic: AbstractStatistic) -> list[tuple[float, float]]:
        """Per level ``(a_ℓ, β_ℓ)``: its estimate's variance ``a_ℓ N^{−β_ℓ}`` at ``N`` points per scrambling, ``β``
        measured between the two counts and clamped to ``[1, 2]`` (1 the Monte-Carlo rate, 2 an error falling as
        ``1/N``, smooth statistics)."""
        out = []
        for v1, v2 in zip(*(_level_variances(r) for r in (self.first, self.second)), strict=True):
            beta = min(max(math.log2(v1 / v2), 1.0), 2.0) if v1 > 0 and v2 > 0 else 1.0
            out.append((v2 * (2 * self.n_q) ** beta, beta))
        return out


class _BiasModel(NamedTuple):
    """``E S(h) − S ≈ constant h^order``, ``|constant| ≤ bound``."""

    bound: float
    constant: float
    order: int


def _level_variances(res: MultilevelEstimate) -> list[float]:
    """The variance of each level's estimate (``V̂_ℓ``, from the scramblings' spread)."""
    return [float(v) / n for v, n in zip(res.level_variances, res.n_paths_per_level, strict=True)]


class _AbstractQuasiMonteCarlo(AbstractEstimator):
    """What quasi-Monte Carlo and multilevel quasi-Monte Carlo share: where they apply, their pilot (two point
    counts of 16 scramblings, the second timed against a plain solve for ``κ``) and their run (points doubled on
    the level with the most variance per unit of work until the standard error meets the target)."""

    @property
    def own_pilot(self) -> bool:
        return True

    def applies(self, pricing: Pricing) -> str | None:
        if _finest(pricing) < pricing.pilot_levels - 1:
            return "does not apply: the pilot's finest step exceeds the Sobol' dimensions"
        if pricing.steps0 & (pricing.steps0 - 1):
            return f"does not apply: (t1 − t0)/dt = {pricing.steps0} steps, not a power of two"
        if not pricing.system.noise.continuous:
            return f"does not apply: the driver {type(pricing.system.noise).__name__} has jumps"
        return None

    pilot_fold: ClassVar[int]  # the pilot key's fold index, its own

    def _bias_model(self, pricing: Pricing) -> tuple[_BiasModel, float]:
        """Its bias model and the pilot work done for it now: the solver's pilot's (every path has the law of a
        Monte-Carlo path, so the scheme's bias is unchanged), or with the control the controlled pilot's (the
        bias of ``Y − β(C − E C)``, :class:`ControlPilot`)."""
        own = pricing.pilot(self.candidate)
        if not self.control:
            return _BiasModel(own.bias_bound, own.bias_constant, own.order), 0.0
        pilot, work = pricing.control_pilot(self.candidate, False)
        return _BiasModel(pilot.bias_bound, pilot.bias_constant, own.order), work

    def _pilot(self, pricing: Pricing, h: float, n_levels: int) -> _QmcPilot | tuple[str, float]:
        """The pilot on ``n_levels`` levels from the step ``h``, or why it failed and its work."""
        key = fold_key(pricing.pilot_key, self.pilot_fold)
        n_q = max(BLOCK, 1 << ((pricing.pilot_paths // QMC_REPLICATES).bit_length() - 1))  # points per scrambling

        def run(k, points):
            start = time.perf_counter()
            res = self._points(pricing, k, h, variance=0.0, max_points=(points,) * n_levels)
            jax.block_until_ready((res.mean, res.cov, res.mean_se, res.cov_se))
            return res, time.perf_counter() - start

        try:
            first, _ = run(key, n_q)
            second, seconds = run(fold_key(key, 1), 2 * n_q)  # compiled now: timed, and twice the points
        except (ValueError, TypeError, SimulationError) as e:  # paths blowing up: not at this step
            return f"does not apply: {str(e).splitlines()[0][:200]}", 0.0
        path_steps = self.copies * second.cost.path_steps
        # κ against plain Monte Carlo with the solver at the finest pilot step, in the compiled program its other
        # alternatives run (its pilot compiled it), in either cost mode: with cost='seconds' every alternative's
        # seconds are its path-steps times its pilot's rate, so quasi-Monte Carlo's must be too, via κ
        h_b = pricing.h0 / 2 ** (pricing.pilot_levels - 1)
        steps_b = pricing.steps0 * 2 ** (pricing.pilot_levels - 1)
        n_ref = RUN_PATHS * math.ceil(path_steps / steps_b / RUN_PATHS)
        reference = pricing.run_with(self.solver).at(h_b, brownian_dt=h_b)
        start = time.perf_counter()
        jax.block_until_ready(
            solve_paths(pricing.system, pricing.y0, fold_key(key, 2), reference, first_path=0, n_paths=n_ref)
        )
        plain_rate = (time.perf_counter() - start) / (n_ref * steps_b)
        kappa = seconds / path_steps / plain_rate if plain_rate > 0 else math.nan
        work = 1.5 * path_steps + float(n_ref * steps_b)
        if not math.isfinite(kappa) or not all(v > 0 and math.isfinite(v) for v in _level_variances(second)):
            return "non-finite pilot", work
        return _QmcPilot(first, second, n_q, kappa, work)

    def _points(self, pricing: Pricing, key, h: float, *, variance: float, max_points: tuple[int, ...], wrt=()):
        """Quasi-Monte Carlo on the levels ``h … h 2^{1−L}`` (``L = len(max_points)``), points doubled until the
        statistic's squared standard error is at most ``variance`` (or ``max_points``), in the program of the driver
        whose direction numbers cover :data:`QMC_FINER` halvings of the pilot's finest step: the run shares the
        pilot's program unless it is finer still."""
        m = pricing.system.noise_dim
        steps_b = pricing.steps0 << min(pricing.pilot_levels - 1 + QMC_FINER, _finest(pricing))
        run = pricing.run_with(self.solver).at(h)
        finest = run.n_steps << (len(max_points) - 1)
        return quasi_monte_carlo_to_variance(
            pricing.system,
            pricing.y0,
            key,
            run,
            statistic=pricing.statistic,
            variance=variance,
            max_points=max_points,
            dimension=max(steps_b, finest) * m,
            replicates=QMC_REPLICATES,
            wrt=wrt,
            antithetic=self.antithetic,
            control="mean" if self.control else None,
        )

    def run(self, pricing: Pricing, plan: AccuracyAlternative) -> tuple[AbstractEstimate, float]:
        """The points doubled until the standard error meets the target with the bias bound at the finest step,
        ``SE² (1 + √(2/(R − 1))) ≤ ε² − (|C| h_L^p)²`` (a margin of one standard error of the variance estimate);
        the plan's counts, at the slowest rate, are the most.  With ``wrt``, the derivatives from the same points."""
        model, _ = self._bias_model(pricing)  # priced: no pilot runs now
        h_fine = plan.dt / 2 ** (len(plan.n_paths) - 1)
        budget = pricing.rmse**2 - bias(model.bound, h_fine, model.order) ** 2
        most = tuple(n // QMC_REPLICATES for n in plan.n_paths)
        key = pricing.run_key
        res = self._points(pricing, key, plan.dt, variance=budget / QMC_MARGIN, max_points=most, wrt=pricing.wrt)
        return res, plan.bias

    def kept_samples(self, plan: AccuracyAlternative) -> float:
        solves = self.copies * (2 if len(plan.n_paths) > 1 else 1)  # a level's fine and coarse
        return solves * min(max(plan.n_paths), RUN_LIMIT)  # one run's values at a time, reduced into sums


@dataclasses.dataclass(frozen=True)
class QuasiMonteCarlo(_AbstractQuasiMonteCarlo):
    """Randomised quasi-Monte Carlo (16 scrambled Sobol' point sets through a Brownian bridge) with ``solver``:
    Euler (``p = 1``) or :class:`~nhsde.PlatenWeak2` with Gaussian increments (``p = 2``; ``W`` from the points);
    ``antithetic``: each point also solved with its increments reflected, its value the pair's average (work
    doubled); ``control``: the linearised system solved on the same points as a control variate (work doubled,
    its bias model the controlled pilot's, :class:`ControlPilot`).

    Pilot: ``n_q`` and then ``2 n_q`` points per scrambling (``pilot_paths/16`` rounded down to a power of two,
    ≥ 64) at the finest pilot step, the second run timed.  Between the two counts its variance falls as
    ``N^{−β}``, ``β`` clamped to ``[1, 2]`` (1 the Monte-Carlo rate, 2 an error falling as ``1/N``), which predicts
    the points the target needs; the bias is the solver's, from its pilot (each path has the law of a
    Monte-Carlo path, so the scheme's bias is unchanged).  Work in the solver's plain path-steps: its path-steps
    times ``κ``, the measured seconds per path-step over those of a compiled plain solve with the same solver and
    step (its work is counted in the pilot's).  The run doubles the points until its own standard error meets
    the target (:meth:`run`), at most the count the slowest rate either side of the pilot allows (the Monte-Carlo
    rate above it, ``N^{−2}`` below).  Steps ``h₀ 2^{−k}`` only while
    ``steps × channels`` stays within the Sobol' dimensions."""

    solver: str | dfx.AbstractSolver = "euler"
    weak_order: int | None = None
    antithetic: bool = False
    control: bool = False
    method: str = dataclasses.field(default="quasi-Monte Carlo", init=False, repr=False)
    pilot_fold: ClassVar[int] = 98

    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        model, model_work = self._bias_model(pricing)
        h_b = pricing.h0 / 2 ** (pricing.pilot_levels - 1)
        pilot = self._pilot(pricing, h_b, 1)
        if isinstance(pilot, tuple):
            return self.row(pilot[0], pilot[1] + model_work)
        n_q, work = pilot.n_q, pilot.work + model_work
        ((a, rate),) = pilot.rates(pricing.statistic)

        def per_replicate(n: float, beta: float | None = None) -> int:
            """Points per scrambling for ``n`` paths at the Monte-Carlo rate, at rate ``β`` from the pilot's
            ``2 n_q``; ``None``: the most, at the slowest rate either side (1 above, 2 below)."""
            r = max(n, 1.0) / QMC_REPLICATES / (2 * n_q)
            return _power_of_two(2 * n_q * (max(r, math.sqrt(r)) if beta is None else r ** (1 / beta)))

        variance = a * (2 * n_q) ** -rate * QMC_REPLICATES * 2 * n_q  # per point, at the Monte-Carlo rate
        cost, k, _, _ = best_single(
            variance,
            model.bound,
            model.order,
            pricing.rmse,
            pricing.h0,
            pricing.steps0,
            self.copies * pilot.kappa,
            _finest(pricing),
            lambda n: QMC_REPLICATES * per_replicate(n, rate),
        )
        if k < 0:
            return self.row("no step reaches the target within the Sobol' dimensions", work)
        h = pricing.h0 / 2**k
        b = bias(model.bound, h, model.order)
        most = per_replicate(variance / ((pricing.rmse - b) * (pricing.rmse + b)))  # the run's cap
        if most > KEY_PATHS // QMC_REPLICATES:
            note = f"needs {most:.3g} points per scrambling, more than the {KEY_PATHS // QMC_REPLICATES} a run indexes"
            return self.row(note, work)
        expected = per_replicate(variance / ((pricing.rmse - b) * (pricing.rmse + b)), rate)
        return AccuracyAlternative(
            self.name,
            cost,
            dt=h,
            n_paths=(QMC_REPLICATES * most,),
            bias=model.constant * h**model.order,  # E S(h) − S ≈ C h^p
            note=f"16 × {expected} points expected (variance ∝ N^−{rate:.2g}), at most 16 × {most}, "
            f"κ = {pilot.kappa:.3g}",
            pilot_work=work,
            kappa=pilot.kappa,
            estimator=self,
        )


@dataclasses.dataclass(frozen=True)
class MultilevelQuasiMonteCarlo(_AbstractQuasiMonteCarlo):
    """Multilevel randomised quasi-Monte Carlo (:func:`~nhsde.statistics.multilevel_quasi_monte_carlo`, Giles &
    Waterhouse 2009) with ``solver`` as :class:`QuasiMonteCarlo`, on levels ``h₀ … h₀ 2^{−L}`` fixed by the solver's
    pilot: ``|C| h_L^p < ε``, the variance budget ``ε² − (|C| h_L^p)²``.

    Pilot: every pilot level's coupled pair at ``n_q`` and ``2 n_q`` points per scrambling, the second timed for
    ``κ``.  Level ``ℓ``'s variance ``a_ℓ N^{−β_ℓ}`` (``β_ℓ`` measured between the counts, clamped to ``[1, 2]``),
    levels beyond the pilot's decaying at its finest rate (clamped to ``[1, 2]``) with its ``β``.  Points
    ``N_ℓ = (λ β_ℓ a_ℓ / C_ℓ)^{1/(1 + β_ℓ)}`` (the least work ``Σ N_ℓ C_ℓ`` with ``Σ a_ℓ N_ℓ^{−β_ℓ}`` at the budget,
    ``λ`` by bisection), powers of two; the cheapest ``L`` within the pilot program's Sobol' dimensions.  The run
    doubles points where the variance per unit of work is largest until its own standard error meets the target,
    each level at most its count at the Monte-Carlo rate (Giles's allocation, ``β = 1``).  ``control`` as for
    :class:`QuasiMonteCarlo`."""

    solver: str | dfx.AbstractSolver = "euler"
    weak_order: int | None = None
    antithetic: bool = False
    control: bool = False
    method: str = dataclasses.field(default="multilevel quasi-Monte Carlo", init=False, repr=False)
    pilot_fold: ClassVar[int] = 97

    def predict(self, pricing: Pricing) -> AccuracyAlternative:
        model, model_work = self._bias_model(pricing)
        m = pricing.pilot_levels
        pilot = self._pilot(pricing, pricing.h0, m)
        if isinstance(pilot, tuple):
            return self.row(pilot[0], pilot[1] + model_work)
        rates = pilot.rates(pricing.statistic)
        v2 = _level_variances(pilot.second)
        decay = min(max(math.log2(v2[-2] / v2[-1]), 1.0), 2.0)
        best: tuple[float, tuple[int, ...], tuple[int, ...], int] = (math.inf, (), (), 0)
        for top in range(1, min(m - 1 + QMC_FINER, _finest(pricing)) + 1):
            b = bias(model.bound, pricing.h0 / 2**top, model.order)
            if not b < pricing.rmse:
                continue
            budget = (pricing.rmse - b) * (pricing.rmse + b)
            levels = [rates[min(ell, m - 1)] for ell in range(top + 1)]
            levels = [(a * 2 ** (-decay * max(0, ell - m + 1)), beta) for ell, (a, beta) in enumerate(levels)]
            costs = [self.copies * level_cost(pricing.steps0, ell, False) for ell in range(top + 1)]
            expected = [_power_of_two(n) for n in _allocate_at_rates(levels, costs, budget)]
            mc = [a * (2 * pilot.n_q) ** -beta * 2 * pilot.n_q for a, beta in levels]  # per point, the MC rate
            most = [max(e, _power_of_two(n)) for e, n in zip(expected, allocate(mc, costs, budget))]
            cost = QMC_REPLICATES * sum(n * c for n, c in zip(expected, costs)) * pilot.kappa
            if cost < best[0] and max(most) <= KEY_PATHS // QMC_REPLICATES:
                best = (cost, tuple(expected), tuple(most), top)
        cost, expected, most, top = best
        if not expected:
            return self.row("no level count reaches the target within the Sobol' dimensions", pilot.work + model_work)
        h_fine = pricing.h0 / 2**top
        return AccuracyAlternative(
            self.name,
            cost,
            dt=pricing.h0,
            n_paths=tuple(QMC_REPLICATES * n for n in most),
            bias=model.constant * h_fine**model.order,
            note=f"{top + 1} levels, 16 × {list(expected)} points expected, at most 16 × {list(most)}, "
            f"κ = {pilot.kappa:.3g}",
            pilot_work=pilot.work + model_work,
            kappa=pilot.kappa,
            estimator=self,
        )


def _allocate_at_rates(levels: list[tuple[float, float]], costs: list[float], budget: float) -> list[float]:
    """Points ``N_ℓ = (λ β_ℓ a_ℓ / C_ℓ)^{1/(1 + β_ℓ)}`` with ``Σ a_ℓ N_ℓ^{−β_ℓ} = budget`` (module of
    :class:`MultilevelQuasiMonteCarlo`), ``λ`` by bisection on its logarithm."""

    def counts(log_lam: float) -> list[float]:
        return [math.exp((log_lam + math.log(beta * a / c)) / (1 + beta)) for (a, beta), c in zip(levels, costs)]

    def excess(log_lam: float) -> float:
        return sum(a * n**-beta for (a, beta), n in zip(levels, counts(log_lam))) - budget

    lo, hi = -200.0, 200.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) > 0 else (lo, mid)
    return counts(hi)


def _finest(pricing: Pricing) -> int:
    """The most refinements ``k`` of ``h₀`` whose ``steps × channels`` fit the Sobol' dimensions (−1: none)."""
    return min(MAX_REFINEMENTS, math.floor(math.log2(MAX_DIMENSION / (pricing.steps0 * pricing.system.noise_dim))))
