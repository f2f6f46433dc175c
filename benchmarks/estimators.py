"""Drift statistics at a requested accuracy for the least work: plain Monte Carlo against the new estimators.

    python benchmarks/estimators.py [--quick] [--scenes ball,sleigh,chaplygin-ball,body] [--out FILE]
    python benchmarks/estimators.py --first-answer [--quick] [--src DIR] [--rows ROWS] [--out FILE]

Warm mode (the default):

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

First-answer mode (``--first-answer``): every measurement in a fresh Python process, compilation
included (this file run as ``--child ROW`` by :mod:`subprocess` with ``sys.executable``; JAX's
persistent compilation cache off unless the row is about it), float64:

(a) ``to_accuracy`` (absolute RMSE = rel·|value|) against the best plain ``simulate`` setting
    for that accuracy (solver, dt, N as recorded by the warm mode, ``BEST_PLAIN``), on the sleigh
    (``ChaplyginSleigh(drift=False)``, E[H](2)), Chaplygin's ball (E[H](4)) and the body on the
    vibrating plane (E[H](1)), at relative RMSE 1e-2 and 1e-3: seconds of the first call
    (imports excluded, compilation included), XLA programs compiled, realised error against the
    exact value (the body: against the recorded reference, whose own SE is 6.6e-4);
(b) the same call again in the same process (warm: nothing left to compile), and for ``to_accuracy`` a
    third time (its second call can still compile: it prices more pilots when its first pilot ran fast);
(c) the command: ``nhsde simulate chaplygin-sleigh --relative-rmse 1e-2`` against the plain
    ``nhsde simulate chaplygin-sleigh`` (defaults), wall seconds of each process;
(d) the persistent compilation cache: the README's main job
    (``nhsde simulate ball-on-vibrating-plane --paths 4096 --t1 10 --dt 0.01``) and the ``--rmse``
    command, each run twice with ``NHSDE_COMPILATION_CACHE`` set to a new empty folder: the second
    process (cache warm) against the first (cold).

``to_accuracy`` runs with its default coarsest step; where that fails (Chaplygin's ball at
b9742d2: 3 of 1024 pilot paths fail at h0 = t1/4 = 1), the row is run again at the warm mode's
h0 (``SCENE:REL:to_accuracy:dt=H``).  ``--quick``: the sleigh at 1e-2 only (``--scenes`` to
choose), (c), and (d) for the main job only (a few minutes, most of it to_accuracy compiling).
``--src DIR``: this process and its children import nhsde from DIR, e.g. a clean
``git archive HEAD src | tar -x -C /tmp/clean`` while the work tree is being edited.
``--rows``: only these (a, b) rows; ``SCENE:REL:mlqmc[:dt=H][:solver=NAME]`` is
:func:`nhsde.statistics.multilevel_quasi_monte_carlo` at the case's h0 (Euler unless named), measured
the same way (first, warm, programs, realised error) and paired with the plain row in the table.  Writes
benchmarks/results/first_answer.json (``_quick`` with ``--quick``) after every row and prints the table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

import jax

for _i, _arg in enumerate(sys.argv[:-1]):  # --src DIR: this process imports nhsde from there too, not the work tree
    if _arg == "--src":
        sys.path.insert(0, str(pathlib.Path(sys.argv[_i + 1]).resolve()))
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
        ml_args = dict(t1=t1, dt=case["h0"], statistic=case["target"], solver=solver_object(solver), save=case["save"])
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
            value, se = est.value()
            modelled = est.cost.path_steps * costs[solver]
            row = dict(
                solver=label,
                eps=eps,
                seconds=sec,
                modelled_seconds=modelled,
                path_steps=est.cost.path_steps,
                value=float(value),
                se=float(se),
                bias_estimate=float(est.bias),
                error=float(value) - exact,
                n_paths=list(est.n_paths_per_level),
            )
            ml_rows.append(row)
            print(
                f"  MLMC {label:<20} ε={eps:.3g}: {sec:7.2f} s run ({modelled:.3g} s modelled), "
                f"{est.cost.path_steps:.3g} path-steps, error {row['error']:+.2e} (SE {row['se']:.1e}, "
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


# ---------------------------------------------------------------------------------------------------------------
# First-answer mode: a fresh process per row, compilation included

# The best plain-MC setting (solver, dt, paths) per scene and relative RMSE, as the warm mode chose it
# (results/estimators.json, results/estimators_body.json: the cheapest modelled (h, N) over the solvers).
BEST_PLAIN = {
    ("sleigh", 1e-2): ("weak2", 2 / 11, 11951),
    ("sleigh", 1e-3): ("weak2", 2 / 33, 1255586),
    ("chaplygin-ball", 1e-2): ("weak2", 1 / 23, 8276),
    ("chaplygin-ball", 1e-3): ("weak2", 1 / 73, 824462),
    ("body", 1e-2): ("heun2", 1 / 8, 1151),
    ("body", 1e-3): ("heun2", 1 / 8, 119258),
}
# The body has no closed form: the warm mode's reference (weak2-gauss, h = 1/64, 2^18 paths, key 99).
BODY_REFERENCE = (0.9772047653522702, 0.0006581949898250264)
FIRST_ANSWER_SCENES = ("sleigh", "chaplygin-ball", "body")
MAIN_JOB = ["simulate", "ball-on-vibrating-plane", "--paths", "4096", "--t1", "10", "--dt", "0.01"]
CLI_PLAIN = ["simulate", "chaplygin-sleigh"]
CLI_RMSE = ["simulate", "chaplygin-sleigh", "--relative-rmse", "1e-2"]


def count_compilations():
    """A list that collects the names of the XLA programs compiled from now on (``jax_log_compiles``)."""
    import logging

    compiled = []

    class Count(logging.Handler):
        def emit(self, record):
            message = record.getMessage()
            if message.startswith("Compiling "):
                compiled.append(message.split(" ")[1])

    logging.getLogger("jax").addHandler(Count())
    logging.getLogger("jax").setLevel(logging.WARNING)
    jax.config.update("jax_log_compiles", True)
    return compiled


def child(row):
    """One row ``SCENE:REL:METHOD`` (METHOD ``to_accuracy`` or ``plain``) in this fresh process: the first call
    (compilation included), then the same call again (warm); prints one JSON line."""
    scene, rel, method, *option = row.split(":")  # option: dt=H, the coarsest step (to_accuracy: default its own)
    rel = float(rel)
    options = dict(o.split("=") for o in option)  # dt=H; mlqmc also solver=NAME (default euler)
    h0 = float(options["dt"]) if "dt" in options else None
    compiled = count_compilations()
    case = CASES[scene]()
    exact = BODY_REFERENCE[0] if case["exact"] is None else case["exact"]
    eps = rel * abs(exact)
    out = dict(row=row, scene=scene, rel=rel, method=method, rmse=eps, exact=exact, reference=case["exact"] is None)
    out["dt"] = h0

    def call():
        if method == "plain":
            solver, dt, n_paths = BEST_PLAIN[(scene, rel)]
            ens = simulate(case, solver, dt, n_paths, key=4)
            jax.block_until_ready(ens.mean)
            value, se = pick(case, ens)
            return value, se, dict(solver=solver, dt=dt, n_paths=n_paths)
        if method == "mlqmc":  # multilevel randomised QMC at the case's h0 ((t1 − t0)/h0 a power of two)
            solver = options.get("solver", "euler")
            est = nhsde.statistics.multilevel_quasi_monte_carlo(
                case["system"],
                case["y0"],
                jax.random.key(6),
                t1=case["t1"],
                dt=case["h0"] if h0 is None else h0,
                statistic=case["target"],
                rmse=eps,
                solver=solver_object(solver),
                save=case["save"],
            )
            value, se = est.value()
            extra = dict(
                choice=f"MLQMC {solver}, {len(est.n_paths_per_level)} levels, N_l·R {list(est.n_paths_per_level)}",
                bias_estimate=float(est.bias),
                work=est.cost.path_steps,
                compile_seconds=est.cost.compile_seconds,
            )
            return float(value), float(se), extra
        res = nhsde.statistics.to_accuracy(
            case["system"],
            case["y0"],
            jax.random.key(5),
            t1=case["t1"],
            statistic=case["target"],
            rmse=eps,
            dt=h0,
            save=case["save"],
        )
        if hasattr(res, "cost"):  # after f3f3b27: value() and Cost records
            value, se = res.value()
            extra = dict(
                work=res.cost.path_steps,
                pilot_work=res.pilot_cost.path_steps,
                predicted_work=res.predicted.path_steps,
                compile_seconds=res.cost.compile_seconds,
                run_seconds=res.run_cost.seconds,
            )
        else:
            value, se = res.value, res.standard_error
            extra = dict(
                work=res.work,
                pilot_work=res.pilot_work,
                predicted_work=res.predicted_work,
                compile_seconds=res.compile_seconds,
                run_seconds=res.run_seconds,
            )
        return float(value), float(se), dict(choice=res.choice, bias_estimate=res.bias, **extra)

    # a third call where the second still compiled (to_accuracy prices further pilots when its first pilot ran
    # fast, i.e. when warm): the call with nothing left to compile
    for phase in ("first", "warm") if method == "plain" else ("first", "warm", "third"):
        del compiled[:]
        start = time.perf_counter()
        value, se, extra = call()
        out[phase] = dict(
            seconds=time.perf_counter() - start,
            compilations=len(compiled),
            value=value,
            se=se,
            error=value - exact,
            **extra,
        )
        print(json.dumps(out), flush=True)  # after each phase: a row stopped at its time limit keeps its first answer


def nhsde_command():
    """The ``nhsde`` command of this interpreter's environment (``python -m nhsde.runs`` without one)."""
    script = pathlib.Path(sys.executable).with_name("nhsde")
    return [str(script)] if script.exists() else [sys.executable, "-m", "nhsde.runs"]


