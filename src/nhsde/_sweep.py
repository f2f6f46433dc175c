"""Parameter sweeps: :func:`sweep` runs :func:`~nhsde.simulate` at every point of a grid of parameters.

The grid's points run in batches under one compiled program (``lax.map``; the
last batch padded with its last point), every point with the same key, so a
point's moments are bitwise those of ``simulate`` called there alone.  With ``wrt``
the pathwise derivatives of the moments and their standard errors come from
:func:`~nhsde.statistics.moment_sensitivities` on the same paths.  Each point's
parameters are checked before anything runs, as ``simulate`` checks them (the
stability limit of the solver's step among them), and a failing point — an
unstable step, failed paths — is named by its parameters.
"""

from __future__ import annotations

import itertools
import json
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import xarray as xr

from ._ensemble import FAILURE_CAUSES, SimulationError
from ._misc import check_key, is_concrete
from ._options import RunOptions, run_options
from ._simulate import MIN_PATHS, simulate
from ._system import StochasticSystem
from .scenes import AbstractScene
from .statistics import moment_sensitivities
from .statistics._estimate import as_statistic
from .statistics._sensitivities import check_wrt

__all__ = ["sweep"]


def _point_text(names: Sequence[str], values) -> str:
    return ", ".join(f"{n}={float(v):g}" for n, v in zip(names, values))


@eqx.filter_jit
def _batch(system: StochasticSystem, names: tuple[str, ...], values, wrt: tuple[str, ...], y0, key, options: dict):
    """Moments, failure counts and (with ``wrt``) derivatives of a batch of points ``values (B, g)``.

    ``lax.map``: the points run one after another in one program, each exactly as ``simulate`` alone runs it
    (``vmap`` would batch the moment sums' reductions, whose rounding then differs from ``simulate``'s).
    """

    def point(theta):
        at = system.replace_params(**dict(zip(names, theta)))
        if not wrt:
            ens = simulate(at, y0, key, on_failure="exclude", **options)
            return ens.ts, (ens.mean, ens.cov, ens.mean_se, ens.cov_se), ens.n_used, ens.n_failed, ()
        sens = moment_sensitivities(at, y0, key, wrt=wrt, on_failure="exclude", **options)
        ens = sens.ensemble
        derivatives = (sens.d_mean, sens.d_cov, sens.d_mean_se, sens.d_cov_se)
        return ens.ts, (ens.mean, ens.cov, ens.mean_se, ens.cov_se), sens.n_used, sens.n_failed, derivatives

    return jax.lax.map(point, values)


def _name_the_failure(system, names, points, wrt, y0, key, options):
    """A batch failed inside its program (a run-time check): run its points plainly until one raises, and raise
    that error naming the point."""
    for theta in points:
        at = system.replace_params(**dict(zip(names, theta.tolist())))
        try:
            if wrt:
                moment_sensitivities(at, y0, key, wrt=wrt, on_failure="exclude", **options)
            else:
                simulate(at, y0, key, on_failure="exclude", **options)
        except SimulationError as e:
            raise SimulationError(f"sweep: at {_point_text(names, theta)}: {e}") from None


