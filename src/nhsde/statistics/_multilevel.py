"""Multilevel Monte Carlo for means and covariances of saved quantities (Giles, Oper. Res. 2008; Acta Numer. 2015).

Levels ``ℓ = 0 … L`` step ``h_ℓ = h₀ 2^{−ℓ}``.  Level 0 samples ``P_0``, level
``ℓ > 0`` the difference ``P_ℓ − P_{ℓ−1}`` of a fine solve at ``h_ℓ`` and a coarse
solve at ``h_{ℓ−1}`` on one Brownian path (``brownian_dt = h_ℓ`` for both, one key
per level, different keys across levels), so that

    E[P_L] = E[P_0] + Σ_{ℓ=1}^{L} E[P_ℓ − P_{ℓ−1}]

holds exactly: the coarse solve sums fine increments, which for Gaussian
increments gives it the law of a plain solve at ``h_{ℓ−1}``.  A covariance is
telescoped the same way, each level's term the difference of the unbiased
sample covariances of its fine and coarse values on the same paths (Bierig &
Chernov, Numer. Math. 133 (2016)); standard errors are those of the paired
per-path combination (``paired_moments``).

Samples per level for a target RMSE ``ε`` (Giles 2008, §2; cost ``C_ℓ`` in
path-steps, level variance ``V_ℓ`` measured):

    N_ℓ = ⌈2 ε⁻² √(V_ℓ/C_ℓ) Σ_k √(V_k C_k)⌉,

so that the Monte-Carlo variance is ``ε²/2``; levels are added (Giles (2015),
Algorithm 1) until the bias estimate ``max(|Ŷ_L|, |Ŷ_{L−1}|/2^α)/(2^α − 1)`` of a
scheme of weak order ``α`` is below ``ε/√2``.  Level ``ℓ`` draws paths
``0, 1, …`` of the key ``fold_in(key, ℓ)`` (the counter-based driver makes path
``i`` the same in any run; beyond ``2^30`` paths, of keys folded from it), in
runs of ``P_ℓ 2^j`` paths (``P_ℓ = piece_paths`` halved per level, at least 64):
the samples of ``N_ℓ`` depend on ``(key, ℓ, N_ℓ)`` only, and a few compiled
programs per level serve every run.  With the allocation fixed
(``n_paths=result.n_paths_per_level``) the estimator is a differentiable function
of the system's parameters (``jax.jacfwd``, ``jax.grad``).
Three-point increments are refused: their sums are not three-point.  Counts whose
per-path values would not fit in memory are refused, with their size, before they run.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float, Int

from .._brownian import BLOCK
from .._ensemble import Save
from .._misc import check_key, check_number, fold_key, is_concrete
from .._options import AbstractSteps, Batching, RunOptions, run_options
from .._solvers import solver_needs
from .._system import StochasticSystem
from .._weak import PlatenWeak2
from ._control_variate import LinearisedControl, PerEntry, fitted_controls
from ._cost import MAX_LEVELS, allocate, check_memory, level_cost, level_piece, path_bytes, peak_bytes
from ._estimate import AbstractEstimate, AbstractStatistic, Cost, Derivatives, Stopwatch, Values, as_statistic
from ._martingale import MartingaleControl
from ._paths import (
    array_module,
    checked_paths,
    coupled_paths,
    coupling_solver,
    on_device,
    paired_moments,
    paired_sensitivities,
    paths_save,
    roles_of,
    safe_sqrt,
)
from ._sensitivities import check_wrt
from ._variance_reduction import check_reflectable

__all__ = ["MultilevelEstimate", "multilevel_monte_carlo"]


class MultilevelEstimate(AbstractEstimate):
    """A multilevel estimate: the moments of every saved quantity plus the levels that made it.

    ``statistic`` is the one the levels were chosen for (``value()`` and ``derivative()`` read it); per level
    ``ℓ``: ``n_paths_per_level[ℓ] = N_ℓ``, ``level_means[ℓ] = Ŷ_ℓ`` (the statistic's level term),
    ``level_variances[ℓ] = V_ℓ`` (its per-sample variance), ``level_costs[ℓ] = C_ℓ`` (path-steps per sample);
    ``bias`` is the bias estimate from the finest levels; ``dt`` is ``h₀``; ``derivatives`` with ``wrt``;
    ``cost.path_steps`` is ``Σ N_ℓ C_ℓ``; ``coefficient``: with a control, its ``β`` per saved entry.
    """

    ts: Float[Values, " n"]
    mean: Float[Values, "n k"]
    cov: Float[Values, "n k k"]
    mean_se: Float[Values, "n k"]
    cov_se: Float[Values, "n k k"]
    n_paths: Int[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    level_means: Float[Values, " L"]
    level_variances: Float[Values, " L"]
    bias: Float[Values, ""]
    n_paths_per_level: tuple[int, ...] = eqx.field(static=True)
    level_costs: tuple[float, ...] = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    derivatives: Derivatives | None
    cost: Cost = eqx.field(static=True)
    statistic: AbstractStatistic = eqx.field(static=True)
    coefficient: PerEntry | None = None


class _Levels:
    """Level runs, their per-path values kept; with a control, the control's values follow the system's."""

    def __init__(self, system, y0, key, run: RunOptions, *, antithetic, piece_paths, wrt, control):
        self.args = (system, y0)
        self.key = key
        assert run.save is not None and run.save.names is not None and run.save.n is not None
        self.options, self.names, self.n_save = run, run.save.names, run.save.n  # at h0, the paths kept
        self.wrt = wrt
        self.h0, self.steps0, self.piece_paths, self.antithetic = run.dt, run.n_steps, piece_paths, antithetic
        self.control: LinearisedControl | MartingaleControl | None = control
        self.paths: list[list[list[Array]]] = []  # level → run → sets
        self.tangents: list[list[list[Array]]] = []  # the same, their tangents in wrt (empty without)
        self._fitted: tuple[int, tuple] | None = None  # (level-0 count, (β_mean, β_cov)) of the control
        self._exact = None  # the control's exact moments and their tangents

    def piece(self, level: int) -> int:
        return level_piece(self.piece_paths, level)

    def cost(self, level: int) -> float:
        return level_cost(self.steps0, level, self.antithetic, self.control is not None)

    def check_memory(self, counts: Sequence[int], name: str, fix: str) -> None:
        """Refuse (naming ``name``) counts per level whose per-path values would not fit in memory."""
        per_sample = path_bytes(self.n_save, len(self.names), len(self.wrt))
        copies = (2 if self.antithetic else 1) * (1 if self.control is None else 2)
        sets = sum(n * (2 if level else 1) * copies for level, n in enumerate(counts))
        check_memory(name, peak_bytes(sets * per_sample), fix)

    def run(self, level: int, first_path: int, n_paths: int) -> tuple[list[Array], list[Array]]:
        h = self.h0 / 2**level
        options: dict[str, Any] = dict(
            dts=(h, 2 * h) if level else (h,),
            brownian_dt=h,
            n_paths=n_paths,
            first_path=first_path,
            antithetic=self.antithetic,
            wrt=self.wrt,
        )
        key = fold_key(self.key, level)  # the control is driven by the same Brownian path
        if isinstance(self.control, MartingaleControl):  # the system carries the control's components
            return self.control.sets(level, key, self.options, **options)
        paths, tangents = coupled_paths(*self.args, key, self.options, **options)
        if self.control is not None:
            c, t = coupled_paths(self.control.system, self.control.start, key, self.options, **options)
            paths, tangents = paths + c, tangents + t
        return paths, tangents

    def grow(self, level: int, n_paths: int):
        """Run level ``level`` up to ``n_paths`` samples, in runs of the piece times a power of two (then the rest)."""
        while len(self.paths) <= level:
            self.paths.append([])
            self.tangents.append([])
        piece = self.piece(level)
        while (missing := n_paths - self.count(level)) > 0:
            size = piece << ((missing // piece).bit_length() - 1) if missing >= piece else missing
            paths, tangents = self.run(level, self.count(level), size)
            self.paths[level].append(paths)
            self.tangents[level].append(tangents)

    def count(self, level: int) -> int:
        return sum(p[0].shape[0] for p in self.paths[level]) if level < len(self.paths) else 0

    def weights(self, level: int) -> list[float]:
        """The weights of the system's sets in the level's term."""
        share = 0.5 if self.antithetic else 1.0
        return [share * w for w in ((1.0, -1.0) if level else (1.0,))] * (2 if self.antithetic else 1)

    def _sets(self, level: int):
        xp = array_module(self.paths[level])
        return [xp.concatenate(parts) for parts in zip(*self.paths[level], strict=True)]

    def coefficients(self, level: int = 0):
        """``(β_mean, β_cov)`` of the control, fitted on level 0's samples (the control's module) and used on every
        level, so that the levels telescope to ``E[Y_L − β C_L]``; the martingale control's, per level."""
        assert self.control is not None
        if isinstance(self.control, MartingaleControl):
            return self.control.coefficients(level)
        if self._fitted is None or self._fitted[0] != self.count(0):
            sets, w = self._sets(0), self.weights(0)
            half = len(w)
            beta = fitted_controls(sets[:half], sets[half:], w)[2]
            self._fitted = (self.count(0), beta)
        return self._fitted[1]

    def _all_weights(self, level: int):
        """``(mean weights, cov weights)`` of every set of the level: ``w`` on the system's, ``−β w`` on the
        control's."""
        w = self.weights(level)
        if self.control is None:
            return w, w
        beta_m, beta_c = self.coefficients(level)
        return w + [-beta_m * x for x in w], w + [-beta_c * x for x in w]

    def exact(self):
        """The control's exact moments ``(ts, mean, cov)`` and their tangents in ``wrt`` (computed once)."""
        assert self.control is not None
        if self._exact is None:
            run, on_host = self.options, array_module(self.paths[0]) is np
            self._exact = self.control.exact(
                self.args[0], self.names, run.t0, run.t1, self.steps0, self.n_save, self.wrt, on_host
            )
        return self._exact

    def moments(self, level: int):
        """``(mean, cov, mean_var, cov_var)`` of the level's term ``P_ℓ − P_{ℓ−1}`` (``P_0`` at level 0); with a
        control, ``P = Y − β C`` and level 0 adds ``β E C``."""
        mean, cov, mean_var, cov_var = paired_moments(self._sets(level), *self._all_weights(level))
        if self.control is not None and level == 0:
            (_, exact_mean, exact_cov), _ = self.exact()
            beta_m, beta_c = self.coefficients()
            mean, cov = mean + beta_m * exact_mean, cov + beta_c * exact_cov
        return mean, cov, mean_var, cov_var

    def sensitivities(self, level: int):
        """``(d_mean, d_cov, d_mean_var, d_cov_var)`` of the level's term in the parameters ``wrt`` (β held
        fixed, as the control's module)."""
        xp = array_module(self.paths[level], self.tangents[level])
        tangents = [xp.concatenate(parts, axis=1) for parts in zip(*self.tangents[level], strict=True)]
        d_mean, d_cov, d_mean_var, d_cov_var = paired_sensitivities(
            self._sets(level), tangents, *self._all_weights(level)
        )
        if self.control is not None and level == 0:
            _, d_exact = self.exact()
            assert d_exact is not None  # with wrt
            _, d_exact_mean, d_exact_cov = d_exact
            beta_m, beta_c = self.coefficients()
            d_mean, d_cov = d_mean + beta_m * d_exact_mean, d_cov + beta_c * d_exact_cov
        return d_mean, d_cov, d_mean_var, d_cov_var


