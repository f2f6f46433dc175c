"""Drift statistics at a requested accuracy for the least work: plain Monte Carlo against the new estimators.

    python benchmarks/estimators.py [--quick] [--scenes ball,sleigh,chaplygin-ball,body] [--out FILE]

For each scene and statistic with an exact value (ball: K_xx(t1), S0 (3.1); sleigh:
E[H](t1) = H0 e^{−4εt1} + ν(1 − e^{−4εt1})/(4ε); Chaplygin's ball: the stationary
E[H] = 3ν/(8ε); the body on the vibrating plane has state-dependent noise and no
closed form, its reference is a fine weak-order-2 run) it measures, in one
process, float64:

1. the warm cost of a path-step of every solver (best of ``--rounds`` interleaved
   runs; PlatenWeak2 ≤ 3× Euler is the target);
2. each solver's weak error at a few steps (with its Monte-Carlo standard error):
   where the weak error enters the Monte-Carlo band, and the bias model ``C h^p``;
3. plain Monte Carlo at its best step for each target RMSE ε (modelled: the
   cheapest ``(h, N)`` with ``C²h^{2p} + σ²/N = ε²``, time = N·steps·cost; one
   target is also run to check the model), and Richardson–Romberg extrapolation
   likewise (its bias ``C' h^{p+1}`` and paired variance measured);
4. multilevel Monte Carlo (Euler, PlatenWeak2 with Gaussian increments, and
   antithetic on the sleigh) run at every target: wall time after one piece on
   every level compiled its programs, path-steps, realised error, levels;
5. the time to reach RMSE = 1e-3·|value| of the best new estimator against the
   best plain-MC setting, and the cost-vs-RMSE slopes (theory: plain Euler −3,
   extrapolated Euler −2.5, MLMC −2).

Writes benchmarks/results/estimators.json and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import nhsde  # noqa: E402
from nhsde.scenes import (  # noqa: E402
    BallOnVibratingPlane,
    BodyOnVibratingPlane,
    ChaplyginBall,
    ChaplyginSleigh,
    ball_covariances,
)
from nhsde.statistics import extrapolate, multilevel_monte_carlo  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
GAUSS = nhsde.PlatenWeak2(increments="gaussian")


def run_seconds(fn):
    """``(fn(), wall seconds)`` of a warm call: ``fn`` runs once untimed to compile."""
    jax.block_until_ready(fn())
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - start


def ball_case():
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    return dict(
        name="ball",
        system=scene.build(),
        y0=jnp.zeros(4),
        t1=2.0,
        target=("cov", "x", "x"),
        save=nhsde.Save(names=("x",), n=2),
        exact=float(ball_covariances(jnp.float64(2.0), 1.0, 1.0, 1 / 1.4)[0]),
        solvers={"euler": 1, "heun2": 2, "sra1": 2, "weak2": 2},
        paired={"euler": 1, "heun2": 2, "sra1": 2, "weak2-gauss": 2},
        dts=[1 / 4, 1 / 8, 1 / 16],
        h0=0.5,
        multilevel=[("euler", False), ("weak2-gauss", False)],
    )


def sleigh_case():
    eps, nu, t1 = 0.5, 1.0, 2.0
    scene = ChaplyginSleigh(eps=eps, nu=nu, drift=False)
    y0 = jnp.array([1.0, 0.5])
    h0 = 0.5 * (1.0 + 2.0 * 0.25)  # H0 = ½(m v² + J ω²), J = I + m a² = 2
    return dict(
        name="sleigh",
        system=scene.build(),
        y0=y0,
        t1=t1,
        target=("mean", "energy"),
        save=nhsde.Save(names=("energy",), n=2),
        exact=h0 * math.exp(-4 * eps * t1) + nu * (1 - math.exp(-4 * eps * t1)) / (4 * eps),
        solvers={"euler": 1, "heun2": 2, "sra1": 2, "weak2": 2},
        paired={"euler": 1, "heun2": 2, "sra1": 2, "weak2-gauss": 2},
        dts=[1 / 4, 1 / 8, 1 / 16],
        h0=0.5,
        multilevel=[("euler", False), ("weak2-gauss", False), ("euler", True)],
    )


def chaplygin_ball_case():
    eps, nu = 1.0, 2.0
    scene = ChaplyginBall(eps=eps, nu=nu)
    return dict(
        name="chaplygin-ball",
        system=scene.build(),
        y0=scene.initial_state().astype(jnp.float64),
        t1=4.0,
        target=("mean", "energy"),
        save=nhsde.Save(names=("energy",), n=2),
        exact=3 * nu / (8 * eps),
        solvers={"euler": 1, "heun2": 2, "sra1": 2, "weak2": 2},
        paired={"euler": 1, "heun2": 2, "sra1": 2, "weak2-gauss": 2},
        dts=[1 / 8, 1 / 16, 1 / 32],
        h0=0.125,
        multilevel=[("euler", False), ("weak2-gauss", False)],
    )


def body_case():
    """State-dependent noise (3 channels), no closed form: the reference is PlatenWeak2 (Gaussian) at h = 1/64."""
    scene = BodyOnVibratingPlane(eps=0.5, nu=1.0)
    return dict(
        name="body",
        system=scene.build(),
        y0=scene.initial_state().astype(jnp.float64),
        t1=1.0,
        target=("mean", "energy"),
        save=nhsde.Save(names=("energy",), n=2),
        exact=None,
        solvers={"euler": 1, "heun2": 2, "weak2": 2},
        paired={"euler": 1, "heun2": 2, "weak2-gauss": 2},
        dts=[1 / 8, 1 / 16, 1 / 32],
        h0=0.125,
        multilevel=[("euler", False), ("weak2-gauss", False)],
    )


CASES = {"ball": ball_case, "sleigh": sleigh_case, "chaplygin-ball": chaplygin_ball_case, "body": body_case}


def solver_object(name):
    return GAUSS if name == "weak2-gauss" else name


def simulate(case, solver, dt, n_paths, key=0):
    return nhsde.simulate(
        case["system"],
        case["y0"],
        jax.random.key(key),
        n_paths=n_paths,
        t1=case["t1"],
        dt=dt,
        solver=solver_object(solver),
        save=case["save"],
    )


def pick(case, ens):
    """(value, standard error, per-path variance) of the case's target in an Ensemble or Estimate."""
    mean, cov, mean_se, cov_se = ens.select(case["save"].names)
    if case["target"][0] == "mean":
        value, se = mean[-1, 0], mean_se[-1, 0]
    else:
        value, se = cov[-1, 0, 0], cov_se[-1, 0, 0]
    return float(value), float(se)


