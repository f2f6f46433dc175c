"""Multilevel randomised quasi-Monte Carlo (Giles & Waterhouse, Radon Ser. Comput. Appl. Math. 8 (2009)).

Levels ``ℓ = 0 … L`` step ``h_ℓ = h₀ 2^{−ℓ}`` as in :mod:`._multilevel`; level ``ℓ`` draws its Wiener paths
from scrambled Sobol' points through a Brownian bridge over its finest grid (``n_ℓ = (t1 − t0)/h_ℓ`` base
steps, ``n_ℓ × channels ≤ 21201`` dimensions, :mod:`._qmc`), and solves the fine (``h_ℓ``) and the coarse
(``2h_ℓ``, each step the sum of two base increments of the same point) on the same points, so that the level
term ``P_ℓ − P_{ℓ−1}`` is computed per point.  ``R`` independent scramblings per level (keys
``fold_in(fold_in(key, ℓ), r)``) give ``R`` independent unbiased estimates ``Ŷ_{ℓ,r}`` of the level term, each
over the points ``0 … N_ℓ − 1`` (a power of two, a net); the level's estimate is their average and its variance
``V̂_ℓ = s²_r(Ŷ_{ℓ,r})/R``.  A covariance is telescoped as in :mod:`._multilevel`, each term from per-replicate
means and second moments (:func:`._qmc.combine_replicates`, unbiased).

Points per level (Giles & Waterhouse, §3): starting from ``N_ℓ = 64``, double ``N_ℓ`` on the level with the
largest ``V̂_ℓ/(N_ℓ C_ℓ)`` (the most variance removed per unit of work, as ``V̂_ℓ ∝ 1/N_ℓ`` at worst) until
``Σ_ℓ V̂_ℓ ≤ ε²/2``; then add a level while the bias estimate of :func:`._multilevel.bias_estimate` exceeds ``ε/√2``.

One compiled solve serves every level, point count and scrambling: the ``R`` scramblings share one driver
(block ``b`` of the run is point block ``b // R`` of scrambling ``b mod R``, so the points ``N … 2N − 1`` of
every scrambling are the contiguous paths ``NR … 2NR − 1``), its direction numbers padded to the dimension of
the finest level allowed, and the bridge depth ``log₂ n_ℓ`` is data.  Per-point values are reduced on the host
into per-scrambling sums, so memory does not grow with ``N_ℓ``.  Plain randomised quasi-Monte Carlo,
:func:`quasi_monte_carlo`, is the one level ``ℓ = 0`` at ``dt``.

With the counts fixed (``n_points``; :func:`quasi_monte_carlo`'s ``n_paths``) the estimate is a function of the
system's parameters that ``jax.jit``, ``jax.grad``, ``jax.jacfwd`` and ``jax.vmap`` transform, as
:func:`~nhsde.statistics.multilevel_monte_carlo`'s: the sums are then reduced in the trace, in the state's precision.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._brownian import BLOCK
from .._ensemble import Save
from .._misc import check_key, check_number, fold_key, is_concrete
from .._options import Batching, FixedSteps, RunOptions, run_options
from .._system import StochasticSystem
from .._weak import PlatenWeak2
from ._control_variate import LinearisedControl, PerEntry
from ._cost import MAX_LEVELS, level_cost
from ._estimate import AbstractStatistic, Derivatives, Stopwatch, as_statistic
from ._multilevel import MultilevelEstimate, bias_estimate
from ._paths import KEY_PATHS, array_module, coupled_paths, on_device, paths_save, roles_of, safe_sqrt
from ._qmc import (
    MAX_DIMENSION,
    QuasiMonteCarloEstimate,
    ScrambledSobol,
    check_solver,
    combine_replicates,
    stacked_scramblings,
)
from ._sensitivities import check_wrt

__all__ = ["multilevel_quasi_monte_carlo", "quasi_monte_carlo_to_variance"]

RUN_LIMIT = 2**18
"""Most paths solved at once: a larger doubling runs in pieces, reduced into sums as they come."""


def _host(x) -> Any:
    """``x`` for the checker: the host (NumPy) values that the estimators' array-generic helpers reduce."""
    return x


def _pick(statistic: AbstractStatistic, names: tuple[str, ...], mean, cov) -> Any:
    """``statistic``'s entry of host ``mean`` and ``cov`` (or of their variances)."""
    return statistic.pick(names, mean, cov)