def sweep(
    scene: AbstractScene | StochasticSystem,
    grid: Mapping[str, Sequence[float]],
    *,
    key,
    n_paths: int,
    t1: float | None = None,
    statistic=None,
    wrt: Sequence[str] | None = None,
    y0=None,
    dt: float | None = None,
    t0: float | None = None,
    solver: Any = None,
    steps=None,
    save=None,
    run: RunOptions | None = None,
    batch: int | None = None,
    on_failure: str = "raise",
    on_batch: Callable[[int, int], None] | None = None,
) -> xr.Dataset:
    """Simulate ``scene`` at every point of the parameter ``grid``; the moments, their derivatives and errors.

    Arguments:
        scene: a scene (its :meth:`build` and, by default, its ``initial_state()``) or a
            :class:`~nhsde.StochasticSystem` (then ``y0`` is needed).
        grid: parameter name → values, e.g. ``{"eps": [0.5, 1, 2], "nu": [0.5, 1]}``: the grid is their
            Cartesian product, a dimension of the result per name, in this order.
        key, n_paths, t0, t1, dt, solver, steps, save, run: as for :func:`~nhsde.simulate`, the same at every
            point.
        statistic: ``Mean(a)`` or ``Covariance(a, b)`` (or ``('mean', a)``, ``('cov', a, b)``) at ``t1`` (as for
            :func:`~nhsde.statistics.to_accuracy`): adds ``value``, ``value_se`` and their derivatives over the grid.
        wrt: parameters to differentiate in (default the grid's; ``()`` for none), pathwise, with standard errors.
        y0: the initial state (default the scene's).
        batch: grid points per compiled call (default: all; ``on_batch`` reports after each).
        on_failure: ``'raise'``: a point with failed paths raises :class:`~nhsde.SimulationError` naming it;
            ``'exclude'``: its failed paths are left out (``n_failed`` counts them).
        on_batch: called as ``on_batch(points_done, points)`` after each batch.

    Returns:
        an ``xarray.Dataset`` with a coordinate per grid parameter and ``time``, ``name``, ``name2``: ``mean``,
        ``cov``, ``mean_se``, ``cov_se``, ``n_used``, ``n_failed``, per ``q`` in ``wrt`` ``d_mean_d_q``,
        ``d_cov_d_q`` and their ``_se``; with ``statistic`` also ``value``, ``value_se``, ``d_value_d_q``,
        ``d_value_d_q_se``.  :func:`nhsde.plot.sweep` draws it.

    Raises:
        ValueError: a bad grid, or a point ``simulate`` would refuse (e.g. a step beyond the solver's stability
            limit), naming the point's parameters.
        SimulationError: a point with failed paths (``on_failure='raise'``) or too few usable ones, named.

    Examples:
        The ball's velocity variance over three frictions, with its derivative in ``eps``:

        >>> import jax
        >>> import nhsde
        >>> scene = nhsde.scenes.BallOnVibratingPlane(drift=False)
        >>> ds = nhsde.sweep(scene, {"eps": [0.5, 1.0, 2.0]}, statistic=("cov", "u_x", "u_x"),
        ...                  key=jax.random.key(0), n_paths=256, t1=2.0, dt=0.02)
        >>> ds["value"].dims, ds["d_value_d_eps"].shape
        (('eps',), (3,))
    """
    run = run_options("sweep", run, t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, adaptive=True)
    if isinstance(scene, AbstractScene):
        system = scene.build()
        y0 = scene.initial_state() if y0 is None else y0
    elif isinstance(scene, StochasticSystem):
        system = scene
        if y0 is None:
            raise TypeError("sweep: y0 is needed with a StochasticSystem (a scene gives its initial state).")
    else:
        raise TypeError(f"scene={type(scene).__name__}; expected a scene or a StochasticSystem.")
    if on_failure not in ("raise", "exclude"):
        raise ValueError(f"on_failure={on_failure!r}; allowed: 'raise', 'exclude'.")
    if not isinstance(grid, Mapping) or not grid:
        raise TypeError(f"grid={grid!r}; expected a dict of parameter names and their values, e.g. {{'eps': [1, 2]}}.")
    for name, value in (("grid", dict(grid)), ("y0", y0), ("the system's parameters", system.params)):
        if not is_concrete(value):
            raise TypeError(
                f"sweep: {name} holds traced values (sweep was called inside jax.jit, jax.grad or jax.vmap). sweep "
                "runs concrete grid points from the host: call it outside the transform and take derivatives with "
                "its wrt=, or transform nhsde.simulate itself."
            )
    names = check_wrt(system, tuple(grid))
    axes = []
    for name in names:
        values = np.asarray(grid[name], np.float64)
        if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
            raise ValueError(f"grid[{name!r}]={grid[name]!r}; expected a non-empty list of finite numbers.")
        axes.append(values)
    wrt = names if wrt is None else (() if not wrt else check_wrt(system, wrt))
    options: dict[str, Any] = dict(n_paths=n_paths, run=run)
    points = np.array(list(itertools.product(*axes)))  # (G, g), the last name fastest

    # every point checked as simulate checks it, before anything runs: the errors and warnings name the point
    warned = []
    shapes = None
    for theta in points:
        at = system.replace_params(**dict(zip(names, theta.tolist())))
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                shapes = jax.eval_shape(lambda at=at: simulate(at, y0, key, **options))
        except ValueError as e:
            raise ValueError(f"sweep: at {_point_text(names, theta)}: {e}") from None
        warned += [(theta, w) for w in caught]
    if warned:
        theta, w = warned[0]
        more = len({tuple(t) for t, _ in warned}) - 1
        others = f" (and at {more} more points)" if more else ""
        warnings.warn(f"sweep: at {_point_text(names, theta)}{others}: {w.message}", w.category, stacklevel=2)
    assert shapes is not None
    saved, roles = shapes.names, shapes.roles
    if statistic is not None:
        statistic = as_statistic(statistic)
        statistic.check(saved)

    batch = len(points) if batch is None else int(batch)
    if batch < 1:
        raise ValueError(f"batch={batch}; must be ≥ 1.")
    results, done = [], 0
    for start in range(0, len(points), batch):
        chunk = points[start : start + batch]
        padded = np.concatenate([chunk, np.repeat(chunk[-1:], batch - len(chunk), axis=0)])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the checks above warned once, naming the points
            try:
                out = jax.block_until_ready(_batch(system, names, jnp.asarray(padded), wrt, y0, key, options))
            except (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError):
                _name_the_failure(system, names, chunk, wrt, y0, key, options)
                raise
        results.append(jax.tree.map(lambda a, n=len(chunk): np.asarray(a[:n]), out))
        done += len(chunk)
        if on_batch is not None:
            on_batch(done, len(points))
    ts, (mean, cov, mean_se, cov_se), n_used, n_failed, derivatives = jax.tree.map(
        lambda *a: np.concatenate(a), *results
    )
    for p, theta in enumerate(points):
        where = f"sweep: at {_point_text(names, theta)}"
        if on_failure == "raise" and n_failed[p] > 0:
            raise SimulationError(
                f"{where}: {int(n_failed[p])} of {n_paths} paths failed ({FAILURE_CAUSES}; or a non-finite tangent); "
                "try a smaller dt, a stiffer-stable solver, float64 states, or on_failure='exclude'."
            )
        if n_used[p] < MIN_PATHS:
            raise SimulationError(f"{where}: only {int(n_used[p])} of {n_paths} paths are usable; need ≥ {MIN_PATHS}.")
        if not all(np.all(np.isfinite(m[p])) for m in (mean, cov, mean_se, cov_se)):
            raise SimulationError(f"{where}: the statistics are not finite (the moment sums overflow).")

    shape = tuple(len(a) for a in axes)
    grid_dims = tuple(names)
    tn, tnn = (*grid_dims, "time", "name"), (*grid_dims, "time", "name", "name2")
    per_point = lambda a: a.reshape(shape + a.shape[1:])
    data: dict[str, Any] = {
        "mean": (tn, per_point(mean), {"long_name": "sample mean over the paths"}),
        "cov": (tnn, per_point(cov), {"long_name": "sample covariance (unbiased) over the paths"}),
        "mean_se": (tn, per_point(mean_se), {"long_name": "Monte-Carlo standard error of mean"}),
        "cov_se": (tnn, per_point(cov_se), {"long_name": "Monte-Carlo standard error of cov"}),
        "n_used": (grid_dims, per_point(n_used.astype(np.int64))),
        "n_failed": (grid_dims, per_point(np.asarray(n_failed, np.int64))),
    }
    if statistic is not None:
        data["value"] = (grid_dims, per_point(statistic.pick(saved, mean, cov)), {"long_name": f"{statistic} at t1"})
        value_se = statistic.pick(saved, mean_se, cov_se)
        data["value_se"] = (grid_dims, per_point(value_se), {"long_name": "its standard error"})
    if wrt:
        d_mean, d_cov, d_mean_se, d_cov_se = derivatives  # (G, p, …)
        for a, q in enumerate(wrt):
            for stat, dims, value, se in (("mean", tn, d_mean, d_mean_se), ("cov", tnn, d_cov, d_cov_se)):
                long_name = f"pathwise (forward-mode) derivative of {stat} in {q}"
                data[f"d_{stat}_d_{q}"] = (dims, per_point(value[:, a]), {"long_name": long_name})
                data[f"d_{stat}_d_{q}_se"] = (dims, per_point(se[:, a]), {"long_name": "its standard error"})
            if statistic is not None:
                d = statistic.pick(saved, d_mean[:, a], d_cov[:, a])
                d_se = statistic.pick(saved, d_mean_se[:, a], d_cov_se[:, a])
                long_name = f"derivative of {statistic} in {q}"
                data[f"d_value_d_{q}"] = (grid_dims, per_point(d), {"long_name": long_name})
                data[f"d_value_d_{q}_se"] = (grid_dims, per_point(d_se), {"long_name": "its standard error"})
    fixed = {row[0]: getattr(system.params, row[0]) for row in system.params.describe()}
    attrs = {
        "statistic": "" if statistic is None else str(statistic),
        "grid": json.dumps(list(names)),
        "wrt": json.dumps(list(wrt)),
        "parameters": json.dumps({k: float(v) for k, v in fixed.items() if np.ndim(v) == 0 and k not in names}),
        "n_paths": int(n_paths),
        "t0": float(run.t0),
        "t1": float(run.t1),
        "key_data": np.asarray(jax.random.key_data(check_key(key))).astype(np.int64).ravel().tolist(),
    }
    coords = {name: values for name, values in zip(names, axes)}
    coords |= {"time": np.asarray(ts[0]), "name": list(saved), "name2": list(saved), "role": ("name", list(roles))}
    return xr.Dataset(data, coords=coords, attrs=attrs)
