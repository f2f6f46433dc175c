"""Work-precision diagrams: error against wall time for every solver and step.

    python benchmarks/work_precision.py [--paths N] [--quick]

Scenes: the ball on the vibrating plane (weak reference: the closed-form
k_xx(t1), S0 (3.1)) and the noisy Chaplygin sleigh (nonlinear; weak reference:
E[H](t1) = H0 e^{−4εt1} + ν(1 − e^{−4εt1})/(4ε), exact from Itô's formula).
Writes benchmarks/results/work_precision.csv and one PNG per scene (strong and
weak error against seconds, with the Monte-Carlo error √(Var/N) of the weak
statistic drawn as a horizontal band: weak errors below it are not resolved),
and prints the cheapest setting for a few accuracies.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import pathlib

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import nhsde  # noqa: E402
from nhsde._work_precision import cheapest_setting, work_precision  # noqa: E402
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"


def ball_case():
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    t1 = 2.0
    reference = float(ball_covariances(jnp.float64(t1), 1.0, 1.0, 1 / 1.4)[0])
    return dict(
        name="ball", system=scene.build(), y0=scene.initial_state().astype(jnp.float64), t1=t1,
        statistic=lambda ens: (ens.cov[-1, 0, 0], ens.cov_se[-1, 0, 0]), reference=reference,
        save=nhsde.Save(names=("x",), n=2), label="k_xx(t1)",
    )


def sleigh_case():
    eps, nu, t1 = 0.5, 1.0, 2.0
    scene = ChaplyginSleigh(eps=eps, nu=nu)
    y0 = scene.initial_state().astype(jnp.float64).at[4].set(0.5)
    j = float(scene.params.inertia + scene.params.mass * scene.params.offset**2)
    h0 = 0.5 * (1.0 + j * 0.25)
    reference = h0 * np.exp(-4 * eps * t1) + nu * (1 - np.exp(-4 * eps * t1)) / (4 * eps)
    return dict(
        name="sleigh", system=scene.build(), y0=y0, t1=t1,
        statistic=lambda ens: (ens.mean[-1, 0], ens.mean_se[-1, 0]), reference=float(reference),
        save=nhsde.Save(names=("energy",), n=2), label="E[H](t1)",
    )


def plot(case, rows, path):
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
    axes[0].set(xlabel="wall time [s]", ylabel="strong RMS error at t1", title=f"{case['name']}: strong")
    axes[1].set(xlabel="wall time [s]", ylabel=f"|{case['label']} − exact|", title=f"{case['name']}: weak")
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
    args = parser.parse_args()
    n_paths = 2048 if args.quick else args.paths
    dts = [2.0**-k for k in (range(3, 6) if args.quick else range(3, 9))]
    solvers = ["euler", "milstein", "heun", "sra1", "exponential"]
    OUT.mkdir(exist_ok=True)
    all_rows = []
    for case in (ball_case(), sleigh_case()):
        rows = work_precision(
            case["system"], case["y0"], jax.random.key(0), t1=case["t1"], solvers=solvers, dts=dts,
            statistic=case["statistic"], reference=case["reference"], n_paths=n_paths, save=case["save"],
        )
        plot(case, rows, OUT / f"work_precision_{case['name']}.png")
        print(f"\n[{case['name']}] {case['label']} exact = {case['reference']:.6g}, {n_paths} paths")
        print(f"{'solver':<12}{'dt':>10}{'strong':>12}{'weak':>12}{'MC se':>10}{'seconds':>10}{'peak MB':>9}")
        for r in rows:
            print(f"{r.solver:<12}{r.dt:>10.4g}{r.strong_error:>12.3g}{r.weak_error:>12.3g}{r.weak_se:>10.2g}"
                  f"{r.seconds:>10.3f}{r.peak_bytes / 2**20:>9.1f}")
            all_rows.append(dict(scene=case["name"], **dataclasses.asdict(r)))
        for tol in (1e-1, 1e-2, 1e-3):
            for kind in ("strong", "weak"):
                try:
                    r = cheapest_setting(rows, tol * (abs(case["reference"]) if kind == "weak" else 1.0), kind=kind)
                    print(f"  cheapest for {kind} error ≤ {tol:g}{' (relative)' if kind == 'weak' else ''}: "
                          f"{r.solver} dt={r.dt:g} ({r.seconds:.3f} s)")
                except ValueError as e:
                    print(f"  {kind} ≤ {tol:g}: {e}")
    with open(OUT / "work_precision.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(all_rows[0]))
        writer.writeheader()
        writer.writerows(all_rows)
    print(f"\nwrote {OUT / 'work_precision.csv'} and the PNG diagrams")


if __name__ == "__main__":
    main()