class _QmcLevels:
    """The levels' runs, reduced per scrambling into sums of the values and of their outer products; with
    ``antithetic``, each point's value is the average over its path and the reflected one (``W → −W``, the
    point set ``1 − u``), and its outer product the average of the two paths' (so covariances stay unbiased).
    Concrete values are reduced on the host in float64; under JAX transformations (``jit``, ``grad``, ``vmap``) in
    the trace, in the state's precision, as the Monte-Carlo estimators' (:func:`._paths.array_module`)."""

    def __init__(
        self,
        system,
        y0,
        key,
        run: RunOptions,
        *,
        replicates,
        dimension,
        wrt=(),
        antithetic=False,
        control: LinearisedControl | None = None,
    ):
        self.system, self.y0, self.key, self.wrt, self.antithetic = system, y0, key, wrt, antithetic
        self.control = control
        self._fitted: tuple[int, tuple] | None = None  # (level-0 points, (β_mean, β_cov)) of the control
        self._exact_moments = None
        assert run.save is not None and run.save.names is not None and run.save.n is not None
        self.run, self.names, self.n_save = run, run.save.names, run.save.n  # at h0, the paths kept
        self.h0, self.steps0, self.replicates, self.dimension = run.dt, run.n_steps, replicates, dimension
        self.points: list[int] = []  # N_ℓ per scrambling
        # level → per solve: sums of the values (R, n, k) and of their outer products (R, n, k, k); with wrt, of
        # their tangents (p, R, n, k) and of the tangents of the outer products (p, R, n, k, k)
        self.sums: list[list[list[Any]]] = []
        self.drivers: list[ScrambledSobol] = []

    def cost(self, level: int) -> float:
        return level_cost(self.steps0, level, self.antithetic, self.control is not None)

    def driver(self, level: int) -> ScrambledSobol:
        while len(self.drivers) <= level:
            ell, m = len(self.drivers), self.system.noise_dim
            v, shift = stacked_scramblings(fold_key(self.key, ell), self.replicates, self.dimension)
            log_base = jax.device_put(np.asarray((self.steps0 << ell).bit_length() - 1, np.int32))
            self.drivers.append(ScrambledSobol(v=v, shift=shift, log_base=log_base, channels=m))
        return self.drivers[level]

    def grow(self, level: int, n_points: int) -> None:
        """Points ``N_ℓ … n_points − 1`` of every scrambling of level ``level`` (contiguous paths, module)."""
        while len(self.points) <= level:
            self.points.append(0)
            self.sums.append([])
        r = self.replicates
        if n_points * r > KEY_PATHS:
            raise ValueError(
                f"level {level}: {n_points} points × {r} scramblings exceed the {KEY_PATHS} paths a run indexes; "
                "raise rmse."
            )
        solved = [(self.system, self.y0)]
        if self.control is not None:  # the control on the same points: its solves' sums follow the system's
            solved.append((self.control.system, self.control.start))
        h = self.h0 / 2**level
        dts = (h, 2 * h) if level else (h,)
        for index, (system, y0) in enumerate(solved):
            driven = eqx.tree_at(lambda s: s.noise, system, self.driver(level))
            first = self.points[level] * r
            while first < n_points * r:
                size = min(n_points * r - first, RUN_LIMIT)
                paths, tangents = coupled_paths(
                    driven,
                    y0,
                    fold_key(self.key, level),
                    self.run,
                    dts=dts,
                    brownian_dt=h,
                    n_paths=size,
                    first_path=first,
                    antithetic=self.antithetic,
                    wrt=self.wrt,
                )
                for a, sums in enumerate(self._reduced(paths, tangents, len(dts))):
                    slot = index * len(dts) + a
                    if slot < len(self.sums[level]):
                        totals = self.sums[level][slot]
                        self.sums[level][slot] = [total + part for total, part in zip(totals, sums, strict=True)]
                    else:
                        self.sums[level].append(sums)
                first += size
        self.points[level] = n_points

    def _reduced(self, paths, tangents, n_dts: int) -> list[list[Any]]:
        """Per solve step of ``coupled_paths``' sets, the per-scrambling sums of the values and of their outer
        products (with ``wrt``, of their tangents), a point's value the average over it and its reflection."""
        r, pairs = self.replicates, 2 if self.antithetic else 1
        xp = array_module(paths, tangents)
        host = (lambda x: np.asarray(x, np.float64)) if xp is np else (lambda x: x)
        out = []
        for a in range(n_dts):
            sums = None
            for i in range(a, len(paths), n_dts):  # the solve at dts[a], then its reflection's
                # path (b·R + r)·BLOCK + lane is point b·BLOCK + lane of scrambling r
                z = host(paths[i]).reshape(-1, r, BLOCK, *paths[i].shape[1:])
                parts = [z.sum(axis=(0, 2)) / pairs, xp.einsum("brlni,brlnj->rnij", z, z) / pairs]
                if self.wrt:
                    t = host(tangents[i]).reshape(len(self.wrt), *z.shape)
                    tz = xp.einsum("pbrlni,brlnj->prnij", t, z) / pairs
                    parts += [t.sum(axis=(1, 3)) / pairs, tz + xp.swapaxes(tz, -1, -2)]
                sums = parts if sums is None else [x + y for x, y in zip(sums, parts, strict=True)]
            assert sums is not None
            out.append(sums)
        return out

    def _weights(self, level: int):
        """``(mean weights, cov weights)`` of the level's solves: ``w`` on the system's, ``−β w`` on the
        control's."""
        w = [1.0, -1.0] if level else [1.0]
        if self.control is None:
            return w, w
        beta_m, beta_c = self.coefficients()
        return w + [-beta_m * x for x in w], w + [-beta_c * x for x in w]

    def _per_replicate(self, level: int, weights, cov_weights):
        """The level's solves' per-scrambling means and second moments, and the per-scrambling estimates of its
        term's mean and covariance."""
        n = self.points[level]
        per_solve = [[total / n for total in sums] for sums in self.sums[level]]
        xp = array_module(per_solve)
        means, seconds = ([p[i] for p in per_solve] for i in (0, 1))
        per_mean = sum(w * m for w, m in zip(weights, means))
        per_cov = sum(w * (s - xp.einsum("rni,rnj->rnij", m, m)) for w, m, s in zip(cov_weights, means, seconds))
        return per_solve, per_mean, per_cov

    def coefficients(self):
        """``(β_mean, β_cov)`` of the control, fitted on level 0's scramblings (the per-scrambling estimates of the
        system's and the control's term, :func:`._control_variate.fitted_controls`' ``β``) and used on every level."""
        assert self.control is not None
        if self._fitted is None or self._fitted[0] != self.points[0]:
            _, y_mean, y_cov = self._per_replicate(0, [1.0, 0.0], [1.0, 0.0])
            _, c_mean, c_cov = self._per_replicate(0, [0.0, 1.0], [0.0, 1.0])
            self._fitted = (self.points[0], (_slope(y_mean, c_mean), _slope(y_cov, c_cov)))
        return self._fitted[1]

    def moments(self, level: int):
        """``(mean, cov, mean_var, cov_var)`` of the level's term (the variances those of the estimates); with
        ``wrt``, then ``(d_mean, d_cov, d_mean_var, d_cov_var)``, the derivatives by the jvp of
        :func:`._qmc.combine_replicates` and their variances from the scramblings' spread.  With the control, the
        term of ``Y − βC`` and, on level 0, ``β E C`` added (its variance over ``R − 2`` degrees of freedom: β is
        fitted there)."""
        r = self.replicates
        weights, cov_weights = self._weights(level)
        per_solve, per_mean, per_cov = self._per_replicate(level, weights, cov_weights)
        xp = array_module(per_solve, weights, cov_weights)
        combined = [combine_replicates(_host(p[0]), _host(p[1])) for p in per_solve]
        mean = sum(w * c[0] for w, c in zip(weights, combined))
        cov = sum(w * c[1] for w, c in zip(cov_weights, combined))
        dof = r - 2 if self.control is not None and level == 0 else r - 1
        out = [mean, cov, xp.var(per_mean, axis=0, ddof=1) * (r - 1) / dof / r]
        out.append(xp.var(per_cov, axis=0, ddof=1) * (r - 1) / dof / r)
        exact = self._exact() if self.control is not None and level == 0 else None
        if exact is not None:
            (_, exact_mean, exact_cov), _ = exact
            beta_m, beta_c = self.coefficients()
            out[0], out[1] = mean + beta_m * exact_mean, cov + beta_c * exact_cov
        if self.wrt:
            d_mean = d_cov = d_per_mean = d_per_cov = 0.0
            for w, cw, (m, s, dm, ds) in zip(weights, cov_weights, per_solve):
                dm_c, dc_c = jax.vmap(lambda a, b, m=m, s=s: jax.jvp(combine_replicates, (m, s), (a, b))[1])(dm, ds)
                d_outer = xp.einsum("prni,rnj->prnij", dm, m)
                d_mean = d_mean + w * xp.asarray(dm_c)
                d_cov = d_cov + cw * xp.asarray(dc_c)
                d_per_mean = d_per_mean + w * dm
                d_per_cov = d_per_cov + cw * (ds - d_outer - xp.swapaxes(d_outer, -1, -2))
            if exact is not None:
                assert exact[1] is not None  # with wrt
                _, d_exact_mean, d_exact_cov = exact[1]
                beta_m, beta_c = self.coefficients()
                d_mean, d_cov = d_mean + beta_m * d_exact_mean, d_cov + beta_c * d_exact_cov
            d_vars = [xp.var(d, axis=1, ddof=1) * (r - 1) / dof / r for d in (d_per_mean, d_per_cov)]
            out += [d_mean, d_cov, *d_vars]
        return tuple(out)

    def _exact(self):
        """The control's exact moments and their tangents in ``wrt`` (computed once)."""
        assert self.control is not None
        if self._exact_moments is None:
            run = self.run
            on_host = array_module(self.sums) is np
            self._exact_moments = self.control.exact(
                self.system, self.names, run.t0, run.t1, self.steps0, self.n_save, self.wrt, on_host
            )
        return self._exact_moments


