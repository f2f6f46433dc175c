"""The ``nhsde`` command: ``scenes``, ``simulate SCENE``, ``simulate --config``, ``fit --config``.

Both ``simulate`` modes write the same netCDF run file (``format = "nhsde-run"``,
see :func:`~nhsde.runs.run`); ``nhsde simulate SCENE --out FILE`` adds the
forward-mode derivatives ``d_mean_d_Q`` and ``d_cov_d_Q`` over ``time × name`` (``× name2``) for ``Q`` the
friction ``eps`` and the scene's noise intensities (``nu``; ``kT`` in a bath).  Before it simulates, the
command prints ``paths × steps`` and, for a run long enough, a rough time from
a timed pilot (kept in the compilation cache folder: the same run again prints the
same estimate without simulating the pilot).  Bad input (a run file, an option, an output path) ends it with
a one-line message and exit status 2; a run that fails, with status 1.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import re
import signal
import sys
import time
from pathlib import Path
from typing import cast

import numpy as np

from .._compilation_cache import enable_compilation_cache
from .._interrupt import watching
from ._config import SOLVER_HELP
from ._distributed import add_flags, processes
from ._fit import fit_data_flags
from ._sweep import sweep_command, sweep_flags

__all__ = ["build_parser", "main"]

PILOTS = "nhsde-pilots.json"
"""The seconds of earlier processes' timed pilots, in the compilation cache folder (JAX reads only its ``*-cache``
files there): a second run of a command prints its estimate without simulating, and so tracing and loading, the
pilot's programs again (about half a second of a warm-cache process)."""

_cache_folder: Path | None = None  # this process's compilation cache folder (main), None where it is off

RUN_EXAMPLE = """\
a run file (TOML; every key is checked, unknown keys are errors):

  scene = "ball-on-vibrating-plane"   # see `nhsde scenes`
  seed = 0                            # the key: jax.random.key(seed)
  precision = "float64"               # or "float32"

  [options]                           # the scene's flags
  drift = true

  [parameters]                        # unnamed parameters keep their defaults
  eps = 0.8
  nu = 1.5

  [initial_state]                     # optional: components of the state
  u_x = 0.0

  [solver]
  name = "sra1"                       # euler, milstein, heun, heun2, sra1, ...
  dt = 0.01
  t0 = 0.0
  t1 = 10.0

  [paths]
  n = 100000
  chunk = 8192                        # paths per piece written (a multiple of 64)

  [statistics]
  save = ["x", "y"]                   # default: the whole state
  save_points = 11
  keep_paths = false                  # true stores every path (needed to fit with full covariances)

  [accuracy]                          # optional: instead, one statistic at t1 to a requested accuracy
  rmse = 0.001                        # or relative_rmse = 0.01 (of the pilot's value); paths.n is unused
  statistic = "cov x x"               # or "mean x"; default: the variance of the drift coordinate
  solver = "any"                      # any, euler or weak2 (Gaussian increments); solver.dt: the coarsest step
  max_path_steps = 1e11               # refuse a predicted work above this

Run it again after an interruption to resume; the result is the same as an uninterrupted run.
"""

FIT_EXAMPLE = """\
a fit file: the run-file keys scene, seed (the model's key: not the data's), precision,
[options], [parameters] (start values), [initial_state], [solver] (name, dt), [paths] (n: model
paths), [statistics] (save: the components to fit, default all), and

  [fit]
  data = "run.nc"                     # a run file, relative to the fit file
  vary = ["eps", "nu"]
  max_steps = 100
"""

_SCENE_DEFAULTS = {"paths": 4096, "t1": 10.0, "dt": 0.01, "solver": "euler", "seed": 0, "save_points": 11}

# run-file keys → the options of `nhsde simulate SCENE` that set them
_FLAGS = {
    "paths.n": "--paths",
    "solver.t1": "--t1",
    "solver.dt": "--dt",
    "solver.name": "--solver",
    "statistics.save_points": "--save-points",
    "statistics.save": "--save",
    "seed": "--seed",
    "accuracy.rmse": "--rmse",
    "accuracy.relative_rmse": "--relative-rmse",
    "accuracy.statistic": "--statistic",
    "accuracy.solver": "--solver",
    "accuracy.max_path_steps": "--max-path-steps",
}
_FLAG_KEYS = re.compile(r"(?<![\w.])(" + "|".join(map(re.escape, _FLAGS)) + r"|parameters\.(\w+))( = )?")


