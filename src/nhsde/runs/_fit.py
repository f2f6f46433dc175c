"""Fit runs: :func:`run_fit` fits parameters to a run file through simulation, writing a netCDF fit file.

A fit file (``format = "nhsde-fit"``) holds ``estimate``, ``se``, ``start`` and
``jacobian_relative_se`` (the Monte-Carlo error of the model's ``∂s/∂θ``, see
:func:`~nhsde.fit.estimate`) over ``parameter``, ``cov`` over ``parameter × parameter2``, the optimiser's
``history`` over ``step × column`` (``loss`` and the parameters), and as
attributes the fit configuration (JSON), ``chi2``, ``dof``, ``steps``,
``converged``, the data file with its configuration and git revision, the
package versions, the sources' SHA-256, the git revision and a checksum.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from ..fit import FitResult, Observations, Simulated, estimate
from ._config import ConfigError, RunConfig
from ._pieces import need_x64
from ._store import FIT_FORMAT, FORMAT, FORMAT_VERSION, claim, load_run, provenance, seal, write

__all__ = ["observations_from_run", "run_fit"]


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
    result = estimate(built.system, observed, model, vary=tuple(d["fit"]["vary"]), max_steps=d["fit"]["max_steps"])
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
            "data_file": str(data_path),
            "data_config": data.attrs["config"],
            "data_git_revision": data.attrs["git_revision"],
            **provenance(),
        },
    )
    return result, seal(ds)