def _slope(y, c):
    """Per entry, the least-squares ``β = Cov_r(y, c)/Var_r(c)`` over the scramblings (1 where ``c`` does not vary:
    the control's module)."""
    xp = array_module(y, c)
    yc, cc = y - y.mean(axis=0), c - c.mean(axis=0)
    var = xp.sum(cc * cc, axis=0)
    return xp.where(var > 0, xp.sum(yc * cc, axis=0) / xp.where(var > 0, var, 1.0), 1.0)


def _checked_run(
    who: str,
    system: StochasticSystem,
    run: RunOptions | None,
    *,
    dt,
    steps,
    t0,
    t1,
    solver,
    save,
    batching,
    replicates,
    antithetic,
    control,
    wrt,
) -> tuple[RunOptions, tuple[str, ...], int]:
    """The checks both quasi-Monte Carlo entry points make: the run options (``(t1 − t0)/dt`` a power of two whose
    steps × channels fit the direction numbers), a Wiener driver, a solver the Sobol' driver gives increments to,
    ``wrt``, ``replicates`` (≥ 2, ≥ 3 with a control) and ``antithetic``; returns ``(run, wrt, replicates)``."""
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    run = run_options(who, run, t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, batching=batching)
    h0, steps0 = run.dt, run.n_steps
    if steps0 & (steps0 - 1):
        raise ValueError(
            f"dt={h0}: (t1 − t0)/dt = {steps0} base steps; quasi-Monte Carlo needs a power of two such as "
            f"{1 << (steps0.bit_length() - 1)} or {1 << steps0.bit_length()} (the Brownian bridge's grid)."
        )
    if not system.noise.continuous:
        raise ValueError(
            f"system.noise={type(system.noise).__name__} has jumps; quasi-Monte Carlo needs a Wiener driver "
            "(nhsde.noise.Wiener)."
        )
    check_solver(run.solver, system)  # (a three-point weak2 is refused here: its increments are not the driver's)
    m = system.noise_dim
    if steps0 * m > MAX_DIMENSION:
        raise ValueError(
            f"dt={h0}, t1={run.t1}: {steps0} steps × {m} channels = {steps0 * m} Sobol' dimensions, beyond the "
            f"{MAX_DIMENSION} of the direction numbers; take a larger dt or a shorter t1 − t0."
        )
    replicates = check_number("replicates", replicates, integer=True)
    if replicates < (2 if control is None else 3):
        raise ValueError(
            f"replicates={replicates}; the standard errors need ≥ 2 independent scramblings, ≥ 3 with control=… "
            "(β is fitted on them)."
        )
    if not isinstance(antithetic, bool):
        raise TypeError(f"antithetic={antithetic!r}; expected True or False.")
    return run, () if wrt is None else check_wrt(system, wrt), replicates


