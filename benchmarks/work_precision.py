"""Work-precision diagrams: error against wall time for every solver and step.

    python benchmarks/work_precision.py [--paths N] [--quick] [--scenes ball,sleigh,chaplygin-ball]

Scenes: the ball on the vibrating plane (weak reference: the closed-form
k_xx(t1), S0 (3.1)), the noisy Chaplygin sleigh (nonlinear; weak reference:
E[H](t1) = H0 e^{−4εt1} + ν(1 − e^{−4εt1})/(4ε), exact from Itô's formula) and
Chaplygin's balanced ball rolling under a random couple (a nonlinear rolling
body, additive noise; weak reference: the stationary E[H] = 3ν/(8ε) of its exact
stationary law, reached from rest long before t1).
Writes benchmarks/results/work_precision.csv (rows of the scenes run replace
their old rows, other scenes' rows are kept) and one PNG per scene (strong and
weak error against seconds, with the Monte-Carlo error √(Var/N) of the weak
statistic drawn as a horizontal band: weak errors below it are not resolved),
and prints the cheapest setting for a few accuracies.  The harness times each
row once; on a loaded machine that is noisy, so ``--cost-rounds`` also times
every solver at one step size interleaved (best of the rounds; written to
results/work_precision_step_cost.json), and the diagrams and the cheapest
settings then use that per-step time × the number of steps as the cost (the
fixed-step loop costs the same per step at every dt); the CSV keeps both.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import nhsde  # noqa: E402
from nhsde import cheapest_setting, work_precision  # noqa: E402
from nhsde.scenes import (  # noqa: E402
    BallOnVibratingPlane,
    ChaplyginBall,
    ChaplyginSleigh,
    ball_covariances,
)

OUT = pathlib.Path(__file__).parent / "results"


def ball_case():
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    t1 = 2.0
    reference = float(ball_covariances(jnp.float64(t1), 1.0, 1.0, 1 / 1.4)[0])
    return dict(
        name="ball",
        system=scene.build(),
        y0=scene.initial_state().astype(jnp.float64),
        t1=t1,
        statistic=lambda ens: (ens.cov[-1, 0, 0], ens.cov_se[-1, 0, 0]),
        reference=reference,
        save=nhsde.Save(names=("x",), n=2),
        label="k_xx(t1)",
        solvers=["euler", "milstein", "heun", "heun2", "sra1", "exponential"],
    )


def sleigh_case():
    eps, nu, t1 = 0.5, 1.0, 2.0
    scene = ChaplyginSleigh(eps=eps, nu=nu)
    y0 = scene.initial_state().astype(jnp.float64).at[4].set(0.5)
    j = float(scene.params.inertia + scene.params.mass * scene.params.offset**2)
    h0 = 0.5 * (1.0 + j * 0.25)
    reference = h0 * np.exp(-4 * eps * t1) + nu * (1 - np.exp(-4 * eps * t1)) / (4 * eps)
    return dict(
        name="sleigh",
        system=scene.build(),
        y0=y0,
        t1=t1,
        statistic=lambda ens: (ens.mean[-1, 0], ens.mean_se[-1, 0]),
        reference=float(reference),
        save=nhsde.Save(names=("energy",), n=2),
        label="E[H](t1)",
        solvers=["euler", "milstein", "heun", "heun2", "sra1", "exponential"],
    )


def chaplygin_ball_case():
    """State (M, γ) from rest, e₃ up; ε = 1, ν = 2 (α = 4ε/ν = 2), I = (0.3, 0.4, 0.5), m = R = 1.

    The stationary law c(1 − D(γ, Aγ))^{−1/2} e^{−αH} gives E[H] = 3/(2α) = 3ν/(8ε)
    (scenes/_chaplygin_ball.py).  From rest E[H](t) relaxes at a rate ≈ 2.2
    (measured: 0.75 − E[H] = 0.023 at t = 1, 0.008 at t = 1.5, SRA1 dt = 1/128,
    16384 paths), so at t1 = 4 the transient is ≈ 3e-5, far below the
    Monte-Carlo error (≈ 5e-3 at 16384 paths).  The friction −2εω = −2εĨ(γ)⁻¹M is
    not linear in the state, so the scene declares no linear drift and the
    exponential solver does not apply; Milstein is Euler–Maruyama for additive noise.
    """
    eps, nu, t1 = 1.0, 2.0, 4.0
    scene = ChaplyginBall(eps=eps, nu=nu)
    return dict(
        name="chaplygin-ball",
        system=scene.build(),
        y0=scene.initial_state().astype(jnp.float64),
        t1=t1,
        statistic=lambda ens: (ens.mean[-1, 0], ens.mean_se[-1, 0]),
        reference=3 * nu / (8 * eps),
        save=nhsde.Save(names=("energy",), n=2),
        label="E[H](t1)",
        solvers=["euler", "heun", "heun2", "sra1"],
    )


CASES = {"ball": ball_case, "sleigh": sleigh_case, "chaplygin-ball": chaplygin_ball_case}


def step_costs(case, dt, n_paths, rounds):
    """Best-of-``rounds`` wall time of each solver at one step, run interleaved (a load spike hits all alike)."""

    def run(solver):
        return nhsde.simulate(
            case["system"],
            case["y0"],
            jax.random.key(0),
            n_paths=n_paths,
            t1=case["t1"],
            dt=dt,
            solver=solver,
            save=case["save"],
        )

    for solver in case["solvers"]:
        jax.block_until_ready(run(solver))  # compile
    times = {solver: [] for solver in case["solvers"]}
    for _ in range(rounds):
        for solver in case["solvers"]:
            start = time.perf_counter()
            jax.block_until_ready(run(solver))
            times[solver].append(time.perf_counter() - start)
    return {solver: min(ts) for solver, ts in times.items()}


def plot(case, rows, path, modelled):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for solver in dict.fromkeys(r.solver for r in rows):
        rs = [r for r in rows if r.solver == solver]
        axes[0].loglog([r.seconds for r in rs], [r.strong_error for r in rs], "o-", label=solver)
        axes[1].loglog([r.seconds for r in rs], [max(r.weak_error, 1e-16) for r in rs], "o-", label=solver)
    se = float(np.median([r.weak_se for r in rows]))
    axes[1].axhspan(1e-16, se, color="0.85", label=f"MC error √(Var/N) = {se:.2g}")
    axes[1].set_ylim(bottom=min(se / 20, min(max(r.weak_error, 1e-16) for r in rows) / 2))
    xlabel = "wall time [s]" + (" (best per-step time × steps)" if modelled else "")
    axes[0].set(xlabel=xlabel, ylabel="strong RMS error at t1", title=f"{case['name']}: strong")
    axes[1].set(xlabel=xlabel, ylabel=f"|{case['label']} − exact|", title=f"{case['name']}: weak")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=16384)
    parser.add_argument("--quick", action="store_true", help="fewer paths and steps")
    parser.add_argument("--scenes", default=",".join(CASES), help=f"comma-separated, from {', '.join(CASES)}")
    parser.add_argument("--cost-rounds", type=int, default=5, help="interleaved rounds of the per-step cost (0 skips)")
    args = parser.parse_args()
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = [s for s in names if s not in CASES]
    if unknown:
        parser.error(f"--scenes: unknown {unknown}; choose from {', '.join(CASES)}")
    n_paths = 2048 if args.quick else args.paths
    dts = [2.0**-k for k in (range(3, 6) if args.quick else range(3, 9))]
    OUT.mkdir(exist_ok=True)
    all_rows, costs = [], {}
    for case in (CASES[name]() for name in names):
        rows = work_precision(
            case["system"],
            case["y0"],
            jax.random.key(0),
            t1=case["t1"],
            solvers=case["solvers"],
            dts=dts,
            statistic=case["statistic"],
            reference=case["reference"],
            n_paths=n_paths,
            save=case["save"],
        )
        measured = {(r.solver, r.dt): r.seconds for r in rows}
        if args.cost_rounds > 0:
            cost_dt = 2.0**-6
            best = step_costs(case, cost_dt, n_paths, args.cost_rounds)
            costs[case["name"]] = dict(
                dt=cost_dt,
                n_paths=n_paths,
                rounds=args.cost_rounds,
                best_seconds=best,
                relative_to_euler={s: t / best["euler"] for s, t in best.items()},
                loadavg=os.getloadavg(),
            )
            rows = [dataclasses.replace(r, seconds=best[r.solver] * cost_dt / r.dt) for r in rows]
        plot(case, rows, OUT / f"work_precision_{case['name']}.png", modelled=args.cost_rounds > 0)
        print(f"\n[{case['name']}] {case['label']} exact = {case['reference']:.6g}, {n_paths} paths")
        if args.cost_rounds > 0:
            print(
                f"  per-step cost at dt={cost_dt:g} (best of {args.cost_rounds}, interleaved), relative to euler: "
                + ", ".join(f"{s} {t / best['euler']:.2f}" for s, t in best.items())
            )
        print(
            f"{'solver':<12}{'dt':>10}{'strong':>12}{'weak':>12}{'MC se':>10}{'measured s':>11}{'cost s':>9}"
            f"{'peak MB':>9}"
        )
        for r in rows:
            once = measured[(r.solver, r.dt)]
            print(
                f"{r.solver:<12}{r.dt:>10.4g}{r.strong_error:>12.3g}{r.weak_error:>12.3g}{r.weak_se:>10.2g}"
                f"{once:>11.3f}{r.seconds:>9.3f}{r.peak_bytes / 2**20:>9.1f}"
            )
            all_rows.append(dict(scene=case["name"], **dataclasses.asdict(r), measured_seconds=once))
        for tol in (1e-1, 1e-2, 1e-3):
            for kind in ("strong", "weak"):
                try:
                    r = cheapest_setting(rows, tol * (abs(case["reference"]) if kind == "weak" else 1.0), kind=kind)
                    print(
                        f"  cheapest for {kind} error ≤ {tol:g}{' (relative)' if kind == 'weak' else ''}: "
                        f"{r.solver} dt={r.dt:g} ({r.seconds:.3f} s)"
                    )
                except ValueError as e:
                    print(f"  {kind} ≤ {tol:g}: {e}")
    path = OUT / "work_precision.csv"
    kept = []
    if path.exists():
        with open(path, newline="") as f:
            kept = [r for r in csv.DictReader(f) if r["scene"] not in names]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in kept + all_rows for k in r)))
        writer.writeheader()
        writer.writerows(kept + all_rows)
    if costs:
        cost_path = OUT / "work_precision_step_cost.json"
        old = json.loads(cost_path.read_text()) if cost_path.exists() else {}
        cost_path.write_text(json.dumps({**old, **costs}, indent=2))
    print(f"\nwrote {OUT / 'work_precision.csv'} and the PNG diagrams")


if __name__ == "__main__":
    main()
