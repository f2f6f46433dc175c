"""Richardson–Romberg (Talay–Tubaro) extrapolation of saved statistics.

A scheme of weak order ``p`` has ``E f(X_h) = E f(X) + C h^p + O(h^{p+1})``
(Talay & Tubaro, Stoch. Anal. Appl. 8 (1990), for Euler, ``p = 1``; Kloeden &
Platen 1992, §15.3, for higher orders), so

    S_ex = (2^p S(h/2) − S(h)) / (2^p − 1)

has bias ``O(h^{p+1})``; for Euler–Maruyama ``S_ex = 2 S(h/2) − S(h)``.  Both
solves run on one Brownian path (``FixedSteps(h, brownian_dt=h/2)`` and
``FixedSteps(h/2, brownian_dt=h/2)`` with one key), so ``S(h/2)`` and ``S(h)`` are
strongly correlated and the Monte-Carlo error of ``S_ex`` is that of the paired
per-path combination, not of two independent runs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float, Int

from .._ensemble import Save
from .._misc import check_number
from .._options import Batching, FixedSteps, RunOptions, run_options
from .._solvers import solver_needs
from .._system import StochasticSystem
from .._weak import PlatenWeak2
from ._cost import check_memory, path_bytes, peak_bytes
from ._estimate import AbstractEstimate, AbstractStatistic, Cost, Derivatives, MonteCarloEstimate, Stopwatch, Values
from ._paths import (
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

__all__ = ["Extrapolation", "extrapolate"]


class Extrapolation(AbstractEstimate):
    """The extrapolated moments, with ``fine``, the plain moments ``S(h/2)`` of the same paths, and
    ``correction = S_ex − S(h/2)`` with its paired standard error: ``−correction`` estimates the bias of ``S(h/2)``,
    ``−2^p·correction`` that of ``S(h)``; ``derivatives`` of the extrapolated moments when asked for (``wrt``);
    ``cost`` both solves' path-steps (of the reflected paths too, with ``antithetic``)."""

    ts: Float[Values, " n"]
    mean: Float[Values, "n k"]
    cov: Float[Values, "n k k"]
    mean_se: Float[Values, "n k"]
    cov_se: Float[Values, "n k k"]
    n_paths: Int[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    fine: MonteCarloEstimate
    correction: MonteCarloEstimate
    derivatives: Derivatives | None
    cost: Cost = eqx.field(static=True)
    statistic: AbstractStatistic | None = eqx.field(static=True)


def extrapolate(
    system: StochasticSystem,
    y0,
    key,
    *,
    n_paths: int,
    t1: float | None = None,
    dt: float | None = None,
    steps: FixedSteps | None = None,
    t0: float | None = None,
    solver: str | dfx.AbstractSolver | None = None,
    order: int | None = None,
    save: Save | None = None,
    antithetic: bool = False,
    batching: Batching | None = None,
    run: RunOptions | None = None,
    wrt: Sequence[str] | None = None,
) -> Extrapolation:
    """Richardson–Romberg extrapolation ``(2^p S(h/2) − S(h))/(2^p − 1)`` of every saved mean and covariance.

    Arguments as :func:`~nhsde.simulate` (``run=`` or its keywords), with ``dt = h`` (or ``steps=FixedSteps(h)``) the
    coarse step (``h/2`` must divide ``t1 − t0``).  ``order``: the weak order ``p`` of ``solver``
    (default 2 for :class:`~nhsde.PlatenWeak2`, else 1; pass 2 for Heun or SRA1
    on additive noise, where they are weak order 2).  ``save`` defaults to the
    whole state at ``t0`` and ``t1``.  ``antithetic`` adds the reflected paths.
    The standard errors are those of the paired per-path combination (module).
    ``wrt``: names of scalar parameters (``('eps', 'nu')``): ``derivatives`` of the extrapolated
    moments in them, with standard errors (per-path tangents).
    """
    watch = Stopwatch()
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    wrt = () if wrt is None else check_wrt(system, wrt)
    run = run_options("extrapolate", run, t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, batching=batching)
    solver_needs(coupling_solver(run.solver), system)
    if order is None:
        order = 2 if isinstance(run.solver, PlatenWeak2) else 1
    p = check_number("order", order, positive=True)
    h, n_steps = run.dt, run.n_steps
    save = paths_save(run.save, n_steps, system.layout.names)
    assert save.names is not None and save.n is not None
    (n_paths,) = checked_paths("n_paths", n_paths)
    solves = 4 if antithetic else 2
    check_memory(
        f"n_paths={n_paths}",
        peak_bytes(solves * n_paths * path_bytes(save.n, len(save.names), len(wrt))),
        "take fewer paths, or average runs of several keys.",
    )
    paths, tangents = coupled_paths(
        system,
        y0,
        key,
        dataclasses.replace(run, save=save),
        dts=(h, h / 2),
        brownian_dt=h / 2,
        n_paths=n_paths,
        antithetic=bool(antithetic),
        wrt=wrt,
    )
    share = 0.5 if antithetic else 1.0

    names, c = save.names, 1 / (2**p - 1)
    count = jax.device_put(np.asarray(n_paths))
    common = dict(
        ts=np.linspace(run.t0, run.t1, save.n),
        n_paths=count,
        names=names,
        roles=roles_of(system, names),
        statistic=None,
    )

    def moments(coarse, fine) -> dict[str, Any]:
        weights = [share * coarse, share * fine] * (len(paths) // 2)
        mean, cov, mean_var, cov_var = paired_moments(paths, weights)
        return dict(mean=mean, cov=cov, mean_se=safe_sqrt(mean_var), cov_se=safe_sqrt(cov_var), **common)

    derivatives = None
    if wrt:
        d_mean, d_cov, d_mean_var, d_cov_var = paired_sensitivities(
            paths, tangents, [share * -c, share * (1 + c)] * (len(paths) // 2)
        )
        derivatives = Derivatives(d_mean, d_cov, safe_sqrt(d_mean_var), safe_sqrt(d_cov_var), wrt)
    path_steps = n_paths * (n_steps + 2 * n_steps) * (2 if antithetic else 1)
    result = Extrapolation(
        **moments(-c, 1 + c),
        fine=MonteCarloEstimate(**moments(0.0, 1.0), derivatives=None, cost=Cost(path_steps * 2 / 3)),
        correction=MonteCarloEstimate(**moments(-c, c), derivatives=None, cost=Cost(path_steps)),
        derivatives=derivatives,
        cost=watch.cost(path_steps),
    )
    return on_device(result, paths[0].dtype)