def multilevel_monte_carlo(
    system: StochasticSystem,
    y0,
    key,
    *,
    statistic,
    t1: float | None = None,
    rmse: float | None = None,
    n_paths: Sequence[int] | None = None,
    dt: float | None = None,
    steps: AbstractSteps | None = None,
    t0: float | None = None,
    solver: str | dfx.AbstractSolver | None = None,
    save: Save | None = None,
    run: RunOptions | None = None,
    weak_order: float | None = None,
    antithetic: bool = False,
    control=None,
    piece_paths: int = 4096,
    max_levels: int = MAX_LEVELS,
    batching: Batching | None = None,
    wrt: Sequence[str] | None = None,
) -> MultilevelEstimate:
    """Multilevel Monte Carlo estimate of the saved means and covariances (module docstring).

    Arguments as :func:`~nhsde.simulate` (``run=`` or its keywords), and:

    - ``statistic``: the statistic whose RMSE is controlled, at ``t1``: :class:`~nhsde.statistics.Mean`,
      :class:`~nhsde.statistics.Covariance` or the shorthand ``('mean', name)``, ``('cov', a, b)``; its names must
      be saved (``save`` defaults to them).
    - ``rmse``: the requested root-mean-square error of ``statistic`` (levels and
      samples chosen adaptively), or ``n_paths``: a fixed ``(N_0, …, N_L)``, e.g.
      ``result.n_paths_per_level`` (no adaptation; differentiable in the parameters).
    - ``dt`` (or ``steps=FixedSteps(dt)``): the coarsest step ``h₀``.
    - ``weak_order``: ``α`` of the bias estimate (default 2 for
      :class:`~nhsde.PlatenWeak2`, else 1, which overestimates the bias of a
      second-order scheme and is safe).
    - ``antithetic``: pair every path with its reflection ``W → −W``.
    - ``control``: ``'mean'`` or a state ``(d,)``: every level's solves also solve the linearised system
      (:func:`~nhsde.statistics.control_variate`'s ``linearisation``; ``y0`` one state) on the same Brownian path,
      and the levels telescope ``P = Y − βC`` with one ``β`` per saved entry fitted on level 0, so that
      ``E[P_L] + β E C = E Y_L − β (E C_L − E C)`` with ``E C`` exact: the bias is ``bias(Y_L) − β bias(C_L)``, as
      for the plain control variate, and the level variances shrink where the linearisation explains the
      paths (level 0 above all).  Twice the path-steps (``level_costs``); ``coefficient`` holds ``β``.
      ``'martingale'``: every level's paths carry the martingale control of each saved mean
      (:func:`~nhsde.statistics.martingale_control_variate`, Euler or weak order 2), fitted once on an independent
      pilot at ``h₀`` (its paths counted in ``cost``): each discretisation's control has mean exactly zero, so the
      bias is the solver's; level 0 uses it, the level differences per mean entry where it lowered the first
      difference's variance on another independent pilot; covariances
      are not controlled.
      ``level_costs`` counted as with ``'mean'``; ``coefficient`` holds the fitted ``β`` (trailing axis: the basis).
    - ``piece_paths``: the smallest run on level 0 (halved per level, at least 64): samples are added in
      multiples of it.
    - ``max_levels``: the most levels to add before giving up.
    - ``wrt``: names of scalar parameters (``('eps', 'nu')``): ``derivatives`` of every saved moment in them
      (``derivative()`` reads the statistic's), with their Monte-Carlo standard errors (per-path tangents of
      every level, :func:`~nhsde.statistics.moment_sensitivities`' estimator on the level differences).
    """
    watch = Stopwatch()
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if (rmse is None) == (n_paths is None):
        raise TypeError("multilevel_monte_carlo needs exactly one of rmse=… (adaptive) or n_paths=(N_0, …, N_L).")
    run = run_options(
        "multilevel_monte_carlo", run, t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, batching=batching
    )
    h0, steps0, solver = run.dt, run.n_steps, run.solver
    solver_needs(coupling_solver(solver), system)
    if not isinstance(antithetic, bool):
        raise TypeError(f"antithetic={antithetic!r}; expected True or False.")
    if antithetic:
        check_reflectable(system.noise, "antithetic=True")
    if weak_order is None:
        alpha = 2 if isinstance(solver, PlatenWeak2) else 1
    else:
        alpha = check_number("weak_order", weak_order, positive=True)
    piece_paths = check_number("piece_paths", piece_paths, integer=True)
    if piece_paths < BLOCK or piece_paths % BLOCK:
        raise ValueError(f"piece_paths={piece_paths}; must be a positive multiple of {BLOCK}.")
    max_levels = check_number("max_levels", max_levels, integer=True)
    if max_levels < (1 if rmse is None else 2):
        raise ValueError(
            f"max_levels={max_levels}; must be ≥ 1, and ≥ 2 with rmse=… (the bias estimate compares two levels)."
        )
    statistic = as_statistic(statistic)
    save = paths_save(run.save, steps0, statistic.names)
    assert save.names is not None
    statistic.check(save.names)
    key = check_key(key)
    wrt = () if wrt is None else check_wrt(system, wrt)
    control_model: LinearisedControl | MartingaleControl | None = None
    if isinstance(control, str) and control not in ("mean", "martingale"):
        raise ValueError(
            f"control={control!r}; allowed: 'mean' (the linearised system about the noiseless motion), a reference "
            f"state of shape ({system.state_dim},) for it, or 'martingale' (the martingale control of the means)."
        )
    if isinstance(control, str) and control == "martingale":
        control_model = MartingaleControl(system, y0, key, dataclasses.replace(run, save=save))
    elif control is not None:
        control_model = LinearisedControl(system, system.state(y0, "y0"), control, save.names, "control")
    levels = _Levels(
        system,
        y0,
        key,
        dataclasses.replace(run, save=save),
        antithetic=antithetic,
        piece_paths=piece_paths,
        wrt=wrt,
        control=control_model,
    )

    if n_paths is not None:
        if not isinstance(n_paths, Sequence) or isinstance(n_paths, str):
            raise TypeError(
                f"n_paths={n_paths!r}; expected one count per level, (N_0, …, N_L): the count fixes the number of "
                f"levels (e.g. n_paths=({n_paths!r},) * 3 for three levels of that many samples each), or give "
                "rmse=… to choose levels and counts."
            )
        counts = list(checked_paths("n_paths", n_paths, per_level=True))
        levels.check_memory(counts, f"n_paths={tuple(counts)}", "take fewer paths, or average runs of several keys.")
        for level, n in enumerate(counts):
            levels.grow(level, n)
        moments = [levels.moments(level) for level in range(len(counts))]
    else:
        eps = check_number("rmse", rmse, positive=True)
        if not is_concrete(system, y0):
            raise TypeError(
                "rmse=…: choosing the levels needs concrete parameters; under jax transformations pass "
                "n_paths=result.n_paths_per_level of an earlier call instead."
            )
        moments = _adapt(levels, eps, alpha, max_levels, statistic, save.names)
        counts = [levels.count(level) for level in range(len(moments))]

    xp = array_module(moments)
    mean, cov, mean_var, cov_var = (xp.sum(xp.stack(parts), axis=0) for parts in zip(*moments, strict=True))
    names = save.names
    level_means = xp.stack([statistic.pick(names, m[0], m[1]) for m in moments])
    level_vars = xp.stack([statistic.pick(names, m[2], m[3]) * n for m, n in zip(moments, counts)])
    derivatives = None
    if wrt:
        sensitivities = [levels.sensitivities(level) for level in range(len(counts))]
        xp = array_module(sensitivities)
        d_mean, d_cov, d_mean_var, d_cov_var = (
            xp.sum(xp.stack(parts), axis=0) for parts in zip(*sensitivities, strict=True)
        )
        derivatives = Derivatives(d_mean, d_cov, safe_sqrt(d_mean_var), safe_sqrt(d_cov_var), wrt)
    level_costs = tuple(levels.cost(level) for level in range(len(counts)))
    fit_path_steps, coefficient = 0.0, None
    if isinstance(control_model, MartingaleControl):
        fit_path_steps, coefficient = control_model.pilot_path_steps, control_model.coefficient
    elif control_model is not None:
        coefficient = PerEntry(*levels.coefficients())
    estimate = MultilevelEstimate(
        ts=np.linspace(run.t0, run.t1, mean.shape[0]),
        mean=mean,
        cov=cov,
        mean_se=safe_sqrt(mean_var),
        cov_se=safe_sqrt(cov_var),
        n_paths=jax.device_put(np.asarray(sum(counts))),
        names=names,
        roles=roles_of(system, names),
        level_means=level_means,
        level_variances=level_vars,
        bias=bias_estimate(level_means, alpha),
        n_paths_per_level=tuple(counts),
        level_costs=level_costs,
        dt=h0,
        derivatives=derivatives,
        cost=watch.cost(sum(n * c for n, c in zip(counts, level_costs)) + fit_path_steps),
        statistic=statistic,
        coefficient=coefficient,
    )
    return on_device(estimate, levels.paths[0][0][0].dtype)


