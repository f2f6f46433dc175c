"""``nhsde sweep SCENE --grid eps=0.5:2:8 nu=0.5,1``: :func:`nhsde.sweep` from the command line, to a sweep file.

A sweep file (``format = "nhsde-sweep"``, netCDF) holds :func:`nhsde.sweep`'s
dataset — the moments, their standard errors and pathwise derivatives over the
grid, and the chosen statistic at ``t1`` (``value``, ``value_se``,
``d_value_d_…``) — with, as attributes, the run configuration of the grid's
base point and the grid (JSON), the package versions, the sources' SHA-256, the
git revision and a checksum, as run files have.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
from pathlib import Path

import jax
import numpy as np

from .._ensemble import Save
from ._config import SOLVER_HELP, ConfigError, RunConfig, SceneSource, default_statistic, parse_statistic
from ._store import FORMAT_VERSION, claim, provenance, seal, write

__all__ = ["SWEEP_FORMAT", "parse_grid", "sweep_command", "sweep_flags"]

SWEEP_FORMAT = "nhsde-sweep"

_DEFAULTS = {"paths": 4096, "t1": 10.0, "dt": 0.01, "solver": "euler", "seed": 0, "save_points": 11}


MAX_GRID_POINTS = 100_000
"""The most grid points a sweep takes (each is a simulation); checked before any value is made."""


def parse_grid(items) -> dict[str, list[float]]:
    """``["eps=0.5:2:4", "nu=0.5,1"]`` → ``{"eps": [0.5, 1, 1.5, 2], "nu": [0.5, 1]}``.

    ``START:STOP:COUNT`` is ``COUNT`` equally spaced values from ``START`` to ``STOP``, both included;
    ``A,B,…`` the values listed.  The grid (the product) has at most :data:`MAX_GRID_POINTS` points.
    """
    grid: dict[str, list[float]] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise ConfigError(f"--grid {item!r}: expected NAME=START:STOP:COUNT or NAME=A,B,..., e.g. eps=0.5:2:8.")
        if name in grid:
            raise ConfigError(f"--grid {item!r}: {name} is given twice.")
        try:
            if ":" in text:
                start, stop, count = text.split(":")
                n = int(count)
                if n < 1:
                    raise ValueError
                if n * math.prod(len(v) for v in grid.values()) > MAX_GRID_POINTS:
                    raise ConfigError(
                        f"--grid {item!r}: {n} values make a grid of "
                        f"{n * math.prod(len(v) for v in grid.values()):,} points; at most {MAX_GRID_POINTS:,} "
                        "(each point is a simulation): take fewer values, or several sweeps."
                    )
                values = np.linspace(float(start), float(stop), n).tolist()
            else:
                values = [float(v) for v in text.split(",")]
        except ConfigError:
            raise
        except ValueError:
            raise ConfigError(
                f"--grid {item!r}: expected NAME=START:STOP:COUNT (COUNT ≥ 1) or NAME=A,B,... with numbers."
            ) from None
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(f"--grid {item!r}: the values must be finite.")
        grid[name] = values
    if math.prod(len(v) for v in grid.values()) > MAX_GRID_POINTS:
        raise ConfigError(
            f"--grid: {math.prod(len(v) for v in grid.values()):,} points; at most {MAX_GRID_POINTS:,} (each point is "
            "a simulation): take fewer values, or several sweeps."
        )
    if not grid:
        raise ConfigError("--grid: give at least one NAME=START:STOP:COUNT.")
    return grid


def sweep_flags(parser: argparse.ArgumentParser):
    """The arguments of ``nhsde sweep``."""
    parser.add_argument("scene", help="scene name, see `nhsde scenes`, or MODULE:CLASS")
    parser.add_argument(
        "--grid",
        nargs="+",
        required=True,
        metavar="NAME=START:STOP:COUNT",
        help="parameter values: COUNT from START to STOP, both included, or NAME=A,B,...; the grid is their product",
    )
    parser.add_argument(
        "--statistic", help="'cov NAME NAME' or 'mean NAME' at t1 (default the variance of the drift coordinate)"
    )
    parser.add_argument("--paths", type=int, help="paths per grid point (default 4096)")
    parser.add_argument("--t1", type=float, help="final time (default 10)")
    parser.add_argument("--dt", type=float, help="time step (default 0.01)")
    parser.add_argument("--solver", help=SOLVER_HELP)
    parser.add_argument("--seed", type=int, help="random seed, the same at every point (default 0)")
    parser.add_argument("--save-points", type=int, help="save times from 0 to t1 (default 11)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a scene parameter")
    parser.add_argument("--x64", action="store_true", help="simulate in float64 (default float32; sums are float64)")
    parser.add_argument("--out", help="the netCDF sweep file (default: none written)")
    parser.add_argument(
        "--progress", action=argparse.BooleanOptionalAction, help="report each tenth of the grid on stderr"
    )


def _config(args, grid: dict[str, list[float]]) -> RunConfig:
    """The run configuration of the grid's base point, with the grid and statistic under ``sweep``."""
    parameters = {}
    for item in args.set:
        name, _, value = item.partition("=")
        try:
            parameters[name] = float(value)
        except ValueError:
            raise ConfigError(f"--set {item!r}: expected NAME=VALUE with a number, e.g. --set eps=0.5.") from None
    clash = sorted(set(grid) & set(parameters))
    if clash:
        raise ConfigError(f"--set {clash[0]}: it is swept by --grid; give it once.")
    n = args.paths
    raw = {
        "scene": args.scene,
        "seed": args.seed,
        "precision": "float64" if args.x64 else "float32",
        "parameters": parameters,
        "solver": {"name": args.solver, "dt": args.dt, "t1": args.t1},
        "paths": {"n": n, "chunk": 64 * max(1, -(-n // 64))},
        "statistics": {"save_points": args.save_points},
    }
    config = RunConfig.from_dict(raw, scene_source=SceneSource(Path.cwd()))  # a MODULE:CLASS named here
    return dataclasses.replace(config, data=config.data | {"sweep": {"grid": grid, "statistic": args.statistic}})


def _fmt(value, se) -> str:
    return f"{float(value): .6g} ± {float(se):.2g}"


def sweep_command(args) -> int:
    """Run ``nhsde sweep``: print the statistic (and its derivatives) at every grid point, save with ``--out``."""
    from .._sweep import sweep  # xarray and pandas: only for this command

    for name, default in _DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    jax.config.update("jax_enable_x64", True)  # float64 sums; --x64 chooses the precision of the paths
    grid = parse_grid(args.grid)
    config = _config(args, grid)
    built = config.build()
    if args.statistic is None:
        statistic = default_statistic(built.system, built.names)
        config.data["sweep"]["statistic"] = " ".join(statistic)
    else:
        try:
            statistic = parse_statistic(args.statistic)
        except ValueError as e:
            raise ConfigError(f"--statistic {e}.") from None
    points = math.prod(len(v) for v in grid.values())
    show = sys.stderr.isatty() if args.progress is None else args.progress

    def report(done, total):
        if show:
            print(f"grid points done: {done} of {total}", file=sys.stderr, flush=True)

    out = Path(args.out) if args.out else None
    with claim(out, config, SWEEP_FORMAT) if out else contextlib.nullcontext():
        print(f"{points} grid points × {args.paths} paths × {round(args.t1 / args.dt)} steps", flush=True)
        ds = sweep(
            built.system,
            grid,
            y0=built.y0,
            key=built.key,
            n_paths=args.paths,
            t1=args.t1,
            dt=args.dt,
            solver=args.solver,
            statistic=tuple(statistic),
            save=Save(names=built.names, n=args.save_points),
            batch=max(1, math.ceil(points / 10)),
            on_batch=report,
        )
        ds.attrs |= {
            "format": SWEEP_FORMAT,
            "format_version": FORMAT_VERSION,
            "config": config.to_json(),
            "scene": args.scene,
            "seed": args.seed,
            "solver": args.solver,
            "dt": args.dt,
            "precision": config.data["precision"],
            **provenance(config),
        }
        seal(ds)
        if out:
            write(ds, out)
    names = list(grid)
    label = " ".join(statistic)
    print(f"\n{label} at t = {args.t1:g}  (value ± standard error; derivatives pathwise, by forward mode)")
    print("".join(f"{n:>10}" for n in names) + f"{'value':>26}" + "".join(f"{'d/d ' + n:>26}" for n in names))
    flat = ds["value"].stack(point=names)
    for p in range(flat.sizes["point"]):
        at = flat.isel(point=p)
        row = "".join(f"{float(at[n]):>10.4g}" for n in names)
        row += f"{_fmt(at.values, ds['value_se'].stack(point=names).values[p]):>26}"
        for n in names:
            d = ds[f"d_value_d_{n}"].stack(point=names).values[p]
            d_se = ds[f"d_value_d_{n}_se"].stack(point=names).values[p]
            row += f"{_fmt(d, d_se):>26}"
        print(row)
    if out:
        print(f"\nsaved {out} (netCDF)")
    return 0