def multilevel_quasi_monte_carlo(
    system: StochasticSystem,
    y0,
    key,
    *,
    statistic,
    t1: float | None = None,
    dt: float | None = None,
    steps: FixedSteps | None = None,
    rmse: float | None = None,
    n_points: Sequence[int] | None = None,
    t0: float | None = None,
    solver: str | dfx.AbstractSolver | None = None,
    save: Save | None = None,
    run: RunOptions | None = None,
    weak_order: float | None = None,
    replicates: int = 16,
    max_levels: int = MAX_LEVELS,
    antithetic: bool = False,
    control=None,
    batching: Batching | None = None,
    wrt: Sequence[str] | None = None,
) -> MultilevelEstimate:
    """Multilevel randomised quasi-Monte Carlo estimate of the saved means and covariances (module).

    Arguments as :func:`~nhsde.statistics.multilevel_monte_carlo` (``statistic`` included), and:

    - ``dt`` (or ``steps=FixedSteps(h₀)``): the coarsest step ``h₀``, with ``(t1 − t0)/h₀`` a power of two (the
      bridge's grid).
    - ``rmse``: the requested root-mean-square error of ``statistic`` (levels and points chosen adaptively), or
      ``n_points``: a fixed ``(N_0, …, N_L)`` points per scrambling, powers of two ≥ 64.
    - ``replicates``: ``R``, the independent scramblings per level (≥ 2; the variances come from their spread).
    - ``antithetic``: each point also solved with its increments reflected (``W → −W``), its value the pair's
      average (:mod:`._variance_reduction`; twice the path-steps, ``level_costs`` doubled).
    - ``control``: ``'mean'`` or a state ``(d,)``: the linearised system solved on the same points as a control
      variate, as in :func:`~nhsde.statistics.multilevel_monte_carlo` (``y0`` one state); ``β`` per saved entry
      fitted on level 0's scramblings (least squares over their estimates; that level's variance then over
      ``R − 2`` degrees of freedom) and used on every level, ``coefficient`` holds it; twice the path-steps.
    - ``wrt``: names of scalar parameters: ``derivatives`` of the means and covariances in them, from the points'
      forward-mode tangents reduced per scrambling like the values (each level's term by the jvp of its
      replicate combination), with standard errors from the scramblings' spread, the levels' variances added.

    Only Wiener drivers, and solvers that need Brownian increments only (Euler, Milstein, Heun, …) or
    ``nhsde.PlatenWeak2(increments='gaussian')``; levels stop
    where ``(t1 − t0)/h_ℓ × channels`` would exceed the 21201 dimensions of the direction numbers.
    ``n_paths_per_level`` counts ``N_ℓ R`` samples, ``level_variances`` are ``V̂_ℓ N_ℓ R`` (per sample, as
    :class:`MultilevelEstimate`'s) and ``level_costs`` path-steps per sample (the QMC driver's path-step costs
    more time than the Wiener driver's).
    """
    watch = Stopwatch()
    if (rmse is None) == (n_points is None):
        raise TypeError(
            "multilevel_quasi_monte_carlo needs exactly one of rmse=… (adaptive) or n_points=(N_0, …, N_L)."
        )
    run, wrt, replicates = _checked_run(
        "multilevel_quasi_monte_carlo",
        system,
        run,
        save=save,
        dt=dt,
        steps=steps,
        t0=t0,
        t1=t1,
        solver=solver,
        batching=batching,
        replicates=replicates,
        antithetic=antithetic,
        control=control,
        wrt=wrt,
    )
    h0, steps0, m = run.dt, run.n_steps, system.noise_dim
    if weak_order is None:
        alpha = 2 if isinstance(run.solver, PlatenWeak2) else 1
    else:
        alpha = check_number("weak_order", weak_order, positive=True)
    max_levels = check_number("max_levels", max_levels, integer=True)
    if max_levels < (1 if rmse is None else 2):
        raise ValueError(
            f"max_levels={max_levels}; must be ≥ 1, and ≥ 2 with rmse=… (the bias estimate compares two levels)."
        )
    by_dimension = (MAX_DIMENSION // (steps0 * m)).bit_length()  # levels whose grid fits the direction numbers
    top = min(max_levels, by_dimension)
    if rmse is not None and top < 2:
        raise ValueError(
            f"dt={h0}: the second level's {2 * steps0} steps × {m} channels exceed the {MAX_DIMENSION} Sobol' "
            "dimensions, and rmse=… needs two levels; take a larger dt or a shorter t1 − t0."
        )
    statistic = as_statistic(statistic)
    save = paths_save(run.save, steps0, statistic.names)
    assert save.names is not None
    statistic.check(save.names)
    key = check_key(key)
    linearised = None
    if control is not None:
        linearised = LinearisedControl(system, system.state(y0, "y0"), control, save.names, "control")
    counts: list[int] = []  # the points per level, where given
    if n_points is not None:
        if not isinstance(n_points, Sequence) or isinstance(n_points, str):
            raise TypeError(f"n_points={n_points!r}; expected one count per level, (N_0, …, N_L).")
        counts = [check_number("n_points", n, integer=True) for n in n_points]
        if not counts or any(n < BLOCK or n & (n - 1) for n in counts):
            raise ValueError(
                f"n_points={n_points!r}; expected one power of two ≥ {BLOCK} per level (the points of a "
                "scrambling form a net)."
            )
        if len(counts) > by_dimension:
            raise ValueError(
                f"n_points={n_points!r}: {len(counts)} levels, but only {by_dimension} fit the {MAX_DIMENSION} "
                f"Sobol' dimensions at dt={h0} with {m} channels."
            )
        top = len(counts)
    dimension = (steps0 << (top - 1)) * m
    levels = _QmcLevels(
        system,
        y0,
        key,
        dataclasses.replace(run, save=save),
        replicates=replicates,
        dimension=dimension,
        wrt=wrt,
        antithetic=antithetic,
        control=linearised,
    )
    if n_points is not None:
        for level, n in enumerate(counts):
            levels.grow(level, n)
        moments = [levels.moments(level) for level in range(len(counts))]
    else:
        eps = check_number("rmse", rmse, positive=True)
        if not is_concrete(system, y0):
            raise TypeError("rmse=…: choosing the levels needs concrete parameters, not traced ones.")
        moments = _adapt(levels, eps, alpha, top, max_levels, statistic, save.names)

    return _estimate(levels, moments, statistic, alpha, watch)


def quasi_monte_carlo(
    system: StochasticSystem,
    y0,
    key,
    *,
    n_paths: int,
    t1: float | None = None,
    dt: float | None = None,
    steps: FixedSteps | None = None,
    replicates: int = 16,
    t0: float | None = None,
    solver: str | dfx.AbstractSolver | None = None,
    save: Save | None = None,
    run: RunOptions | None = None,
    antithetic: bool = False,
    batching: Batching | None = None,
    wrt: Sequence[str] | None = None,
) -> QuasiMonteCarloEstimate:
    """Means and covariances of the saved quantities by randomised quasi-Monte Carlo (module).

    The one level of :func:`multilevel_quasi_monte_carlo` at ``dt``: ``replicates × n_paths`` paths in the runs
    of one compiled solve, the system's Wiener driver replaced by ``replicates`` independently scrambled Sobol'
    point sets (keys ``fold_in(fold_in(key, 0), r)``) through a Brownian bridge, ``n_paths`` paths each; the
    per-replicate moments are reduced from the paths on the host in float64.  The same key gives bitwise the same
    result, whatever the batching.  Every path has the law of a Monte-Carlo path, so the estimate is unbiased for
    the scheme's expectation at ``dt``: ``mean = avg_r m_r``, ``cov = avg_r S_r − mean meanᵀ − Ĉov(mean)`` with ``S_r``
    replicate ``r``'s second moment and ``Ĉov(mean)`` the replicate spread over ``R``. Paths within a replicate are
    dependent, so per-path standard errors would be wrong: the errors are the standard deviations over the independent
    replicates divided by ``√R`` (``R ≥ 8`` gives usable errors).

    The gain needs a statistic smooth in the path ``W`` (moments of a smooth flow are; indicators and
    maxima gain little), and falls with the dimension ``(t1 − t0)/dt × noise channels``.  Measured against
    Monte Carlo at the same paths, scheme and step: on the ball (Euler, 16 steps, 4096 paths × 16
    replicates) the covariances' standard errors 24–49× smaller (variance ÷700–2400) at ~7× the time per
    path; the host prototype (``benchmarks/qmc.py``, 16384 paths) variance ÷120–3400 on the ball, the sleigh
    and the body on the vibrating plane, ÷4–7 on Chaplygin's ball.

    Arguments as :func:`~nhsde.simulate` (the step ``dt=h`` or ``steps=FixedSteps(h)``); ``n_paths`` per replicate,
    a power of two ≥ 64 (the Sobol' points ``0 … n_paths − 1`` form a net); ``(t1 − t0)/dt`` a power of two with
    ``(t1 − t0)/dt × channels ≤ 21201``; ``solver`` one of :func:`._qmc.allowed_solvers`: one that needs Brownian
    increments only (not Lévy area), or ``nhsde.PlatenWeak2(increments='gaussian')`` (weak order 2), whose ``ΔW``
    come from the points and two-point ``V`` pseudo-random from the run's key ``fold_in(key, 0)``; ``antithetic``: every
    point also solved with its increments reflected (``W → −W``, the point set ``1 − u``), its value the pair's
    average and its second moment the average of the two paths' (twice the path-steps; it gains where the statistic
    has a part odd in ``W``, :mod:`._variance_reduction`); ``wrt``: names of scalar parameters: ``derivatives`` of
    the moments in them (forward mode), with errors from the replicate spread.  Under ``jax.jit``, ``jax.grad`` and
    ``jax.vmap`` (over parameters or keys) it runs as plain Monte Carlo does (module).
    """
    watch = Stopwatch()
    run, wrt, replicates = _checked_run(
        "quasi_monte_carlo",
        system,
        run,
        save=save,
        dt=dt,
        steps=steps,
        t0=t0,
        t1=t1,
        solver=solver,
        batching=batching,
        replicates=replicates,
        antithetic=antithetic,
        control=None,
        wrt=wrt,
    )
    n_paths = check_number("n_paths", n_paths, integer=True)
    if n_paths < BLOCK or n_paths & (n_paths - 1) or n_paths * replicates > KEY_PATHS:
        raise ValueError(
            f"replicates={replicates}, n_paths={n_paths}: quasi-Monte Carlo needs n_paths a power of two ≥ {BLOCK} "
            f"(the Sobol' points of a scrambling form a net), and at most {KEY_PATHS} paths in all."
        )
    key = check_key(key)
    save = paths_save(Save() if run.save is None else run.save, run.n_steps, system.layout.names)
    assert save.names is not None and save.n is not None
    system.observe(save.names)  # unknown names raise naming save
    run = dataclasses.replace(run, save=save)
    levels = _QmcLevels(
        system,
        y0,
        key,
        run,
        replicates=replicates,
        dimension=run.n_steps * system.noise_dim,
        wrt=wrt,
        antithetic=antithetic,
    )
    levels.grow(0, n_paths)
    mean, cov, mean_var, cov_var, *tangents = levels.moments(0)
    derivatives = None
    if tangents:
        d_mean, d_cov, d_mean_var, d_cov_var = tangents
        derivatives = Derivatives(d_mean, d_cov, safe_sqrt(d_mean_var), safe_sqrt(d_cov_var), wrt)
    estimate = QuasiMonteCarloEstimate(
        ts=np.linspace(run.t0, run.t1, save.n),
        mean=mean,
        cov=cov,
        mean_se=safe_sqrt(mean_var),
        cov_se=safe_sqrt(cov_var),
        n_paths=jax.device_put(np.asarray(replicates * n_paths)),
        names=save.names,
        roles=roles_of(system, save.names),
        replicates=replicates,
        derivatives=derivatives,
        cost=watch.cost(replicates * n_paths * levels.cost(0)),
        statistic=None,
    )
    return on_device(estimate, jnp.asarray(y0).dtype)


def _adapt(
    levels: _QmcLevels, eps: float, alpha: float, top: int, max_levels: int, statistic: AbstractStatistic, names
):
    """Giles & Waterhouse (2009), §3: double the points where ``V̂_ℓ/(N_ℓ C_ℓ)`` is largest until ``Σ V̂_ℓ ≤ ε²/2``,
    add levels until the bias estimate is ``≤ ε/√2``; returns the moments of each level."""
    n_levels = min(3, top)
    for level in range(n_levels):
        levels.grow(level, BLOCK)
    moments = [levels.moments(level) for level in range(n_levels)]
    while True:
        _double(levels, moments, eps**2 / 2, None, statistic, names)
        means = np.stack([_pick(statistic, names, mm[0], mm[1]) for mm in moments])
        bias = float(bias_estimate(means, alpha))
        if bias <= eps / math.sqrt(2):
            return moments
        if n_levels >= top:
            limit = (
                f"max_levels={max_levels}: {top} levels"
                if top == max_levels
                else f"dt={levels.h0}: {top} levels fill the {MAX_DIMENSION} Sobol' dimensions, and after them"
            )
            raise ValueError(
                f"{limit} the bias estimate {bias:.3g} is still above rmse/√2 = {eps / math.sqrt(2):.3g}; raise "
                f"max_levels or rmse, or check weak_order={alpha}."
            )
        levels.grow(n_levels, BLOCK)
        moments.append(levels.moments(n_levels))
        n_levels += 1


def _double(levels: _QmcLevels, moments: list, variance: float, most: Sequence[int] | None, statistic, names) -> None:
    """Double the points of the level with the largest ``V̂_ℓ/(N_ℓ C_ℓ)`` (among those below ``most``, points per
    scrambling per level) until ``Σ_ℓ V̂_ℓ ≤ variance``; ``moments`` (one per level) updated in place."""
    n_levels = len(moments)
    variances = [float(_pick(statistic, names, mm[2], mm[3])) for mm in moments]
    while sum(variances) > variance:
        open_levels = [ell for ell in range(n_levels) if most is None or levels.points[ell] < most[ell]]
        if not open_levels:
            return
        worst = max(open_levels, key=lambda ell: variances[ell] / (levels.points[ell] * levels.cost(ell)))
        levels.grow(worst, 2 * levels.points[worst])
        for ell in range(n_levels) if worst == 0 and levels.control is not None else (worst,):  # β refitted
            moments[ell] = levels.moments(ell)
            variances[ell] = float(_pick(statistic, names, moments[ell][2], moments[ell][3]))


def _estimate(levels: _QmcLevels, moments, statistic: AbstractStatistic, alpha: float, watch: Stopwatch):
    """The :class:`MultilevelEstimate` of the levels' ``moments`` (their sum telescopes to the finest level)."""
    n_levels = len(moments)
    samples = [levels.points[level] * levels.replicates for level in range(n_levels)]
    xp = array_module(moments)
    mean, cov, mean_var, cov_var, *tangents = (xp.sum(xp.stack(parts), axis=0) for parts in zip(*moments, strict=True))
    derivatives = None
    if tangents:  # the levels are independent: their derivatives' variances add
        d_mean, d_cov, d_mean_var, d_cov_var = tangents
        derivatives = Derivatives(d_mean, d_cov, safe_sqrt(d_mean_var), safe_sqrt(d_cov_var), levels.wrt)
    names = levels.names
    level_means = xp.stack([_pick(statistic, names, mm[0], mm[1]) for mm in moments])
    level_vars = xp.stack([_pick(statistic, names, mm[2], mm[3]) * n for mm, n in zip(moments, samples)])
    level_costs = tuple(levels.cost(level) for level in range(n_levels))
    fields: dict[str, Any] = dict(
        ts=np.linspace(levels.run.t0, levels.run.t1, mean.shape[0]),
        mean=mean,
        cov=cov,
        mean_se=safe_sqrt(mean_var),
        cov_se=safe_sqrt(cov_var),
        n_paths=jax.device_put(np.asarray(sum(samples))),
        names=names,
        roles=roles_of(levels.system, names),
        level_means=level_means,
        level_variances=level_vars,
        bias=bias_estimate(level_means, alpha),
        n_paths_per_level=tuple(samples),
        level_costs=level_costs,
        dt=levels.h0,
        derivatives=derivatives,
        cost=watch.cost(sum(n * c for n, c in zip(samples, level_costs))),
        statistic=statistic,
        coefficient=None if levels.control is None else PerEntry(*levels.coefficients()),
    )
    return on_device(MultilevelEstimate(**fields), jnp.asarray(levels.y0).dtype)


def quasi_monte_carlo_to_variance(
    system: StochasticSystem,
    y0,
    key,
    run: RunOptions,
    *,
    statistic: AbstractStatistic,
    variance: float,
    max_points: Sequence[int],
    dimension: int,
    replicates: int = 16,
    wrt: tuple[str, ...] = (),
    antithetic: bool = False,
    control=None,
) -> MultilevelEstimate:
    """Randomised quasi-Monte Carlo with the options ``run`` on the levels ``h = dt … dt 2^{1−L}`` of the module
    (``dt`` its step), ``L = len(max_points)`` (one level: plain quasi-Monte Carlo at ``dt``): 64 points per
    scrambling on every level, then the points of the level with the most variance per unit of work doubled until
    the squared standard error of ``statistic`` is at most ``variance``, or every level ``ℓ`` has ``max_points[ℓ]``
    (powers of two).  Every point count runs in the compiled programs of the driver's ``dimension`` (≥ the finest
    level's ``(t1 − t0)/h × channels``; ``run.save`` keeps the per-path values); ``bias`` is the levels' estimate
    (``nan`` for one level); with parameter names ``wrt``, ``derivatives`` from the points' tangents;
    ``antithetic``: each point with its reflection, ``control``: the linearised system as a control variate (as
    :func:`multilevel_quasi_monte_carlo`).  For the estimators' own checked arguments: a run that stops where it is
    accurate enough, unlike counts fixed in advance at the Monte-Carlo rate, on levels fixed in advance (their bias
    bounded by the estimator's pilot)."""
    watch = Stopwatch()
    save = run.save
    assert save is not None and save.names is not None and save.paths
    names = save.names
    levels = _QmcLevels(
        system,
        y0,
        key,
        run,
        replicates=replicates,
        dimension=dimension,
        wrt=wrt,
        antithetic=antithetic,
        control=None if control is None else LinearisedControl(system, y0, control, names, "control"),
    )
    for level, most in enumerate(max_points):
        levels.grow(level, min(BLOCK, most))
    moments = [levels.moments(level) for level in range(len(max_points))]
    _double(levels, moments, variance, max_points, statistic, save.names)
    return _estimate(levels, moments, statistic, 2.0 if isinstance(run.solver, PlatenWeak2) else 1.0, watch)