def bias_estimate(level_means, alpha):
    """Giles (2015) Algorithm 1: ``max(|Ŷ_L|, |Ŷ_{L−1}|/2^α)/(2^α − 1)``."""
    xp = array_module(level_means)
    if level_means.shape[0] < 2:
        return xp.asarray(xp.nan, level_means.dtype)
    return xp.maximum(xp.abs(level_means[-1]), xp.abs(level_means[-2]) / 2**alpha) / (2**alpha - 1)


def _adapt(levels: _Levels, eps: float, alpha: float, max_levels: int, statistic: AbstractStatistic, names):
    """Giles (2015) Algorithm 1 with samples in whole pieces; returns the moments of each level."""
    n_levels = min(3, max_levels)
    wanted = [levels.piece(level) for level in range(n_levels)]
    while True:
        for level, n in enumerate(wanted):
            levels.grow(level, n)
        moments = [levels.moments(level) for level in range(n_levels)]
        counts = [levels.count(level) for level in range(n_levels)]
        variances = [max(float(statistic.pick(names, m[2], m[3])) * n, 1e-300) for m, n in zip(moments, counts)]
        costs = [levels.cost(level) for level in range(n_levels)]
        optimal = allocate(variances, costs, eps * eps / 2)  # a product: 1e300² is inf, not an error
        if not all(o < 2.0**62 for o in optimal):
            raise ValueError(
                f"rmse={eps:.3g}: the level variances {variances} need more than 2^62 samples; raise rmse."
            )
        wanted = [
            max(n, levels.piece(level) * math.ceil(o / levels.piece(level)))
            for level, (n, o) in enumerate(zip(counts, optimal))
        ]
        if wanted != counts:
            levels.check_memory(wanted, f"rmse={eps:.3g}: the samples per level {tuple(wanted)}", "raise rmse.")
            continue
        means = np.stack([statistic.pick(names, m[0], m[1]) for m in moments])
        if float(bias_estimate(means, alpha)) <= eps / math.sqrt(2):
            return moments
        if n_levels >= max_levels:
            raise ValueError(
                f"max_levels={max_levels}: the bias estimate {float(bias_estimate(means, alpha)):.3g} is still above "
                f"rmse/√2 = {eps / math.sqrt(2):.3g}; raise max_levels or rmse, or check weak_order={alpha}."
            )
        n_levels += 1
        wanted.append(levels.piece(n_levels - 1))
