"""Command line: ``nhsde scenes``, ``nhsde simulate SCENE``, ``nhsde simulate --config`` and ``nhsde fit --config``.

``nhsde simulate --config run.toml [--out run.nc]`` runs the file's description
(see ``nhsde._runs``) in pieces, writing a netCDF file after each; run it again
after an interruption and it resumes.  ``nhsde fit --config fit.toml [--out
fit.nc]`` fits parameters to a run file through simulation.

``nhsde simulate`` prints the drift statistics at the final time with their
Monte-Carlo standard errors and their derivatives with respect to ``eps`` and
``nu`` (forward mode through the simulation).  ``--out FILE.npz`` saves them:
arrays ``ts``, ``mean``, ``cov``, ``mean_se``, ``cov_se`` (all saved components,
at the save times), ``failed`` (per path), ``d_mean_d_eps``, ``d_mean_d_nu``,
``d_cov_d_eps``, ``d_cov_d_nu``, and ``metadata``: a JSON string with the scene,
its parameters, the component names, solver, steps, seed and package versions.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

FORMAT_VERSION = 1


def _parse_set(items, scene_cls):
    known = {name for name, *_ in scene_cls.Parameters.describe()}
    out = {}
    for item in items:
        if "=" not in item:
            raise SystemExit(f"--set {item!r}: expected NAME=VALUE, e.g. --set eps=0.5.")
        name, value = item.split("=", 1)
        if name not in known:
            raise SystemExit(f"--set {name}: unknown parameter; parameters: {', '.join(sorted(known))}.")
        try:
            out[name] = float(value)
        except ValueError:
            raise SystemExit(f"--set {name}={value!r}: not a number.") from None
    return out


def _cmd_scenes(args):
    from .scenes import SCENES

    for name, cls in SCENES.items():
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        print(f"{name}: {doc}")
        for pname, default, allowed, pdoc in cls.Parameters.describe():
            print(f"    {pname:<14} default {float(default):<8g} {allowed:<18} {pdoc}")
    return 0


def _fmt(mean, se):
    return f"{float(mean): .6g} ± {float(se):.2g}"


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

_LEGACY_DEFAULTS = {"paths": 4096, "t1": 10.0, "dt": 0.01, "solver": "euler", "seed": 0, "save_points": 11}


def _cmd_simulate(args):
    if args.config is not None:
        return _cmd_simulate_config(args)
    if args.scene is None:
        raise SystemExit("nhsde simulate: give a SCENE (see `nhsde scenes`) or --config FILE.")
    for name, default in _LEGACY_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    import diffrax as dfx
    import jax
    import jax.numpy as jnp

    if args.x64:
        jax.config.update("jax_enable_x64", True)

    import nhsde
    from nhsde.scenes import get_scene

    try:
        scene_cls = get_scene(args.scene)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    values = _parse_set(args.set, scene_cls)
    try:
        scene = scene_cls(**values)
        system = scene.build()
    except ValueError as e:
        raise SystemExit(str(e)) from None
    y0 = scene.initial_state()
    key = jax.random.key(args.seed)

    def run(eps, nu):
        sysp = system.replace_params(eps=eps, nu=nu)
        ens = nhsde.simulate(
            sysp,
            y0,
            key,
            n_paths=args.paths,
            t1=args.t1,
            dt=args.dt,
            solver=args.solver,
            save=nhsde.Save(n=args.save_points),
            progress_meter=dfx.TqdmProgressMeter() if args.progress else None,
        )
        return (ens.mean, ens.cov), ens

    p = system.params
    # at ν = 0 paths scale like √ν: the ν-derivative does not exist and is reported as nan
    argnums = (0, 1) if float(p.nu) > 0 else (0,)
    try:
        (d_mean, d_cov), ens = jax.jacfwd(run, argnums=argnums, has_aux=True)(p.eps, p.nu)
    except (ValueError, TypeError, nhsde.SimulationError) as e:
        raise SystemExit(f"nhsde simulate: {e}") from None
    if len(argnums) == 1:
        d_mean, d_cov = (d_mean[0], jnp.full_like(d_mean[0], jnp.nan)), (d_cov[0], jnp.full_like(d_cov[0], jnp.nan))
    d_eps, d_nu = (d_mean[0], d_cov[0]), (d_mean[1], d_cov[1])
    n_failed = int(ens.n_failed)
    print(f"scene {args.scene}: " + ", ".join(f"{k}={float(getattr(p, k)):g}" for k, *_ in p.describe()))
    print(
        f"{args.paths} paths, t1={args.t1}, dt={args.dt}, solver {args.solver}, seed {args.seed}; "
        f"failed paths: {n_failed}"
    )
    names = ens.names
    last = -1
    print(
        f"\nat t = {float(ens.ts[last]):g}  (mean ± standard error; derivatives by forward mode"
        + ("" if len(argnums) == 2 else "; d/d nu is nan: it does not exist at nu = 0")
        + ")"
    )
    print(f"{'quantity':<22}{'value':>26}{'d/d eps':>14}{'d/d nu':>14}")
    for i, n in enumerate(names):
        role = ens.roles[i]
        label = f"m[{n}]" + (" (systematic drift)" if role == "dependent_coordinate" else "")
        print(
            f"{label:<22}{_fmt(ens.mean[last, i], ens.mean_se[last, i]):>26}"
            f"{float(d_eps[0][last, i]):>14.5g}{float(d_nu[0][last, i]):>14.5g}"
        )
    for i, a in enumerate(names):
        for j, b in enumerate(names[: i + 1]):
            label = f"K[{a},{b}]"
            print(
                f"{label:<22}{_fmt(ens.cov[last, i, j], ens.cov_se[last, i, j]):>26}"
                f"{float(d_eps[1][last, i, j]):>14.5g}{float(d_nu[1][last, i, j]):>14.5g}"
            )
    if any(r == "dependent_coordinate" for r in ens.roles) and len(ens.ts) >= 3:
        d_eff = nhsde.statistics.effective_diffusion(ens)
        print("\neffective diffusion (½ dK/dt over the second half):", np.array2string(np.asarray(d_eff), precision=5))
    if args.scene == "ball-on-vibrating-plane":
        from nhsde.scenes import ball_covariances

        kxx, kxu, kuu = ball_covariances(ens.ts[last], p.eps, p.nu, p.delta)
        print(f"closed form (S0 (3.1)): k_xx={float(kxx):.6g}  k_xu={float(kxu):.6g}  k_uu={float(kuu):.6g}")
    if args.out:
        meta = {
            "format": "nhsde-simulate",
            "format_version": FORMAT_VERSION,
            "scene": args.scene,
            "parameters": {k: float(getattr(p, k)) for k, *_ in p.describe()},
            "names": list(names),
            "roles": list(ens.roles),
            "paths": args.paths,
            "t1": args.t1,
            "dt": args.dt,
            "solver": args.solver,
            "seed": args.seed,
            "x64": bool(args.x64),
            "versions": _versions(),
        }
        np.savez(
            args.out,
            ts=ens.ts,
            mean=ens.mean,
            cov=ens.cov,
            mean_se=ens.mean_se,
            cov_se=ens.cov_se,
            failed=ens.failed,
            d_mean_d_eps=d_eps[0],
            d_mean_d_nu=d_nu[0],
            d_cov_d_eps=d_eps[1],
            d_cov_d_nu=d_nu[1],
            metadata=json.dumps(meta),
        )
        print(f"\nsaved {args.out}")
    return 0


def _versions():
    from ._runs import versions

    return versions()


def _config_run(args, kind):
    """Load and validate ``--config`` (x64 on: runs keep float64 sums)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from ._runs import ConfigError, load_config

    try:
        return load_config(args.config, kind)
    except ConfigError as e:
        raise SystemExit(f"nhsde {kind}: {e}") from None


