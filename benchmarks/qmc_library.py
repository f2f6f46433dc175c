"""``nhsde.statistics.quasi_monte_carlo`` against the best plain-MC setting on the sleigh, at RMSE = 1e-3 × |E[H]|.

    python benchmarks/qmc_library.py

One process, float64, warm best-of-3 times: plain ``weak2`` at dt = 1/16 with 1.26e6 paths (the best plain
setting of ``benchmarks/estimators.py`` at that target) against randomised QMC with ``heun2`` at dt = 1/16,
16 replicates of 512, 1024 and 2048 paths.  Prints each run's error against the exact E[H], its standard
error and the time ratio (recorded in ``benchmarks/RESULTS.md``, "Quasi-Monte Carlo").
"""

from __future__ import annotations

import math
import time

import jax

jax.config.update("jax_enable_x64", True)

from estimators import sleigh_case  # noqa: E402

import nhsde  # noqa: E402
from nhsde.statistics import quasi_monte_carlo  # noqa: E402


def best_of(run, rounds=3):
    run()  # compile
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - start)
    return result, min(times)


def main():
    case = sleigh_case()
    exact, t1, system, y0, save = case["exact"], case["t1"], case["system"], case["y0"], case["save"]
    target = 1e-3 * abs(exact)

    def line(label, result, seconds):
        value, se = float(result.mean[-1, 0]), float(result.mean_se[-1, 0])
        rmse = math.hypot(value - exact, se)
        print(
            f"{label}: {seconds:.3f} s, error {value - exact:+.1e}, SE {se:.1e}, "
            f"RMSE ≈ {rmse:.1e} (target {target:.1e})"
        )

    def plain_run():
        return nhsde.simulate(
            system, y0, jax.random.key(1), n_paths=1_260_000 // 64 * 64, t1=t1, dt=1 / 16, solver="weak2", save=save
        )

    plain, t_plain = best_of(plain_run)
    line("plain weak2, dt 1/16, 1.26e6 paths", plain, t_plain)
    for n in (512, 1024, 2048):

        def qmc_run(n=n):
            return quasi_monte_carlo(
                system, y0, jax.random.key(0), n_paths=n, t1=t1, dt=1 / 16, replicates=16, solver="heun2", save=save
            )

        qmc, t_qmc = best_of(qmc_run)
        line(f"QMC heun2, dt 1/16, {n} × 16 paths", qmc, t_qmc)
        print(f"  time ratio plain / QMC: {t_plain / t_qmc:.1f}")


if __name__ == "__main__":
    main()
