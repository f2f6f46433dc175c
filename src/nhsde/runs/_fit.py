"""Fit runs: :func:`run_fit` fits parameters to a run file through simulation, writing a netCDF fit file.

A fit file (``format = "nhsde-fit"``) holds ``estimate``, ``se``, ``start`` and
``jacobian_relative_se`` (the Monte-Carlo error of the model's ``∂s/∂θ``, see
:func:`~nhsde.fit.estimate`) over ``parameter``, ``cov`` over ``parameter × parameter2``, the optimiser's
``history`` over ``step × column`` (``loss`` and the parameters), and as
attributes the fit configuration (JSON), ``chi2``, ``dof``, ``steps``,
``converged``, where the correlations of the data's statistics came from (``correlations``: ``paths``, or
``model`` for a run file without its paths; see :func:`~nhsde.fit.estimate`) and ``inflation``, the data file
with its configuration and git revision, the
package versions, the sources' SHA-256, the git revision and a checksum.

:func:`fit_data` fits a scene to a data file (CSV or netCDF, the layouts of
:mod:`nhsde.fit`), as ``nhsde fit --data FILE --scene SCENE`` does.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from .._options import FixedSteps
from .._system import StochasticSystem
from ..fit import FitResult, MomentEquations, Observations, Simulated, estimate
from ..fit._estimate import check_step_budget
from ..scenes import get_scene
from ._config import SOLVER_HELP, ConfigError, RunConfig
from ._pieces import need_x64
from ._store import FIT_FORMAT, FORMAT, FORMAT_VERSION, claim, load_run, provenance, seal, write

if TYPE_CHECKING:
    import xarray as xr  # imported where used: `import nhsde.runs` leaves it (and pandas) until a run file

__all__ = [
    "DATA_MODELS",
    "fit_data",
    "fit_data_command",
    "fit_data_flags",
    "observations_from_run",
    "read_data",
    "run_fit",
]

DATA_MODELS = ("simulate", "moments")
"""The models of :func:`fit_data`: :class:`~nhsde.fit.Simulated` and :class:`~nhsde.fit.MomentEquations`."""


def observations_from_run(ds: xr.Dataset, names=None) -> Observations:
    """:class:`nhsde.fit.Observations` of a run file at all save times but the first (the initial state).

    With stored paths (``statistics.keep_paths``) the statistics' covariance is
    estimated in full; otherwise from the standard errors alone.
    """
    stored = list(ds["name"].values)
    names = stored if names is None else list(names)
    for name in names:
        if name not in stored:
            raise ConfigError(
                f"statistics.save: {name!r} is not in the data; it holds {', '.join(stored)}.", "statistics.save"
            )
    idx = [stored.index(n) for n in names]
    ts = ds["time"].values[1:]
    if "paths" in ds:
        good = ds["failed"].values == 0
        return Observations.from_paths(ts, ds["paths"].values[good][:, 1:][..., idx], names)
    ix = np.ix_(idx, idx)
    cov, cov_se = ds["cov"].values[1:][:, ix[0], ix[1]], ds["cov_se"].values[1:][:, ix[0], ix[1]]
    return Observations.from_statistics(
        ts, names, ds["mean"].values[1:, idx], cov, ds["mean_se"].values[1:, idx], cov_se, int(ds.attrs["n_used"])
    )


def run_fit(config: RunConfig, out=None) -> tuple[FitResult, xr.Dataset]:
    """Fit ``fit.vary`` to the run file ``fit.data`` through simulation; returns ``(FitResult, dataset)``.

    The model simulates ``paths.n`` paths with ``seed`` (use a seed other than
    the data's), the solver and ``dt`` of the file, from the scene's initial
    state, at the data's save times; ``parameters`` are the start values.  With
    ``out`` the dataset is written there (netCDF); ``out`` is checked first, as
    :func:`~nhsde.runs.run` checks its output.
    """
    if config.kind != "fit":
        raise ValueError(f"run_fit: this is a {config.kind!r} configuration; use run.")
    need_x64()
    if out is None:
        return _fit(config)
    out = Path(out)
    with claim(out, config, FIT_FORMAT):
        result, ds = _fit(config)
        write(ds, out)
    return result, ds


def _fit(config: RunConfig) -> tuple[FitResult, xr.Dataset]:
    import xarray as xr

    d = config.data
    data_path = config.base / d["fit"]["data"]
    if not data_path.is_file():
        raise ConfigError(f"fit.data = {d['fit']['data']!r}: no such file {data_path}.", "fit.data")
    data = load_run(data_path)
    if data.attrs.get("format") != FORMAT:
        raise ConfigError(f"fit.data = {d['fit']['data']!r}: not an nhsde run file.", "fit.data")
    observed = observations_from_run(data, d["statistics"]["save"])
    built = config.build()
    model = Simulated(
        built.y0,
        built.key,
        n_paths=d["paths"]["n"],
        steps=d["solver"]["dt"],
        solver=d["solver"]["name"],
        t0=float(data["time"].values[0]),
    )
    vary, max_steps = tuple(d["fit"]["vary"]), d["fit"]["max_steps"]
    result = estimate(built.system, observed, model, vary=vary, max_steps=max_steps, progress=terminal_progress())
    ds = xr.Dataset(
        {
            "estimate": (("parameter",), result.values),
            "se": (("parameter",), result.se),
            "cov": (("parameter", "parameter2"), result.cov),
            "start": (("parameter",), result.init),
            "jacobian_relative_se": (("parameter",), result.jacobian_relative_se),
            "history": (("step", "column"), result.history),
        },
        coords={"parameter": list(result.names), "parameter2": list(result.names), "column": ["loss", *result.names]},
        attrs={
            "format": FIT_FORMAT,
            "format_version": FORMAT_VERSION,
            "config": config.to_json(),
            "chi2": result.chi2,
            "dof": result.dof,
            "steps": result.steps,
            "converged": int(result.converged),
            "observed_from_trajectories": int(observed.from_trajectories),
            "correlations": result.correlations,
            "inflation": result.inflation,
            "data_file": str(data_path),
            "data_config": data.attrs["config"],
            "data_git_revision": data.attrs["git_revision"],
            **provenance(config),
        },
    )
    return result, seal(ds)


def read_data(path, system: StochasticSystem | None = None) -> Observations:
    """:class:`~nhsde.fit.Observations` of a data file: CSV (``.csv``), else netCDF (an nhsde run file, all its
    times but the first, or any dataset :meth:`~nhsde.fit.Observations.from_xarray` reads).

    With ``system``, every component must be one of its state or observable names.
    """

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"--data {path}: no such file.")
    if path.suffix.lower() == ".csv":
        return Observations.from_csv(path, system=system)
    ds = load_run(path)
    if ds.attrs.get("format") == FORMAT:
        return Observations.from_xarray(ds.isel(time=slice(1, None)), system=system)
    return Observations.from_xarray(ds, system=system)


def _data_step(ts, t0: float) -> float:
    """The largest step of at most 0.01 that divides the spacing of the observation times (and their start)."""
    h = float(ts[0] - t0 if len(ts) == 1 else ts[1] - ts[0])
    return h / math.ceil(h / 0.01) if h > 0 else 0.01


def fit_data(
    data,
    scene: str | type,
    vary: tuple[str, ...],
    *,
    parameters: dict[str, float] | None = None,
    model: str = "simulate",
    n_paths: int = 4096,
    dt: float | None = None,
    solver: str = "euler",
    seed: int = 0,
    t0: float = 0.0,
    max_steps: int = 100,
    progress: Callable[[int, float, dict[str, float]], None] | None = None,
) -> tuple[FitResult, Observations]:
    """Fit the parameters ``vary`` of the scene ``scene`` (a name of :func:`~nhsde.scenes.get_scene` or a scene
    class) to the data file ``data``; returns the fit and the data.

    The model starts at the scene's initial state at ``t0``: ``"simulate"`` simulates ``n_paths`` paths with
    ``jax.random.key(seed)`` (use a seed other than the data's), ``solver`` and step ``dt``; ``"moments"``
    integrates the normal-approximation moment equations with step ``dt`` (exact for linear systems).  ``dt``
    defaults to the largest step of at most 0.01 that divides the spacing of the observation times.
    ``parameters`` are the start values (and the fixed values of the other parameters); ``progress`` is
    :func:`~nhsde.fit.estimate`'s.

    Refused before any run: observation times before ``t0`` (outside the model's span), a span that steps of
    ``dt`` cross in more than :class:`~nhsde.FixedSteps`' step budget, and a complex initial state.
    """
    if model not in DATA_MODELS:
        raise ConfigError(f"--model {model!r}: allowed models are {', '.join(DATA_MODELS)}.")
    scene_cls: Any = get_scene(scene) if isinstance(scene, str) else scene
    try:
        built = scene_cls(**(parameters or {}))
    except (TypeError, ValueError) as e:
        raise ConfigError(f"--set: {e}") from None
    system = built.build()
    observed = read_data(data, system)
    ts = observed.ts
    if ts[0] < t0:
        raise ConfigError(
            f"--t0 {t0:g}: the data {data} start at t={ts[0]:g}, before it; the model runs from --t0 (the scene's "
            f"initial state) and gives statistics at times ≥ --t0: give --t0 ≤ {ts[0]:g}."
        )
    step = _data_step(ts, t0) if dt is None else dt
    remedy = (
        f"give a larger --dt, or the data's times in the scene's time unit (they run from t={ts[0]:.10g} to "
        f"t={ts[-1]:.10g})."
    )
    try:
        check_step_budget(t0, float(ts[-1]), FixedSteps(step), remedy)
    except ValueError as e:
        raise ConfigError(f"--data {data} with --t0 {t0:g}: {e}") from None
    state = built.initial_state()
    if np.iscomplexobj(state):
        raise ConfigError(
            f"--scene: the initial state of {getattr(scene_cls, '__name__', scene)} is complex "
            f"({np.asarray(state).tolist()}); the state is real (its imaginary part would be lost)."
        )
    y0 = jnp.asarray(state, jnp.float64)
    if model == "simulate":
        fitted = Simulated(y0, jax.random.key(seed), n_paths=n_paths, steps=step, solver=solver, t0=t0)
    else:
        fitted = MomentEquations(y0, dt=step, t0=t0)
    return estimate(system, observed, fitted, vary=tuple(vary), max_steps=max_steps, progress=progress), observed


def terminal_progress() -> Callable[[int, float, dict[str, float]], None] | None:
    """A fit's progress printer, one line per optimizer step on stderr, where stderr is a terminal (else None)."""
    if not sys.stderr.isatty():
        return None

    def show(step: int, loss: float, values: dict[str, float]):
        shown = "  ".join(f"{n} = {v:.6g}" for n, v in values.items())
        print(f"fit step {step:3d}: chi2/2 = {loss:.6g}  {shown}", file=sys.stderr, flush=True)

    return show


def fit_data_flags(parser: argparse.ArgumentParser):
    """The options of ``nhsde fit --data FILE --scene SCENE --fit NAMES``."""
    parser.add_argument("--data", help="a data file: CSV (per path or summary, see the fitting guide) or netCDF")
    parser.add_argument("--scene", help="with --data: the scene to fit (a name of `nhsde scenes` or MODULE:CLASS)")
    parser.add_argument("--fit", help="with --data: the parameters to fit, comma-separated (default eps,nu)")
    parser.add_argument("--model", choices=DATA_MODELS, help="with --data: simulate (default) or moments")
    parser.add_argument("--paths", type=int, help="with --data --model simulate: model paths (default 4096)")
    parser.add_argument("--dt", type=float, help="with --data: the model's step (default ≤ 0.01, dividing the data's)")
    parser.add_argument("--solver", help=f"with --data --model simulate: {SOLVER_HELP}")
    parser.add_argument("--seed", type=int, help="with --data: the model's seed, not the data's (default 1)")
    parser.add_argument("--t0", type=float, help="with --data: the time of the scene's initial state (default 0)")
    parser.add_argument("--max-steps", type=int, help="with --data: the most optimizer steps (default 100)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="with --data: a start or fixed parameter"
    )
    parser.add_argument(
        "--json",
        action="store_true",
        help='with --data: print {name: {"value": v, "se": s}, ..., "chi2", "dof", "chi2_per_dof", "converged", '
        '"steps", "note"} only',
    )


def fit_data_command(args) -> int:
    """``nhsde fit --data FILE --scene SCENE --fit NAMES``: the fit's table, or with ``--json`` its values and
    standard errors as JSON, with ``chi2``, ``dof``, ``chi2_per_dof``, ``converged``, the optimiser's ``steps`` and
    the ``note`` of what the fit left out ("" where nothing)."""
    if args.config is not None or args.out is not None:
        raise ConfigError("--data cannot be combined with --config or --out; a data fit prints its result.")
    if args.scene is None:
        raise ConfigError("--data needs --scene SCENE (see `nhsde scenes`, or MODULE:CLASS).")
    parameters = {}
    for item in args.set:
        name, _, value = item.partition("=")
        try:
            parameters[name] = float(value)
        except ValueError:
            raise ConfigError(f"--set {item!r}: expected NAME=VALUE with a number, e.g. --set eps=0.5.") from None
    vary = tuple(n.strip() for n in (args.fit or "eps,nu").split(","))
    if not all(vary):
        raise ConfigError(f"--fit {args.fit!r}: expected comma-separated parameter names, e.g. --fit eps,nu.")
    jax.config.update("jax_enable_x64", True)
    options = {
        "model": args.model,
        "n_paths": args.paths,
        "dt": args.dt,
        "solver": args.solver,
        "seed": 1 if args.seed is None else args.seed,
        "t0": args.t0,
        "max_steps": args.max_steps,
    }
    scene = get_scene(args.scene, folder=Path.cwd())  # a MODULE:CLASS named on the command line: the current directory
    result, observed = fit_data(
        args.data,
        scene,
        vary,
        parameters=parameters,
        progress=terminal_progress(),
        **{k: v for k, v in options.items() if v is not None},
    )
    if args.json:
        out: dict[str, Any] = {
            n: {"value": float(v), "se": float(s)} for n, v, s in zip(result.names, result.values, result.se)
        }
        out |= {
            "chi2": float(result.chi2),
            "dof": int(result.dof),
            "chi2_per_dof": float(result.chi2) / result.dof if result.dof > 0 else None,
            "converged": bool(result.converged),
            "steps": int(result.steps),
            "note": result.note,
        }
        print(json.dumps(out))
        return 0
    layout = "per-path" if observed.from_trajectories else "summary"
    print(f"{args.data}: {layout} data, {observed.n_paths} paths, {len(observed.ts)} times, names {observed.names}")
    print(result)
    return 0