def _cmd_simulate_config(args):
    from pathlib import Path

    from ._ensemble import SimulationError
    from ._runs import ConfigError, run

    given = [f"--{n.replace('_', '-')}" for n in _LEGACY_DEFAULTS if getattr(args, n) is not None]
    given += ["--set"] if args.set else []
    given += ["--x64"] if args.x64 else []
    given += ["SCENE"] if args.scene is not None else []
    if given:
        raise SystemExit(f"nhsde simulate: {', '.join(given)} cannot be combined with --config; set them in the file.")
    config = _config_run(args, "simulate")
    out = Path(args.out) if args.out else Path(args.config).with_suffix(".nc")

    def report(k):
        print(f"piece {k + 1} written to {out}", flush=True)

    try:
        ds = run(config, out, on_piece=report, progress=args.progress)
    except (ConfigError, ValueError, SimulationError) as e:
        raise SystemExit(f"nhsde simulate: {e}") from None
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
    print(f"\nsaved {out}")
    return 0


def _cmd_fit(args):
    from pathlib import Path

    from ._ensemble import SimulationError
    from ._runs import ConfigError, run_fit

    config = _config_run(args, "fit")
    out = Path(args.out) if args.out else Path(args.config).with_suffix(".nc")
    try:
        result, _ = run_fit(config, out)
    except (ConfigError, ValueError, SimulationError, FloatingPointError) as e:
        raise SystemExit(f"nhsde fit: {e}") from None
    print(result)
    print(f"\nsaved {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nhsde", description="Stochastic nonholonomic mechanics in JAX.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("scenes", help="list the scenes and their parameters")
    sim = sub.add_parser(
        "simulate",
        help="simulate a scene; print drift statistics and their gradients, or run a --config file",
        epilog=RUN_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sim.add_argument("scene", nargs="?", help="scene name, see `nhsde scenes` (or use --config)")
    sim.add_argument("--config", help="a TOML run file; runs (or resumes) it, writing netCDF to --out")
    sim.add_argument("--paths", type=int, help="number of paths (default 4096)")
    sim.add_argument("--t1", type=float, help="final time (default 10)")
    sim.add_argument("--dt", type=float, help="time step (default 0.01)")
    sim.add_argument("--solver", help="euler, milstein, heun, heun2, sra1 or exponential (default euler)")
    sim.add_argument("--seed", type=int, help="random seed (default 0)")
    sim.add_argument("--save-points", type=int, help="save times from 0 to t1 (default 11)")
    sim.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a scene parameter")
    sim.add_argument(
        "--out",
        help="save the results to this file (.npz for SCENE; netCDF for --config, default the config's name with .nc)",
    )
    sim.add_argument("--x64", action="store_true", help="compute in float64")
    sim.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    fit = sub.add_parser(
        "fit",
        help="fit parameters to a run file through simulation (--config FILE)",
        epilog=FIT_EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    fit.add_argument("--config", required=True, help="a TOML fit file")
    fit.add_argument("--out", help="netCDF file for the estimates (default the config's name with .nc)")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "scenes":
        return _cmd_scenes(args)
    if args.command == "fit":
        return _cmd_fit(args)
    return _cmd_simulate(args)


if __name__ == "__main__":
    sys.exit(main())