def _as_flags(message: str) -> str:
    """A configuration error in the words of the command line: ``paths.n = 0`` → ``--paths 0``."""
    message = re.sub(r"^parameters: ", "--set: ", message)

    def flag(m):
        name = f"--set {m.group(2)}" if m.group(2) else _FLAGS[m.group(1)]
        return name + (" " if m.group(3) else "")

    return _FLAG_KEYS.sub(flag, message)


def _fmt(mean, se) -> str:
    return f"{float(mean): .6g} ± {float(se):.2g}"


def _progress_meter(args):
    """A progress bar with ``--progress``, or by default when stderr is a terminal."""
    import diffrax as dfx

    show = sys.stderr.isatty() if args.progress is None else args.progress
    args.bar_drawn = show  # a bar cut short leaves stderr mid-line: the command's message starts a new one
    return dfx.TqdmProgressMeter() if show else None


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.1f} s"
    return f"{seconds / 60:.1f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def _plan(config, n_paths: int, derivatives: bool = False) -> str:
    """``paths × steps`` of a run and, unless it is about as short as a pilot, roughly how long it takes, compiling
    included: a pilot of one chunk's paths over at most 20 steps, run twice (the first compiles, the second is timed
    and scaled to the run's chunks and steps).  The run's program compiles about as long as the pilot's, twice as
    long with the derivatives (their tangents; 1.6–3× measured on the sleigh, by hand and from its spec).  The seconds
    of the same pilot in an earlier process come from the compilation cache folder where it keeps them
    (:data:`PILOTS`)."""
    import jax

    from .._simulate import default_chunk_size

    s = config.data["solver"]
    steps = round((s["t1"] - s["t0"]) / s["dt"])
    text = f"{n_paths} paths × {steps} steps ({s['name']}, dt = {s['dt']:g})"
    m = min(steps, 20)
    piece = min(n_paths, config.data["paths"]["chunk"])  # a run file's piece: one simulate call
    chunk = default_chunk_size(piece, len(jax.devices()), jax.default_backend())
    # a small run ends within seconds, and for a run of a few pilots the pilot's two calls cost half the run
    if n_paths * steps <= max(16 * 64 * 100, 4 * chunk * m):
        return text
    key = _pilot_key(config, chunk, m)
    timed = _stored_pilot(key)
    if timed is None:
        timed = _timed_pilot(config, chunk, m)
        _store_pilot(key, timed)
    compiling, stepping = timed
    factor = 3 if derivatives else 1
    compiling *= 2 if derivatives else 1
    seconds = compiling + stepping * factor * -(-n_paths // chunk) * steps / m
    return (
        text + f", roughly {_duration(seconds)}{' with the derivatives' if derivatives else ''}, about "
        f"{_duration(compiling)} of it compiling (an estimate from a timed pilot of {chunk} paths × {m} steps)"
    )


def _pilot_key(config, chunk: int, m: int) -> str:
    """What a pilot's time depends on: the run without its paths and statistics, the pilot's ``chunk`` paths and
    ``m`` steps, the JAX version and the device."""
    import jax

    data = {k: v for k, v in config.data.items() if k not in ("paths", "statistics")}
    described = [
        data,
        chunk,
        m,
        jax.__version__,
        jax.devices()[0].device_kind,
        jax.dtypes.canonicalize_dtype(np.float64).name,
    ]
    return hashlib.sha256(json.dumps(described, sort_keys=True, default=str).encode()).hexdigest()


def _stored_pilot(key: str) -> tuple[float, float] | None:
    """``(compiling, stepping)`` seconds of an earlier process's pilot (:data:`PILOTS`), or None (none, unreadable,
    or no cache)."""
    if _cache_folder is None:
        return None
    try:
        timed = json.loads((_cache_folder / PILOTS).read_text()).get(key)
    except (OSError, ValueError, AttributeError):
        return None
    if not (isinstance(timed, list) and len(timed) == 2 and all(isinstance(t, (int, float)) for t in timed)):
        return None
    compiling, stepping = float(timed[0]), float(timed[1])
    return (compiling, stepping) if compiling >= 0 and stepping > 0 else None


def _store_pilot(key: str, timed: tuple[float, float]) -> None:
    """Keep the pilot's seconds for the next process (best effort: a folder that cannot be written is left)."""
    if _cache_folder is None:
        return
    path = _cache_folder / PILOTS
    try:
        stored = json.loads(path.read_text()) if path.exists() else {}
        stored = stored if isinstance(stored, dict) else {}
    except (OSError, ValueError):
        stored = {}
    stored[key] = list(timed)
    try:
        partial = path.with_name(f"{PILOTS}.{os.getpid()}")
        partial.write_text(json.dumps(stored))
        partial.replace(path)  # whole or not at all, for processes that read it meanwhile
    except OSError:
        pass


def _timed_pilot(config, chunk: int, m: int) -> tuple[float, float]:
    """``(compiling, stepping)``: seconds of a pilot of ``chunk`` paths over ``m`` steps, run twice; the first call's
    excess over the second is its compilation."""
    import jax

    from .._ensemble import Save
    from .._simulate import simulate

    s = config.data["solver"]
    built = config.build()

    def pilot() -> float:
        start = time.perf_counter()
        ens = simulate(
            built.system,
            built.y0,
            built.key,
            n_paths=chunk,
            t0=s["t0"],
            t1=s["t0"] + m * s["dt"],
            dt=s["dt"],
            solver=s["name"],
            save=Save(names=built.names, n=2),
            on_failure="exclude",
        )
        jax.block_until_ready(ens.mean)
        return time.perf_counter() - start

    first = pilot()
    stepping = pilot()
    return max(first - stepping, 0.0), stepping


def _saved(out: Path) -> str:
    return f"saved {out} (netCDF{'' if out.suffix == '.nc' else ', although the name does not end in .nc'})"


def _cmd_scenes(args) -> int:
    from ..scenes import SCENES, get_scene, installed_scenes

    installed = installed_scenes()
    for name in [*SCENES, *installed]:
        try:
            cls = get_scene(name)
        except ValueError as e:  # a broken installed scene is reported, not fatal
            print(f"{name}: cannot be loaded: {e}")
            continue
        where = f" (installed: {installed[name]})" if name in installed else ""
        print(f"{name}: {cls.description()}{where}")
        for pname, default, allowed, pdoc in cls.Parameters.describe():
            print(f"    {pname:<14} default {float(cast(float, default)):<8g} {allowed:<18} {pdoc}")
    print("\nor MODULE:CLASS: a scene class of your own, importable from the current directory or PYTHONPATH")
    return 0


def _parse_set(items) -> dict[str, float]:
    from ._config import ConfigError

    out = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected NAME=VALUE, e.g. --set eps=0.5.")
        name, value = item.split("=", 1)
        try:
            out[name] = float(value)
        except ValueError:
            raise ConfigError(f"--set {name}={value!r}: not a number.") from None
    return out


def _scene_config(args):
    """The run configuration of ``nhsde simulate SCENE``'s options: one piece of all the paths."""
    from ..scenes import get_scene
    from ._config import ConfigError, RunConfig, SceneSource

    get_scene(args.scene, folder=Path.cwd())  # a ValueError names the known scenes
    raw = {
        "scene": args.scene,
        "seed": args.seed,
        "precision": "float64" if args.x64 else "float32",
        "parameters": _parse_set(args.set),
        "solver": {"name": args.solver, "dt": args.dt, "t1": args.t1},
        "paths": {"n": args.paths, "chunk": 64 * max(1, -(-args.paths // 64))},
        "statistics": {"save_points": args.save_points, "save": _save_names(args)},
    }
    try:
        return RunConfig.from_dict(raw, scene_source=SceneSource(Path.cwd()))
    except ConfigError as e:
        raise ConfigError(_as_flags(str(e)), e.key) from None


def _save_names(args) -> list[str] | None:
    """``--save x,y,energy``: the state components and observables to save and print (``None``: the state)."""
    if not args.save:
        return None
    return [n.strip() for n in args.save.split(",") if n.strip()]


def _accuracy_given(args) -> bool:
    return args.rmse is not None or args.relative_rmse is not None


def _run_accuracy(config, built, out: Path | None = None) -> int:
    """``[accuracy]`` of a run (or ``--rmse``): one statistic at ``t1`` by :func:`~nhsde.statistics.to_accuracy`,
    with its pathwise derivatives in ``eps`` and ``nu`` (``eps`` only at ``nu = 0``) and their standard errors;
    with ``out``, the estimate is also written there as JSON (:func:`_write_estimate`)."""
    from .._ensemble import Save
    from .._weak import PlatenWeak2
    from ..scenes import ball_covariances
    from ..statistics import to_accuracy
    from ._config import default_statistic, parse_statistic

    d, a, s = config.data, config.data["accuracy"], config.data["solver"]
    statistic = (
        default_statistic(built.system, built.names) if a["statistic"] is None else parse_statistic(a["statistic"])
    )
    solver = {"any": None, "weak2": PlatenWeak2(increments="gaussian")}.get(a["solver"], a["solver"])
    target = f"rmse {a['rmse']:g}" if a["rmse"] is not None else f"relative rmse {a['relative_rmse']:g}"
    label = f"m[{statistic[1]}]" if statistic[0] == "mean" else f"K[{statistic[1]},{statistic[2]}]"
    params = config.parameters()
    wrt = _derivative_parameters(config, built.system.params)[1]
    print(f"scene {d['scene']}: " + ", ".join(f"{k}={v:g}" for k, v in params.items()))
    print(
        f"{label} at t = {s['t1']:g} to {target}: pilots from the coarsest step dt = {s['dt']:g}, "
        f"seed {d['seed']}, {d['precision']}",
        flush=True,
    )
    result = to_accuracy(
        built.system,
        built.y0,
        built.key,
        t0=s["t0"],
        t1=s["t1"],
        dt=s["dt"],
        statistic=statistic,
        rmse=a["rmse"],
        relative_rmse=a["relative_rmse"],
        solver=solver,
        save=Save(names=built.names, n=2),
        max_path_steps=a["max_path_steps"],
        wrt=wrt,
    )
    print(result.report())
    print(
        f"\n{label} = {_fmt(*result.value())}  (mean ± standard error; bias estimate "
        f"{result.bias:.2g}; target rmse {result.rmse:.3g}, estimated {result.estimated_rmse:.3g})"
    )
    for q, value, se in zip(result.wrt, *result.derivative(), strict=True):
        print(f"d{label}/d{q} = {_fmt(value, se)}  (pathwise, by forward mode, on the same paths)")
    if len(wrt) == 1:
        print(f"d{label}/dnu: does not exist at nu = 0")
    print(
        f"work: {result.cost.path_steps:.4g} path-steps ({result.pilot_cost.path_steps:.4g} in pilots), "
        f"{result.cost.seconds:.1f} s ({result.cost.compile_seconds:.1f} s compiling); by {result.choice}"
    )
    if d["scene"] == "ball-on-vibrating-plane" and statistic[0] == "cov":
        p = built.system.params
        kxx, kxu, kuu = ball_covariances(np.float64(s["t1"]), p.eps, p.nu, p.delta)
        print(f"closed form (S0 (3.1)): k_xx={float(kxx):.6g}  k_xu={float(kxu):.6g}  k_uu={float(kuu):.6g}")
    if out is not None:
        _write_estimate(out, config, " ".join(statistic), result)
        print(f"\nsaved {out} (JSON)")
    return 0


def _write_estimate(out: Path, config, statistic: str, result) -> None:
    """The estimate of ``--rmse`` (or ``[accuracy]``) as JSON at exactly ``out``, written whole then renamed:
    ``format = "nhsde-estimate"``, the configuration, the statistic at ``t``, ``value`` and ``se``, ``bias``, the
    target and estimated RMSE, ``derivatives`` ``{name: {"value", "se"}}``, the work, the estimator chosen and
    the provenance (package versions and sources, git revision, time)."""
    import json
    import os

    from ._store import provenance

    estimate = {
        "format": "nhsde-estimate",
        "format_version": 1,
        "config": config.data,
        "scene": config.data["scene"],
        "parameters": config.parameters(),
        "statistic": statistic,
        "t": config.data["solver"]["t1"],
        "value": result.value()[0],
        "se": result.value()[1],
        "bias": float(result.bias),
        "rmse_target": float(result.rmse),
        "rmse_estimated": float(result.estimated_rmse),
        "derivatives": {
            q: {"value": float(v), "se": float(e)} for q, v, e in zip(result.wrt, *result.derivative(), strict=True)
        },
        "work_path_steps": result.cost.path_steps,
        "pilot_work_path_steps": result.pilot_cost.path_steps,
        "pilot_seconds": result.pilot_cost.seconds,
        "seconds": result.cost.seconds,
        "compile_seconds": result.cost.compile_seconds,
        "estimator": str(result.choice),
        **provenance(config),
    }
    partial = out.with_name(out.name + ".partial")
    try:
        partial.write_text(json.dumps(estimate, indent=2, sort_keys=True) + "\n")
        os.replace(partial, out)
    except OSError as e:
        raise OSError(f"{out}: cannot write the estimate ({e.strerror or e}).") from None


def _cmd_accuracy_scene(args) -> int:
    """``nhsde simulate SCENE --rmse R`` (or ``--relative-rmse``): one statistic to that accuracy."""
    import math

    import jax

    from ..scenes import get_scene
    from ._config import ConfigError, RunConfig, SceneSource

    for name in ("paths", "save_points"):
        if getattr(args, name) is not None:
            flag = "--" + name.replace("_", "-")
            raise ConfigError(
                f"{flag} cannot be combined with --rmse/--relative-rmse: the estimator chooses the paths."
            )
    jax.config.update("jax_enable_x64", True)
    get_scene(args.scene, folder=Path.cwd())  # a ValueError names the known scenes
    t1 = _SCENE_DEFAULTS["t1"] if args.t1 is None else args.t1
    dt = args.dt if args.dt is not None else t1 / math.ceil(t1 / 0.25) if t1 > 0 else 0.25
    accuracy = {
        "rmse": args.rmse,
        "relative_rmse": args.relative_rmse,
        "statistic": args.statistic,
        "solver": args.solver or "any",
        "max_path_steps": args.max_path_steps,
    }
    raw = {
        "scene": args.scene,
        "seed": _SCENE_DEFAULTS["seed"] if args.seed is None else args.seed,
        "precision": "float64" if args.x64 else "float32",
        "parameters": _parse_set(args.set),
        "solver": {"dt": dt, "t1": t1},
        "statistics": {"save_points": 2},
        "accuracy": {k: v for k, v in accuracy.items() if v is not None},
    }
    try:
        config = RunConfig.from_dict(raw, scene_source=SceneSource(Path.cwd()))
    except ConfigError as e:
        raise ConfigError(_as_flags(str(e)), e.key) from None
    return _run_accuracy(config, config.build(), Path(args.out) if args.out else None)


def _derivative_parameters(config, params) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(reported, differentiated)``: a scene run reports derivatives in ``eps`` and in the scene's noise
    intensities (``Scene.intensities``: ``nu``, or ``kT`` in a bath); an intensity at 0 is not differentiated (paths
    scale like its square root there: the derivative does not exist, reported as nan)."""
    reported = ("eps", *config.scene_class.intensities)
    return reported, tuple(q for q in reported if q == "eps" or float(getattr(params, q)) > 0)


_SENSITIVITY_BYTES = 4 * 2**30


def _check_sensitivity_memory(args, state_dim: int, n_params: int):
    """The pathwise derivatives keep every path's saved values and tangents: refuse what would not fit."""
    need = 8 * args.paths * args.save_points * state_dim * (1 + n_params)
    if need > _SENSITIVITY_BYTES:
        raise ValueError(
            f"--paths {args.paths} with --save-points {args.save_points}: the derivatives' per-path tangents need "
            f"{need / 2**30:.1f} GiB (at most {_SENSITIVITY_BYTES / 2**30:.0f} GiB); use fewer save points or paths, "
            "or a run file (nhsde simulate run.toml), which stores statistics without derivatives."
        )


def _print_effective_diffusion(scene: str, ens, p) -> None:
    """``D = ½ dK/dt`` of the dependent coordinates over the second half, each entry ± its standard error (from
    the paths), and the closed form where the scene has one: the ball's ``νδ²/(8ε²)`` per axis."""
    from .. import statistics

    d, se = np.asarray(statistics.effective_diffusion(ens)), np.asarray(statistics.effective_diffusion_se(ens))
    names = statistics.drift_statistics(ens).names
    exact = None
    if scene == "ball-on-vibrating-plane" and float(p.eps) > 0:
        exact = float(p.nu * p.delta**2 / (8 * p.eps**2))
    print(
        "\neffective diffusion D = ½ dK/dt over the second half (value ± standard error"
        + ("; closed form: nu delta²/(8 eps²) on the diagonal, 0 off it, for long times)" if exact is not None else ")")
    )
    for i, a in enumerate(names):
        for j, b in enumerate(names[: i + 1]):
            closed = "" if exact is None else f"   closed form {exact if i == j else 0.0:.6g}"
            print(f"  D[{a},{b}] = {_fmt(d[i, j], se[i, j])}{closed}")


def _cmd_simulate_scene(args) -> int:
    """Simulate a scene, print its statistics at ``t1`` with their ``eps``/``nu`` derivatives, save with ``--out``."""
    if _accuracy_given(args):
        return _cmd_accuracy_scene(args)
    import jax

    from .. import statistics
    from .._ensemble import Save
    from ..scenes import ball_covariances
    from ._store import Pieces, claim, dataset, provenance, write

    for name, default in _SCENE_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    jax.config.update("jax_enable_x64", True)  # float64 sums; --x64 chooses the precision of the paths
    config = _scene_config(args)
    built = config.build()
    d = config.data

    p = jax.tree.map(np.asarray, built.system.params)  # printed on the host, not one program per operation
    reported, wrt = _derivative_parameters(config, p)
    _check_sensitivity_memory(args, len(built.names), len(wrt))
    out = Path(args.out) if args.out else None
    with claim(out, config) if out else contextlib.nullcontext():
        print(_plan(config, args.paths, derivatives=True), flush=True)
        sens = statistics.moment_sensitivities(
            built.system,
            built.y0,
            built.key,
            wrt=wrt,
            n_paths=args.paths,
            t1=args.t1,
            dt=args.dt,
            solver=args.solver,
            save=Save(names=built.names, n=args.save_points),
            on_failure="exclude",
            progress_meter=_progress_meter(args),
        )
        ens = sens.ensemble

        def by_parameter(field):  # per reported parameter, nan where not differentiated
            values = np.asarray(getattr(sens, field))
            return tuple(values[wrt.index(q)] if q in wrt else np.full_like(values[0], np.nan) for q in reported)

        d_mean, d_cov, d_mean_se, d_cov_se = map(by_parameter, ("d_mean", "d_cov", "d_mean_se", "d_cov_se"))
        pieces = Pieces()
        pieces.add(ens, keep_paths=False)
        if out:
            tn, tnn = ("time", "name"), ("time", "name", "name2")
            derivatives = {}
            for a, q in enumerate(reported):
                for stat, dims, value, se in (("mean", tn, d_mean, d_mean_se), ("cov", tnn, d_cov, d_cov_se)):
                    long_name = f"pathwise (forward-mode) derivative of {stat} in {q}"
                    derivatives[f"d_{stat}_d_{q}"] = (dims, np.asarray(value[a]), {"long_name": long_name})
                    derivatives[f"d_{stat}_d_{q}_se"] = (dims, np.asarray(se[a]), {"long_name": "its standard error"})
            write(dataset(config, built, pieces, provenance(config), extra=derivatives), out)

    params = config.parameters()
    print(f"scene {args.scene}: " + ", ".join(f"{k}={v:g}" for k, v in params.items()))
    print(
        f"{args.paths} paths, t1={args.t1}, dt={args.dt}, solver {args.solver}, seed {args.seed}, "
        f"{d['precision']}; failed paths: {sum(pieces.n_failed)}"
    )
    names, roles, last = built.names, built.roles, -1
    absent = "".join(f"; d/d {q} is nan: it does not exist at {q} = 0" for q in reported if q not in wrt)
    print(f"\nat t = {args.t1:g}  (value ± standard error; derivatives pathwise, by forward mode{absent})")
    print(f"{'quantity':<22}{'value':>26}" + "".join(f"{f'd/d {q}':>26}" for q in reported))
    # the run file's statistics (float64, from the moment sums), written with --out or not
    mean, cov, mean_se, cov_se = (np.asarray(a, np.float64)[last] for a in pieces.total().statistics())
    for i, n in enumerate(names):
        label = f"m[{n}]" + (" (systematic drift)" if roles[i] == "dependent_coordinate" else "")
        print(
            f"{label:<22}{_fmt(mean[i], mean_se[i]):>26}"
            + "".join(f"{_fmt(d_mean[a][last, i], d_mean_se[a][last, i]):>26}" for a in range(len(reported)))
        )
    for i, a in enumerate(names):
        for j, b in enumerate(names[: i + 1]):
            print(
                f"{f'K[{a},{b}]':<22}{_fmt(cov[i, j], cov_se[i, j]):>26}"
                + "".join(f"{_fmt(d_cov[q][last, i, j], d_cov_se[q][last, i, j]):>26}" for q in range(len(reported)))
            )
    if "dependent_coordinate" in roles and len(ens.ts) >= 3:
        _print_effective_diffusion(args.scene, ens, p)
    if args.scene == "ball-on-vibrating-plane":
        kxx, kxu, kuu = ball_covariances(np.float64(args.t1), p.eps, p.nu, p.delta)
        print(f"closed form (S0 (3.1)): k_xx={float(kxx):.6g}  k_xu={float(kxu):.6g}  k_uu={float(kuu):.6g}")
    if out:
        print(f"\n{_saved(out)}")
    return 0


def _load(args, kind: str):
    """Load and validate ``--config`` (float64 on: runs keep float64 sums)."""
    import jax

    from ._config import load_config

    jax.config.update("jax_enable_x64", True)
    return load_config(args.config, kind, trust_scene=args.trust_scene)


def _cmd_simulate_config(args) -> int:
    from ._config import ConfigError
    from ._pieces import run

    given = [f"--{n.replace('_', '-')}" for n in _SCENE_DEFAULTS if getattr(args, n) is not None]
    given += ["--set"] if args.set else []
    given += ["--x64"] if args.x64 else []
    given += ["--save"] if args.save else []
    given += ["SCENE"] if args.scene is not None else []
    if given:
        raise ConfigError(f"{', '.join(given)} cannot be combined with --config; set them in the file.")
    if _accuracy_given(args) or args.statistic is not None or args.max_path_steps is not None:
        raise ConfigError(
            "--rmse, --relative-rmse, --statistic, --max-path-steps cannot be combined with --config; use [accuracy]."
        )
    config = _load(args, "simulate")
    if "accuracy" in config.data:
        return _run_accuracy(config, config.build(), Path(args.out) if args.out else None)
    out = Path(args.out) if args.out else Path(args.config).with_suffix(".nc")
    n, chunk = config.data["paths"]["n"], config.data["paths"]["chunk"]

    def start(done):
        resuming = f"; resuming: {done} of {-(-n // chunk)} pieces are written" if done else ""
        print(f"{out}: {_plan(config, max(n - done * chunk, 0))} in pieces of {chunk}{resuming}", flush=True)

    def report(k):
        print(f"piece {k + 1} written to {out}", flush=True)

    ds = run(config, out, on_start=start, on_piece=report, progress_meter=_progress_meter(args))
    names = list(ds["name"].values)
    print(
        f"\n{ds.attrs['scene']}: {ds.attrs['n_used']} paths used, {ds.attrs['n_failed']} failed; "
        f"git {ds.attrs['git_revision']}"
    )
    print(f"at t = {float(ds['time'][-1]):g}  (mean ± standard error)")
    for i, a in enumerate(names):
        print(f"  m[{a}] = {_fmt(ds['mean'][-1, i], ds['mean_se'][-1, i])}")
    for i, a in enumerate(names):
        for j, b in enumerate(names[: i + 1]):
            print(f"  K[{a},{b}] = {_fmt(ds['cov'][-1, i, j], ds['cov_se'][-1, i, j])}")
    print(f"\n{_saved(out)}")
    return 0


def _cmd_simulate(args) -> int:
    from ._config import ConfigError

    if args.config is not None:
        return _cmd_simulate_config(args)
    if args.scene is None:
        raise ConfigError("give a SCENE (see `nhsde scenes`) or --config FILE.")
    if not _accuracy_given(args):
        for flag, value in (("--statistic", args.statistic), ("--max-path-steps", args.max_path_steps)):
            if value is not None:
                raise ConfigError(f"{flag} needs --rmse or --relative-rmse.")
    return _cmd_simulate_scene(args)


def _cmd_fit(args) -> int:
    from ._config import ConfigError
    from ._fit import fit_data_command, run_fit

    if args.data is not None:
        return fit_data_command(args)
    if args.config is None:
        raise ConfigError("give --config FILE (a fit file) or --data FILE --scene SCENE --fit NAMES.")
    config = _load(args, "fit")
    out = Path(args.out) if args.out else Path(args.config).with_suffix(".nc")
    result, _ = run_fit(config, out)
    print(result)
    print(f"\n{_saved(out)}")
    return 0


_TRUST_HELP = (
    "with --config: import the file's MODULE:CLASS scene although the file records no scene_sha256 for it (its "
    "code runs unchecked)"
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``nhsde`` command."""
    parser = argparse.ArgumentParser(prog="nhsde", description="Stochastic nonholonomic mechanics in JAX.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("scenes", help="list the scenes and their parameters")
    sim = sub.add_parser(
        "simulate",
        help="simulate a scene; print drift statistics and their gradients, or run a --config file",
        epilog=RUN_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sim.add_argument(
        "scene",
        nargs="?",
        help="scene name, see `nhsde scenes`, or MODULE:CLASS, a scene class of your own (or use --config)",
    )
    sim.add_argument("--config", help="a TOML run file; runs (or resumes) it, writing netCDF to --out")
    sim.add_argument("--trust-scene", action="store_true", help=_TRUST_HELP)
    sim.add_argument("--paths", type=int, help="number of paths (default 4096)")
    sim.add_argument("--t1", type=float, help="final time (default 10)")
    sim.add_argument(
        "--dt",
        type=float,
        help="time step (default 0.01); with --rmse the coarsest step the estimators consider "
        "(default: t1 in equal steps of at most 0.25)",
    )
    sim.add_argument("--solver", help=SOLVER_HELP)
    sim.add_argument("--seed", type=int, help="random seed (default 0)")
    sim.add_argument("--save-points", type=int, help="save times from 0 to t1 (default 11)")
    sim.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a scene parameter")
    sim.add_argument(
        "--save",
        metavar="NAME,NAME",
        help="the state components and observables to save and print, e.g. x,y,energy (default: the whole state)",
    )
    sim.add_argument(
        "--out",
        help="write the netCDF run file here, exactly this name (for --config default: the config's name with .nc); "
        "with --rmse or [accuracy], the estimate as JSON",
    )
    sim.add_argument("--x64", action="store_true", help="simulate in float64 (default float32; sums are float64)")
    sim.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        help="a progress bar (default: when stderr is a terminal)",
    )
    sim.add_argument(
        "--rmse",
        type=float,
        help="estimate one statistic at t1 to this root-mean-square error by the cheapest estimator a pilot "
        "predicts (plain, extrapolated, multilevel, antithetic, control variate); --dt is the coarsest step",
    )
    sim.add_argument("--relative-rmse", type=float, help="as --rmse, relative to the pilot's |value|")
    sim.add_argument(
        "--statistic",
        help="with --rmse: 'cov NAME NAME' or 'mean NAME' at t1, NAME a state component or an observable of the "
        "scene, e.g. 'mean energy' (default the variance of the drift coordinate)",
    )
    sim.add_argument("--max-path-steps", type=float, help="with --rmse: refuse a predicted work above this")
    fit = sub.add_parser(
        "fit",
        help="fit parameters to a run file through simulation (--config FILE)",
        epilog=FIT_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    fit.add_argument("--config", help="a TOML fit file")
    fit.add_argument("--trust-scene", action="store_true", help=_TRUST_HELP)
    fit.add_argument("--out", help="netCDF file for the estimates (default the config's name with .nc)")
    fit_data_flags(fit)  # --data FILE --scene SCENE --fit NAMES, the model's options, --json
    sweep_flags(sub.add_parser("sweep", help="simulate a scene over a grid of parameters; a statistic at each point"))
    for p in (sim, fit):
        add_flags(p)  # --coordinator, --num-processes, --process-id: several processes, process 0 writes
    return parser


def _runtime_message(error: Exception) -> str:
    """The library's message inside a run-time error raised from compiled code (``eqx.error_if``), without the
    tracebacks around it."""
    text = str(error)
    for marker in ("EquinoxRuntimeError: ", "SimulationError: "):
        if marker in text:
            return text.rsplit(marker, 1)[1].split("\n\n", 1)[0]
    return text.splitlines()[0]


SIGINT_IGNORED_NOTE = (
    "nhsde: started with SIGINT ignored (as by `nohup … &`): Ctrl-C cannot stop this run; use `kill` or start it "
    "in the foreground"
)


def main(argv=None) -> int:
    """Entry point of the ``nhsde`` command; returns the exit status.

    0 on success; 2 for bad input (a run file, an option, an output path), 1 for
    a run that failed (failed paths, a full disk), each with a one-line message
    on stderr.  JAX's persistent compilation cache is on, in ``~/.cache/nhsde/jax``
    (:func:`~nhsde.enable_compilation_cache`; ``NHSDE_COMPILATION_CACHE`` moves it or, ``off``, turns it off).
    """
    import equinox as eqx
    import jax

    from .._ensemble import SimulationError

    args = build_parser().parse_args(argv)
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN and sys.stderr.isatty():
        print(SIGINT_IGNORED_NOTE, file=sys.stderr)
    commands = {"scenes": _cmd_scenes, "simulate": _cmd_simulate, "fit": _cmd_fit, "sweep": sweep_command}
    command = commands[args.command]
    try:
        global _cache_folder
        _cache_folder = enable_compilation_cache()  # $NHSDE_COMPILATION_CACHE: another folder, or off
        with (
            processes(args),  # jax.distributed from the flags or NHSDE_* variables; none: one process
            watching(),  # Ctrl-C stops a compiled run within seconds
        ):
            return command(args)
    except ValueError as e:  # ConfigError, and what simulate refuses
        message, status = str(e), 2
    except (SimulationError, FloatingPointError, OSError) as e:
        message, status = str(e), 1
    except (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError) as e:  # a check inside a transformed computation
        message, status = _runtime_message(e), 1
    except KeyboardInterrupt:
        message, status = "interrupted; a run file keeps the pieces written (the same command resumes it)", 130
    new_line = "\n" if getattr(args, "bar_drawn", False) else ""
    print(f"{new_line}nhsde {args.command}: {' '.join(message.split())}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