CHILD_SRC = ""


def fresh_process(argv, cache="off", timeout=None):
    """Run ``argv`` in a new process (CPU, compilation cache ``cache``): (wall seconds, rc, stdout, stderr)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", NHSDE_COMPILATION_CACHE=str(cache))
    if CHILD_SRC:  # --src: the children import nhsde from there (e.g. a clean `git archive` of one commit)
        env["PYTHONPATH"] = CHILD_SRC
    start = time.perf_counter()
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        text = [x.decode(errors="replace") if isinstance(x, bytes) else (x or "") for x in (e.stdout, e.stderr)]
        return time.perf_counter() - start, "timeout", *text
    return time.perf_counter() - start, proc.returncode, proc.stdout, proc.stderr


def api_row(row, timeout):
    wall, rc, stdout, stderr = fresh_process([sys.executable, __file__, "--child", row], timeout=timeout)
    lines = [line for line in (stdout or "").splitlines() if line.startswith("{")]
    if not lines:
        tail = (stderr or "").strip().splitlines()[-3:]
        print(f"  {row}: rc {rc} after {wall:.1f} s: {' | '.join(tail)}", flush=True)
        return dict(row=row, process_seconds=wall, rc=rc, error_tail=tail)
    out = json.loads(lines[-1])
    out.update(process_seconds=wall, rc=rc)
    f = out["first"]
    w = out.get("warm", dict(seconds=math.nan, compilations=-1))
    how = f.get("choice") or "{solver} dt={dt:.4g} N={n_paths}".format(**f)
    print(
        f"  {row:<32} first {f['seconds']:7.2f} s ({f['compilations']:3d} programs, process {wall:6.1f} s, rc {rc}), "
        f"warm {w['seconds']:7.2f} s ({w['compilations']} programs); error {f['error']:+.2e} "
        f"(target {out['rmse']:.2e}, SE {f['se']:.1e}); {how}",
        flush=True,
    )
    return out


def cli_row(label, argv, cache, timeout):
    wall, rc, stdout, stderr = fresh_process(nhsde_command() + argv, cache=cache, timeout=timeout)
    lines = (stdout or "").strip().splitlines()
    work = [line for line in lines if line.startswith("work:")]
    compile_split = [line.rsplit(";", 1)[-1].strip() for line in lines if "of it compiling" in line]
    print(
        f"  {label:<32} {wall:7.1f} s (process, rc {rc})"
        + (f"; {work[-1]}" if work else "")
        + (f" ({compile_split[-1]})" if compile_split else ""),
        flush=True,
    )
    if rc != 0:
        print("    " + " | ".join((stderr or "").strip().splitlines()[-3:]), flush=True)
    compiling = [line for line in lines if "of it compiling" in line]  # to_accuracy's own split of its seconds
    return dict(
        label=label, argv=argv, cache=str(cache), seconds=wall, rc=rc, report=compiling, stdout_tail=lines[-12:]
    )


def first_answer(args):
    """Rows (a)–(d) of the first-answer mode (module docstring); writes the JSON, prints the table."""
    global CHILD_SRC
    CHILD_SRC = str(pathlib.Path(args.src).resolve()) if args.src else ""
    rels = [1e-2] if args.quick else [1e-2, 1e-3]
    scenes = [s for s in args.scenes.split(",") if s in FIRST_ANSWER_SCENES] if args.scenes_given else None
    scenes = scenes or (["sleigh"] if args.quick else list(FIRST_ANSWER_SCENES))
    start = time.perf_counter()
    revision = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--short", "src"], capture_output=True, text=True).stdout.strip()
    machine = dict(
        cpu_count=os.cpu_count(),
        platform=platform.platform(),
        versions=dict(jax=jax.__version__, nhsde=nhsde.__version__),
        git=revision,
        src_uncommitted=[] if args.src else dirty.splitlines(),
        src=args.src or str(pathlib.Path(nhsde.__file__).parents[1]),
        date=time.strftime("%Y-%m-%d %H:%M %Z"),
        loadavg_start=os.getloadavg(),
    )
    print(f"machine: {machine}", flush=True)
    OUT.mkdir(exist_ok=True)
    path = pathlib.Path(args.out) if args.out else OUT / f"first_answer{'_quick' if args.quick else ''}.json"
    api, cli, cache = [], [], []
    record = dict(machine=machine, args=vars(args), best_plain={f"{k[0]}:{k[1]:g}": v for k, v in BEST_PLAIN.items()})
    record.update(to_accuracy_vs_plain=api, cli=cli, cache=cache)

    def save():  # after every row: a run cut short keeps what it measured
        path.write_text(json.dumps(record, indent=2, default=str))

    def pairs(rel):
        print(f"(a, b) to_accuracy against the best plain simulate setting at {rel:g}, each a fresh process:")
        for scene in scenes:
            for method in ("to_accuracy", "plain"):
                api.append(api_row(f"{scene}:{rel:g}:{method}", args.row_timeout))
                save()
                if method == "to_accuracy" and api[-1]["rc"] not in (0, "timeout"):
                    # the default coarsest step failed (Chaplygin's ball at b9742d2): the warm mode's h0
                    api.append(api_row(f"{scene}:{rel:g}:{method}:dt={CASES[scene]()['h0']:g}", args.row_timeout))
                    save()

    if args.rows:  # only these rows (SCENE:REL:METHOD[:dt=H]), e.g. to complete a run
        for row in args.rows.split(","):
            api.append(api_row(row, args.row_timeout))
            save()
        record["table"] = first_answer_table(api, cli, cache)
        save()
        print("\n" + record["table"] + f"\nwrote {path}")
        return
    pairs(rels[0])  # the tighter target last: its rows take longest
    print("(c) the command, each a fresh process, cache off:", flush=True)
    cli.append(cli_row("nhsde --relative-rmse 1e-2", CLI_RMSE, "off", args.row_timeout))
    cli.append(cli_row("nhsde (plain)", CLI_PLAIN, "off", args.row_timeout))
    save()
    print("(d) the persistent compilation cache: a new empty folder, then the same command again:", flush=True)
    jobs = ([] if args.quick else [("--relative-rmse 1e-2", CLI_RMSE)]) + [("main job", MAIN_JOB)]
    for label, argv in jobs:
        with tempfile.TemporaryDirectory(prefix="nhsde-cache-") as folder:
            for state in ("cold", "warm"):
                cache.append(cli_row(f"{label}, cache {state}", argv, folder, args.row_timeout))
                save()
    for rel in rels[1:]:
        pairs(rel)
    machine["loadavg_end"] = os.getloadavg()
    machine["wall_seconds"] = time.perf_counter() - start
    record["table"] = first_answer_table(api, cli, cache)
    save()
    print("\n" + record["table"])
    print(
        f"\nload average {machine['loadavg_start']} → {machine['loadavg_end']}, {machine['wall_seconds']:.0f} s in all"
    )
    print(f"wrote {path}")


def first_answer_table(api, cli, cache):
    """The markdown table of the first-answer rows: seconds, realised error, ratio."""
    lines = [
        "| row | to_accuracy / `--rmse` | plain `simulate` / command | ratio |",
        "|---|---|---|---:|",
    ]
    by_row = {r["row"]: r for r in api}

    def cell(r, phase):
        if r is None or phase not in r:
            return f"no answer (rc {r['rc'] if r else '?'}, {r['process_seconds']:.0f} s)" if r else "not run"
        m = r[phase]
        what = m.get("choice") or "{solver} dt={dt:.3g} N={n_paths}".format(**m)
        ref = " vs ref." if r["reference"] else ""
        return f"{m['seconds']:.2f} s, error {m['error']:+.1e}{ref} ({m['compilations']} programs; {what})"

    for r in api:
        scene, rel, method, *option = r["row"].split(":")
        if method not in ("to_accuracy", "mlqmc"):
            continue
        p = by_row.get(f"{scene}:{rel}:plain")
        rel = " ".join([rel, *option])
        for phase, name in (("first", "first answer, fresh process"), ("warm", "warm, same process")):
            ratio = r[phase]["seconds"] / p[phase]["seconds"] if phase in r and p and phase in p else math.nan
            lines.append(f"| {scene} {rel} ({name}) | {cell(r, phase)} | {cell(p, phase)} | {ratio:.2f} |")
    if len(cli) == 2:
        ratio = cli[0]["seconds"] / cli[1]["seconds"]
        lines.append(
            f"| command, chaplygin-sleigh (process, cache off) | {cli[0]['seconds']:.1f} s (rc {cli[0]['rc']}) "
            f"| {cli[1]['seconds']:.1f} s (rc {cli[1]['rc']}) | {ratio:.2f} |"
        )
    for cold, warm in zip(cache[::2], cache[1::2]):
        lines.append(
            f"| cache: {cold['label'].rsplit(',', 1)[0]} (warm / cold) "
            f"| warm {warm['seconds']:.1f} s (rc {warm['rc']}) | cold {cold['seconds']:.1f} s (rc {cold['rc']}) "
            f"| {warm['seconds'] / cold['seconds']:.2f} |"
        )
    return "\n".join(lines)


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
    parser.add_argument(
        "--first-answer",
        action="store_true",
        help="time to first answer: a fresh process per row, compilation included (results/first_answer.json)",
    )
    parser.add_argument("--row-timeout", type=float, default=360.0, help="first-answer mode: seconds per process")
    parser.add_argument(
        "--src",
        help="first-answer mode: the children import nhsde from this src/ folder (default the installed one), e.g. "
        "`git archive HEAD src | tar -x -C /tmp/clean` and --src /tmp/clean/src to measure one commit",
    )
    parser.add_argument("--rows", help="first-answer mode: only these rows, SCENE:REL:METHOD[:dt=H],...")
    parser.add_argument("--child", help=argparse.SUPPRESS)  # one first-answer row, in this fresh process
    args = parser.parse_args()
    if args.child:
        return child(args.child)
    if args.first_answer:
        args.scenes_given = "--scenes" in sys.argv
        return first_answer(args)
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
