"""Command line: ``nhsde scenes`` and ``nhsde simulate SCENE``.

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


def _cmd_simulate(args):
    import jax

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
            sysp, y0, key, n_paths=args.paths, t1=args.t1, dt=args.dt, solver=args.solver,
            save=nhsde.Save(n=args.save_points), progress=args.progress,
        )
        return (ens.mean, ens.cov), ens

    p = system.params
    try:
        (d_mean, d_cov), ens = jax.jacfwd(run, argnums=(0, 1), has_aux=True)(p.eps, p.nu)
    except (ValueError, TypeError, nhsde.SimulationError) as e:
        raise SystemExit(f"nhsde simulate: {e}") from None
    d_eps, d_nu = (d_mean[0], d_cov[0]), (d_mean[1], d_cov[1])
    n_failed = int(ens.n_failed)
    print(f"scene {args.scene}: " + ", ".join(f"{k}={float(getattr(p, k)):g}" for k, *_ in p.describe()))
    print(f"{args.paths} paths, t1={args.t1}, dt={args.dt}, solver {args.solver}, seed {args.seed}; "
          f"failed paths: {n_failed}")
    names = ens.names
    last = -1
    print(f"\nat t = {float(ens.ts[last]):g}  (mean ± standard error; derivatives by forward mode)")
    print(f"{'quantity':<22}{'value':>26}{'d/d eps':>14}{'d/d nu':>14}")
    for i, n in enumerate(names):
        role = ens.roles[i]
        label = f"m[{n}]" + (" (systematic drift)" if role == "dependent_coordinate" else "")
        print(f"{label:<22}{_fmt(ens.mean[last, i], ens.mean_se[last, i]):>26}"
              f"{float(d_eps[0][last, i]):>14.5g}{float(d_nu[0][last, i]):>14.5g}")
    for i, a in enumerate(names):
        for j, b in enumerate(names[: i + 1]):
            label = f"K[{a},{b}]"
            print(f"{label:<22}{_fmt(ens.cov[last, i, j], ens.cov_se[last, i, j]):>26}"
                  f"{float(d_eps[1][last, i, j]):>14.5g}{float(d_nu[1][last, i, j]):>14.5g}")
    if any(r == "dependent_coordinate" for r in ens.roles) and len(ens.ts) >= 3:
        d_eff = nhsde.statistics.effective_diffusion(ens)
        print("\neffective diffusion (½ dK/dt over the second half):", np.array2string(np.asarray(d_eff), precision=5))
    if args.scene == "ball-on-vibrating-plane":
        from nhsde.scenes import ball_covariances

        kxx, kxu, kuu = ball_covariances(ens.ts[last], p.eps, p.nu, p.delta)
        print(f"closed form (S0 (3.1)): k_xx={float(kxx):.6g}  k_xu={float(kxu):.6g}  k_uu={float(kuu):.6g}")
    if args.out:
        meta = {
            "format": "nhsde-simulate", "format_version": FORMAT_VERSION, "scene": args.scene,
            "parameters": {k: float(getattr(p, k)) for k, *_ in p.describe()}, "names": list(names),
            "roles": list(ens.roles), "paths": args.paths, "t1": args.t1, "dt": args.dt, "solver": args.solver,
            "seed": args.seed, "x64": bool(args.x64), "versions": _versions(),
        }
        np.savez(
            args.out, ts=ens.ts, mean=ens.mean, cov=ens.cov, mean_se=ens.mean_se, cov_se=ens.cov_se,
            failed=ens.failed, d_mean_d_eps=d_eps[0], d_mean_d_nu=d_nu[0], d_cov_d_eps=d_eps[1],
            d_cov_d_nu=d_nu[1], metadata=json.dumps(meta),
        )
        print(f"\nsaved {args.out}")
    return 0


def _versions():
    from importlib.metadata import version

    return {pkg: version(pkg) for pkg in ("nhsde", "jax", "jaxlib", "diffrax", "equinox")}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nhsde", description="Stochastic nonholonomic mechanics in JAX.")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("scenes", help="list the scenes and their parameters")
    sim = sub.add_parser("simulate", help="simulate a scene; print drift statistics and their gradients")
    sim.add_argument("scene", help="scene name, see `nhsde scenes`")
    sim.add_argument("--paths", type=int, default=4096, help="number of paths (default 4096)")
    sim.add_argument("--t1", type=float, default=10.0, help="final time (default 10)")
    sim.add_argument("--dt", type=float, default=0.01, help="time step (default 0.01)")
    sim.add_argument("--solver", default="euler", help="euler, milstein, heun or sra1 (default euler)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--save-points", type=int, default=11, help="save times from 0 to t1 (default 11)")
    sim.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a scene parameter")
    sim.add_argument("--out", help="save the results to this .npz file")
    sim.add_argument("--x64", action="store_true", help="compute in float64")
    sim.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "scenes":
        return _cmd_scenes(args)
    return _cmd_simulate(args)


if __name__ == "__main__":
    sys.exit(main())
