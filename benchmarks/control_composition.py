"""The linearised control variate inside multilevel Monte Carlo and quasi-Monte Carlo: what it gains per unit of work.

    python benchmarks/control_composition.py [--scenes sleigh,chaplygin-ball,body] [--out FILE]

The scenes and statistics of ``benchmarks/estimators.py`` (``E[H](t1)``), weak order 2 with Gaussian increments,
float64, the same key with and without the control (``control='mean'``):

1. **Multilevel**: ``multilevel_monte_carlo`` with fixed counts ``(4096, 1024, 256, 256)`` from the scene's ``h0``;
   the level variances ``V_ℓ`` and Giles' work to a fixed RMSE, ``(Σ √(V_ℓ C_ℓ))²`` (``C_ℓ`` path-steps per sample,
   doubled by the control), and the warm seconds of the call.
2. **Quasi-Monte Carlo**: one level of 16 × 1024 points at ``h0/4`` (``multilevel_quasi_monte_carlo``); the
   estimate's variance, its variance times path-steps, and the warm seconds.
3. **``to_accuracy`` at relative RMSE 1e-3** given one estimator each, the sleigh only (``--accuracy``): first and
   warm seconds in this process (the estimators' programs partly shared), work and pilot work.

Ratios are "with the control / without"; below 1 the control pays.  Writes ``--out`` (default
``benchmarks/results/control_composition.json``) and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

import nhsde  # noqa: E402
from nhsde.statistics import (  # noqa: E402
    Multilevel,
    QuasiMonteCarlo,
    multilevel_monte_carlo,
    multilevel_quasi_monte_carlo,
    to_accuracy,
)

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from estimators import BODY_REFERENCE, CASES  # noqa: E402

GAUSS = nhsde.PlatenWeak2(increments="gaussian")
COUNTS = (4096, 1024, 256, 256)


def warm(fn):
    fn()
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def multilevel_row(case, control):
    def call():
        return multilevel_monte_carlo(
            case["system"],
            case["y0"],
            jax.random.key(1),
            t1=case["t1"],
            dt=case["h0"],
            statistic=case["target"],
            n_paths=COUNTS,
            solver=GAUSS,
            save=case["save"],
            control=control,
        )

    est, seconds = warm(call)
    v, c = np.asarray(est.level_variances), np.asarray(est.level_costs)
    return dict(
        variances=v.tolist(),
        work=float(np.sum(np.sqrt(v * c)) ** 2),
        seconds=seconds,
        value=float(est.value()[0]),
        se=float(est.value()[1]),
    )


def qmc_row(case, control):
    def call():
        return multilevel_quasi_monte_carlo(
            case["system"],
            case["y0"],
            jax.random.key(1),
            t1=case["t1"],
            dt=case["h0"] / 4,
            statistic=case["target"],
            n_points=(1024,),
            solver=GAUSS,
            save=case["save"],
            control=control,
        )

    est, seconds = warm(call)
    variance = float(est.value()[1]) ** 2
    return dict(
        variance=variance,
        work=variance * est.cost.path_steps,
        seconds=seconds,
        value=float(est.value()[0]),
        se=float(est.value()[1]),
    )


def accuracy_rows(case):
    exact = BODY_REFERENCE[0] if case["exact"] is None else case["exact"]
    rows = {}
    for name, estimator in (
        ("multilevel", Multilevel(GAUSS)),
        ("multilevel + control", Multilevel(GAUSS, control=True)),
        ("QMC", QuasiMonteCarlo(GAUSS)),
        ("QMC + control", QuasiMonteCarlo(GAUSS, control=True)),
    ):
        times = []
        for _ in range(2):
            start = time.perf_counter()
            res = to_accuracy(
                case["system"],
                case["y0"],
                jax.random.key(5),
                t1=case["t1"],
                statistic=case["target"],
                rmse=1e-3 * abs(exact),
                save=case["save"],
                estimators=(estimator,),
            )
            times.append(time.perf_counter() - start)
        rows[name] = dict(
            first=times[0],
            warm=times[1],
            error=float(res.value()[0]) - exact,
            work=res.run_cost.path_steps,
            pilot=res.pilot_cost.path_steps,
        )
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="sleigh,chaplygin-ball,body")
    parser.add_argument("--accuracy", action="store_true", help="also part 3 (the sleigh)")
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "control_composition.json"))
    args = parser.parse_args()
    results = {}
    for scene in args.scenes.split(","):
        case = CASES[scene]()
        results[scene] = {
            "multilevel": [multilevel_row(case, c) for c in (None, "mean")],
            "qmc": [qmc_row(case, c) for c in (None, "mean")],
        }
        if args.accuracy and scene == "sleigh":
            results[scene]["to_accuracy"] = accuracy_rows(case)
    pathlib.Path(args.out).write_text(json.dumps(results, indent=1))
    print(
        "| scene | MLMC V_ℓ without → with | MLMC work ratio | MLMC seconds | QMC variance ratio | QMC work ratio "
        "| QMC seconds |"
    )
    print("|---|---|---:|---:|---:|---:|---:|")
    for scene, r in results.items():
        (m0, m1), (q0, q1) = r["multilevel"], r["qmc"]
        v = ", ".join(f"{a:.2g}→{b:.2g}" for a, b in zip(m0["variances"], m1["variances"]))
        print(
            f"| {scene} | {v} | {m1['work'] / m0['work']:.2f} | {m0['seconds']:.2f} → {m1['seconds']:.2f} "
            f"| {q1['variance'] / q0['variance']:.2f} | {q1['work'] / q0['work']:.2f} "
            f"| {q0['seconds']:.2f} → {q1['seconds']:.2f} |"
        )
        for name, row in r.get("to_accuracy", {}).items():
            print(
                f"  to_accuracy 1e-3, {name}: first {row['first']:.2f} s, warm {row['warm']:.2f} s, "
                f"error {row['error']:+.2e}, run {row['work']:.3g} + pilot {row['pilot']:.3g} path-steps"
            )


if __name__ == "__main__":
    main()