def step_costs(case, dt, n_paths, rounds):
    """Warm seconds per path-step of every solver, best of ``rounds`` interleaved runs."""
    names = list(case["solvers"]) + (["weak2-gauss"] if "weak2" in case["solvers"] else [])
    for s in names:
        jax.block_until_ready(simulate(case, s, dt, n_paths).mean)
    best = {s: math.inf for s in names}
    for _ in range(rounds):
        for s in names:
            start = time.perf_counter()
            jax.block_until_ready(simulate(case, s, dt, n_paths).mean)
            best[s] = min(best[s], time.perf_counter() - start)
    steps = round(case["t1"] / dt)
    return {s: t / (n_paths * steps) for s, t in best.items()}


def fit_bias(hs, errors, ses, p):
    """``C`` of ``bias = C h^p`` by weighted least squares, and whether any point is resolved (|error| > 3 SE)."""
    hs, errors, ses = map(np.asarray, (hs, errors, ses))
    w = 1 / ses**2
    return float(np.sum(w * errors * hs**p) / np.sum(w * hs ** (2 * p))), bool(np.any(np.abs(errors) > 3 * ses))


def cheapest(t1, cost_per_step, sigma2, c, p, eps, h_max, steps_per_h=1.0):
    """Cheapest (seconds, h, N) with C²h^{2p} + σ²/N ≤ ε², h = t1/n ≤ h_max (the bias model is measured up to h_max)."""
    best = (math.inf, None, None)
    for n in range(math.ceil(t1 / h_max - 1e-9), 1 << 16):
        h = t1 / n
        room = eps**2 - (c * h**p) ** 2
        if room <= 0:
            continue
        n_paths = math.ceil(sigma2 / room)
        seconds = n_paths * n * steps_per_h * cost_per_step
        best = min(best, (seconds, h, n_paths))
        if (c * h**p) ** 2 < 0.01 * eps**2:
            break
    return best


