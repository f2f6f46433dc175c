"""Do antithetic points and the linearised control variate add to randomised quasi-Monte Carlo?

    python benchmarks/qmc_composition.py [--out FILE]

Standard errors only (no timings, so the machine's load does not enter), float64, the scenes of
``benchmarks/estimators.py`` at a step where QMC runs (``(t1 − t0)/dt`` a power of two):

1. **Antithetic points at equal work**: ``quasi_monte_carlo`` with 1024 points per scrambling against
   ``antithetic=True`` with 512 (each point solved twice): the same path-steps.  The standard error of each saved
   mean (the energy; the ball from rest's ``x`` and ``u_x``, odd in ``W``).
2. **The control variate on top of QMC**: the linearised system (``linearised_system``, the control of
   ``control_variate``) solved on the same scrambled points as the system (same key), 16 independent runs of two
   scramblings × 1024 points each; the variance of the system's estimate over the 16 runs against that of
   ``Ŷ − β Ĉ`` (``β`` fitted on the 16 runs, and ``β = 1``).  A reduction near 1 means QMC already removed what
   the control would (its linear part).

Writes ``--out`` (default benchmarks/results/qmc_composition.json) and prints both tables.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import nhsde  # noqa: E402
from nhsde.scenes import BallOnVibratingPlane, BodyOnVibratingPlane, ChaplyginBall, ChaplyginSleigh  # noqa: E402
from nhsde.statistics import linearised_system, quasi_monte_carlo  # noqa: E402

# name: (scene, y0 (None: the scene's initial state), t1, dt, saved names)
CASES = {
    "ball": (BallOnVibratingPlane(eps=1.0, nu=1.0), jnp.zeros(4), 1.0, 1 / 16, ("x", "u_x")),
    "sleigh": (ChaplyginSleigh(eps=0.5, nu=1.0, drift=False), jnp.array([1.0, 0.5]), 2.0, 1 / 16, ("energy",)),
    "chaplygin-ball": (ChaplyginBall(eps=1.0, nu=2.0), None, 4.0, 1 / 8, ("energy",)),
    "body": (BodyOnVibratingPlane(eps=0.5, nu=1.0), None, 1.0, 1 / 16, ("energy",)),
}


def antithetic_at_equal_work(name):
    scene, y0, t1, dt, names = CASES[name]
    system = scene.build()
    y0 = (scene.initial_state() if y0 is None else y0).astype(jnp.float64)
    row = {}
    for anti, points in ((False, 1024), (True, 512)):
        r = quasi_monte_carlo(
            system, y0, jax.random.key(3), n_paths=points, t1=t1, dt=dt, antithetic=anti, save=nhsde.Save(names=names)
        )
        row["antithetic" if anti else "plain"] = dict(
            se=[float(x) for x in r.mean_se[-1]], mean=[float(x) for x in r.mean[-1]], path_steps=r.cost.path_steps
        )
    return row


def control_on_top(name, runs=16):
    scene, y0, t1, dt, _ = CASES[name]
    if name == "ball":
        return None  # linear: the control is the system itself
    system = scene.build()
    y0 = (scene.initial_state() if y0 is None else y0).astype(jnp.float64)
    control, start = linearised_system(system), jnp.concatenate([y0, y0])
    save = nhsde.Save(names=("energy",), n=2)
    ys, cs = [], []
    for k in range(runs):
        args = dict(n_paths=1024, t1=t1, dt=dt, replicates=2, save=save)
        ys.append(float(quasi_monte_carlo(system, y0, jax.random.key(k), **args).mean[-1, 0]))
        cs.append(float(quasi_monte_carlo(control, start, jax.random.key(k), **args).mean[-1, 0]))
    y, c = np.array(ys), np.array(cs)
    beta = float(np.cov(y, c)[0, 1] / np.var(c, ddof=1))
    return dict(
        beta=beta,
        reduction_fitted=float(np.var(y, ddof=1) / np.var(y - beta * c, ddof=1)),
        reduction_beta_1=float(np.var(y, ddof=1) / np.var(y - c, ddof=1)),
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "qmc_composition.json"))
    args = parser.parse_args()
    out = {name: dict(antithetic=antithetic_at_equal_work(name), control=control_on_top(name)) for name in CASES}
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1))
    print("| scene | statistic | SE plain (16 × 1024) | SE antithetic (16 × 512 pairs) | ratio |")
    print("|---|---|---:|---:|---:|")
    for name, row in out.items():
        for i, stat in enumerate(CASES[name][4]):
            p, a = row["antithetic"]["plain"]["se"][i], row["antithetic"]["antithetic"]["se"][i]
            print(f"| {name} | E[{stat}] | {p:.3g} | {a:.3g} | {a / p:.3g} |")
    print("\n| scene | β fitted | variance ÷ (β fitted) | variance ÷ (β = 1) |")
    print("|---|---:|---:|---:|")
    for name, row in out.items():
        if row["control"]:
            c = row["control"]
            print(f"| {name} | {c['beta']:.3g} | {c['reduction_fitted']:.3g} | {c['reduction_beta_1']:.3g} |")


if __name__ == "__main__":
    main()