def slope(xs, ys):
    ok = [(x, y) for x, y in zip(xs, ys) if np.isfinite(y) and y > 0]
    if len(ok) < 2:
        return float("nan")
    x, y = np.log([a for a, _ in ok]), np.log([b for _, b in ok])
    return float(np.polyfit(x, y, 1)[0])


def run_case(case, args):
    out = dict(name=case["name"], target=list(case["target"]))
    t1 = case["t1"]
    # reference
    if case["exact"] is None:
        ref = simulate(case, "weak2-gauss", case["dts"][-1] / 2, args.reference_paths, key=99)
        value, se = pick(case, ref)
        case["exact"] = value
        out["reference"] = dict(value=value, se=se, dt=case["dts"][-1] / 2, n_paths=args.reference_paths)
    exact = case["exact"]
    out["exact"] = exact
    print(f"\n[{case['name']}] target {case['target']} at t1={t1}: exact {exact:.6g}")

    # 1. step costs
    costs = step_costs(case, case["dts"][1], args.paths, args.rounds)
    out["seconds_per_path_step"] = costs
    print(
        "  warm cost per path-step relative to euler: "
        + ", ".join(f"{s} {c / costs['euler']:.2f}" for s, c in costs.items())
    )

    # 2. weak errors against the exact value: where each solver enters the Monte-Carlo band
    rows, models = [], {}
    for solver, p in case["solvers"].items():
        errs, ses = [], []
        for h in case["dts"]:
            try:
                value, se = pick(case, simulate(case, solver, h, args.paths, key=1))
            except nhsde.SimulationError:
                value, se = math.nan, math.nan
            errs.append(value - exact)
            ses.append(se)
            rows.append(dict(solver=solver, dt=h, error=value - exact, se=se))
        in_band = [h for h, e, s in zip(case["dts"], errs, ses) if np.isfinite(e) and abs(e) <= 2 * s]
        print(
            f"  {solver:<8} weak error/SE at dt {case['dts']}: "
            + ", ".join(f"{e / s:+.1f}" if np.isfinite(e) else "fail" for e, s in zip(errs, ses))
            + f"  (SE {np.nanmedian(ses):.2g}, {args.paths} paths); largest dt in the MC band: "
            + (f"{max(in_band):g}" if in_band else "-")
        )
        if solver == "weak2":  # three-point: no shared path, so its bias model comes from these errors
            good = [k for k, e in enumerate(errs) if np.isfinite(e)]
            c, resolved = fit_bias([case["dts"][k] for k in good], [errs[k] for k in good], [ses[k] for k in good], p)
            models[solver] = dict(p=p, c=c, resolved=resolved, sigma2=float(np.nanmedian(ses) ** 2 * args.paths))
    out["weak_errors"] = rows

    # 3. paired runs on one Brownian path (extrapolate): −correction is the bias of S(h/2) (plain model),
    #    the extrapolated value's error the bias C' h^{p+1} (extrapolation model)
    extrap = {}
    for solver, p in case["paired"].items():
        fine, corr, ex = [], [], []
        hs = case["dts"][:2]
        for h in hs:
            try:
                est = extrapolate(
                    case["system"],
                    case["y0"],
                    jax.random.key(2),
                    n_paths=args.paths,
                    t1=t1,
                    dt=h,
                    solver=solver_object(solver),
                    order=p,
                    save=case["save"],
                )
            except nhsde.SimulationError:
                continue
            fine.append(pick(case, est.fine))
            corr.append(pick(case, est.correction))
            ex.append(pick(case, est))
        if not fine:
            continue
        halves = [h / 2 for h in hs[: len(fine)]]
        c, resolved = fit_bias(halves, [-v for v, _ in corr], [se for _, se in corr], p)
        sigma2 = float(np.median([se**2 for _, se in fine])) * args.paths
        models[solver] = dict(p=p, c=c, resolved=resolved, sigma2=sigma2)
        c_ex, resolved_ex = fit_bias(hs[: len(ex)], [v - exact for v, _ in ex], [se for _, se in ex], p + 1)
        extrap[solver] = dict(
            p=p + 1,
            c=c_ex,
            resolved=resolved_ex,
            sigma2=float(np.median([se**2 for _, se in ex])) * args.paths,
            cost=costs[solver],
        )
        print(
            f"  paired {solver:<11} bias of S(h/2) at h/2 = {halves}: "
            + ", ".join(f"{-v:+.2e}±{se:.1e}" for v, se in corr)
            + f" → {abs(c):.3g}·h^{p}{'' if resolved else ' (unresolved)'}; extrapolated error/SE: "
            + ", ".join(f"{(v - exact) / se:+.1f}" for v, se in ex)
            + f" → {abs(c_ex):.3g}·h^{p + 1}{'' if resolved_ex else ' (unresolved)'}"
        )
    out["bias_models"], out["extrapolation_models"] = models, extrap

    # 4. modelled plain MC and extrapolation, measured MLMC
    targets = [r * abs(exact) for r in args.targets]
    plain, ex_rows, ml_rows = [], [], []
    for eps in targets:
        best_plain = None
        for solver, m in models.items():
            sec, h, n = cheapest(t1, costs[solver], m["sigma2"], m["c"], m["p"], eps, case["dts"][0])
            plain.append(dict(eps=eps, solver=solver, seconds=sec, dt=h, n_paths=n))
            if best_plain is None or sec < best_plain["seconds"]:
                best_plain = plain[-1]
        for solver, m in extrap.items():
            sec, h, n = cheapest(t1, m["cost"], m["sigma2"], m["c"], m["p"], eps, case["dts"][0], steps_per_h=3.0)
            ex_rows.append(dict(eps=eps, solver=solver, seconds=sec, dt=h, n_paths=n))
        print(
            f"  ε = {eps:.3g} ({eps / abs(exact):.0e} rel.): best plain MC {best_plain['solver']} "
            f"dt={best_plain['dt']:.4g} "
            f"N={best_plain['n_paths']} ≈ {best_plain['seconds']:.3g} s (modelled)"
        )
    for solver, anti in case["multilevel"]:
        label = solver + (" + antithetic" if anti else "")
        levels = 11 if solver == "euler" else 6
        warm = tuple(max(64, (args.piece_paths >> ell) // 64 * 64) for ell in range(levels))
        ml_args = dict(t1=t1, dt=case["h0"], target=case["target"], solver=solver_object(solver), save=case["save"])
        ml_args.update(antithetic=anti, piece_paths=args.piece_paths)
        try:  # one piece on every level: compiles each level's programs before the timed runs
            multilevel_monte_carlo(case["system"], case["y0"], jax.random.key(0), n_paths=warm, **ml_args)
        except nhsde.SimulationError:
            pass
        for eps in targets:

            def ml(eps=eps):
                return multilevel_monte_carlo(case["system"], case["y0"], jax.random.key(3), rmse=eps, **ml_args)

            try:
                start = time.perf_counter()
                est = ml()
                sec = time.perf_counter() - start
            except (nhsde.SimulationError, ValueError) as e:
                print(f"  MLMC {label:<20} ε={eps:.3g}: {type(e).__name__}: {str(e)[:120]}")
                continue
            modelled = est.cost * costs[solver]
            row = dict(
                solver=label,
                eps=eps,
                seconds=sec,
                modelled_seconds=modelled,
                path_steps=est.cost,
                value=float(est.value),
                se=float(est.standard_error),
                bias_estimate=float(est.bias),
                error=float(est.value) - exact,
                n_paths=list(est.n_paths_per_level),
            )
            ml_rows.append(row)
            print(
                f"  MLMC {label:<20} ε={eps:.3g}: {sec:7.2f} s run ({modelled:.3g} s modelled), "
                f"{est.cost:.3g} path-steps, error {row['error']:+.2e} (SE {row['se']:.1e}, "
                f"bias est. {row['bias_estimate']:.1e}), "
                f"N_ℓ {row['n_paths']}"
            )
    out["plain_modelled"], out["extrapolation_modelled"], out["multilevel"] = plain, ex_rows, ml_rows

    # check the plain-MC model at the loosest target: run its best setting
    first = min((r for r in plain if r["eps"] == targets[0]), key=lambda r: r["seconds"])
    ens, sec = run_seconds(lambda: simulate(case, first["solver"], first["dt"], first["n_paths"], key=4))
    value, se = pick(case, ens)
    out["plain_check"] = dict(**first, measured_seconds=sec, error=value - exact, se=se)
    print(
        f"  check: plain {first['solver']} dt={first['dt']:.4g} N={first['n_paths']}: {sec:.2f} s run "
        f"(model {first['seconds']:.2f} s), error {value - exact:+.2e} (target ε {targets[0]:.2e}, SE {se:.1e})"
    )

    # 5. summary at the tightest target, slopes
    eps = targets[-1]
    best_plain = min((r for r in plain if r["eps"] == eps), key=lambda r: r["seconds"])
    new = [dict(kind="MLMC " + r["solver"], seconds=r["seconds"]) for r in ml_rows if r["eps"] == eps]
    new += [dict(kind="extrapolated " + r["solver"], seconds=r["seconds"]) for r in ex_rows if r["eps"] == eps]
    best_new = min(new, key=lambda r: r["seconds"])
    out["summary"] = dict(
        eps=eps, best_plain=best_plain, best_new=best_new, ratio=best_plain["seconds"] / best_new["seconds"]
    )
    # slopes over the targets from 1e-2 down: at looser ones MLMC's whole pieces of samples dominate
    tight = [e for e in targets if e <= 1.001e-2 * abs(exact)]

    def series(rows, solver, key):
        return [r[key] for r in rows if r["solver"] == solver and r["eps"] in tight]

    slopes = {
        "plain euler (modelled)": slope(tight, series(plain, "euler", "seconds")),
        "extrapolated euler (modelled)": slope(tight, series(ex_rows, "euler", "seconds")),
    }
    for label in dict.fromkeys(r["solver"] for r in ml_rows):
        rs = [r for r in ml_rows if r["solver"] == label and r["eps"] in tight]
        slopes[f"MLMC {label} (path-steps)"] = slope([r["eps"] for r in rs], [r["path_steps"] for r in rs])
        slopes[f"MLMC {label} (run seconds)"] = slope([r["eps"] for r in rs], [r["seconds"] for r in rs])
    out["slopes"] = slopes
    print(
        f"  RMSE {eps:.2e} ({args.targets[-1]:.0e}·|value|): best plain MC {best_plain['solver']} "
        f"{best_plain['seconds']:.3g} s (modelled) vs best new {best_new['kind']} {best_new['seconds']:.3g} s: "
        f"{out['summary']['ratio']:.1f}× less time"
    )
    print("  cost-vs-RMSE slopes: " + ", ".join(f"{k} {v:+.2f}" for k, v in slopes.items()))
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer paths, looser targets")
    parser.add_argument(
        "--scenes", default="ball,sleigh,chaplygin-ball", help=f"comma-separated, from {', '.join(CASES)}"
    )
    parser.add_argument("--paths", type=int, default=16384, help="paths per weak-error and step-cost run")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--piece-paths", type=int, default=65536, help="MLMC paths per run on level 0")
    parser.add_argument("--reference-paths", type=int, default=2**18)
    parser.add_argument("--out", help="the JSON to write (default results/estimators.json, _quick with --quick)")
    args = parser.parse_args()
    args.targets = [3e-2, 1e-2, 3e-3] if args.quick else [3e-2, 1e-2, 3e-3, 1e-3]
    if args.quick:
        args.paths, args.rounds, args.piece_paths, args.reference_paths = 4096, 1, 8192, 2**15
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = [s for s in names if s not in CASES]
    if unknown:
        parser.error(f"--scenes: unknown {unknown}; choose from {', '.join(CASES)}")
    start = time.perf_counter()
    machine = dict(
        cpu_count=os.cpu_count(),
        platform=platform.platform(),
        versions=dict(jax=jax.__version__, nhsde=nhsde.__version__),
        devices=[str(d) for d in jax.devices()],
        loadavg_start=os.getloadavg(),
    )
    print(f"machine: {machine}")
    results = [run_case(CASES[name](), args) for name in names]
    machine["loadavg_end"] = os.getloadavg()
    machine["wall_seconds"] = time.perf_counter() - start
    print(
        f"\nload average {machine['loadavg_start']} → {machine['loadavg_end']}, {machine['wall_seconds']:.0f} s in all"
    )
    OUT.mkdir(exist_ok=True)
    suffix = "_quick" if args.quick else ""
    path = pathlib.Path(args.out) if args.out else OUT / f"estimators{suffix}.json"
    path.write_text(json.dumps(dict(machine=machine, args=vars(args), cases=results), indent=2, default=str))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
