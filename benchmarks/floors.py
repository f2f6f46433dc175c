"""The floors under "answers in seconds": the least time any estimator could take, against the best plain setting.

    python benchmarks/floors.py [--out FILE] [--rels 1e-2,1e-3] [--no-cache]

For each scene of ``benchmarks/estimators.py --first-answer`` (the sleigh, Chaplygin's ball, the body on the
vibrating plane; the statistic E[H](t1), float64) and each relative RMSE ε, in one process:

1. ``h₀``: the coarsest step an estimator may start from, found the way ``to_accuracy`` finds it: ``(t1 − t0)/4``,
   halved until its first solver damps the declared friction (``stable_step``) and until 65536 paths survive
   there (Chaplygin's ball loses paths at 1/4).
2. ``σ²``: the variance of ``H(t1)`` at ``h₀`` (65536 paths, its first solver), and the unavoidable work of an
   estimator with neither bias nor variance reduction run at ``h₀`` or finer, ``W_min = ⌈σ²/ε²⌉ · t1/h₀``
   path-steps.  Every estimator of ``to_accuracy`` without variance reduction does at least this (plain Monte
   Carlo at ``h₀``; multilevel's level 0 alone; extrapolation's finer solve alone), before any pilot and any work
   to certify its bias.
3. ``rate``: the warm seconds per path-step of that solver in the estimators' own runs (8192 paths, the base step as
   data, paths kept), and the **warm floor** ``W_min × rate``.
4. The **first-answer floor**: the warm floor plus the compile and trace time of that one run's program (its first
   call in this process less its warm call): any estimator compiles at least its solve.
5. The variance reduction the project's estimators reach on the scene: quasi-Monte Carlo at ``h₀`` (16 scramblings
   of 1024 points, the first solver) against Monte Carlo at the same step, solver and paths, its gain per second
   ``(variance ratio)/(seconds ratio)``; the floors are divided by the best gain (a floor with variance reduction).
6. The best plain setting (``BEST_PLAIN``: solver, step and paths whose bias was measured against the exact value or
   a fine reference): its warm seconds (65536 of its paths, timed warm, scaled to its count) and its first answer
   (the same plus its program's compile, measured on the program's first call in this process).

Then the ratios the issue's targets ask for: plain / floor, warm and first.  A target above these ratios cannot be met
by any estimator the project has, however it is engineered.

7. The **multilevel floor**, the bias included.  The floors above grant an estimator no bias at ``h₀``; where the
   solver's bias there exceeds ε, the corrections to a finer step cost more.  On 65536 paths per level, coupled as
   the multilevel estimators couple them (both solves on one Brownian path of the finer step), the mean and
   variance ``V_ℓ`` of ``Y_ℓ = S(h_ℓ) − S(h_{ℓ−1})`` at ``h_ℓ = h₀ 2^{−ℓ}``, ``ℓ ≤ 5``; a lower bound on the bias
   ``b_L ≥ |Σ_{ℓ>L} Ŷ_ℓ| − 2 SE``; and the least warm seconds of a multilevel estimator with oracle knowledge of
   the ``V_ℓ``, no pilot and no rounding, over its first and finest levels (``multilevel_floor``): plain Monte Carlo
   at any ``h_k`` is the one-level case.  QMC's gain per second is granted to every level, and, as multilevel QMC
   measured (its finer levels at the Monte-Carlo rate), to the first level only.  A multilevel, plain or QMC
   estimator on these solvers cannot be faster than this.

And the persistent compilation cache (unless ``--no-cache``): the README's main job run in fresh processes with the
cache cold and warm, and the floor of a warm-cache process, ``import nhsde`` (measured in a fresh process) plus the
job run a second time in one process (nothing left to compile or trace).

Writes ``benchmarks/results/floors.json`` and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import platform
import sys
import tempfile
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import estimators as bench  # noqa: E402  (the cases, BEST_PLAIN and the fresh-process helpers)

import nhsde  # noqa: E402
from nhsde._simulate import stable_step  # noqa: E402
from nhsde.statistics import quasi_monte_carlo  # noqa: E402

SCENES = ("sleigh", "chaplygin-ball", "body")
FIRST_SOLVER = {"sleigh": bench.GAUSS, "chaplygin-ball": bench.GAUSS, "body": "heun2"}  # to_accuracy's first pilot
PROBE_PATHS = 65536
RUN_PATHS = 8192  # the estimators' large runs (statistics._paths.LARGE_RUN_PATHS)
ML_LEVELS = 6  # coupled levels h0 … h0/32 measured for the multilevel floor
ML_PATHS = 65536


def solve(case, solver, dt, n_paths, key=1, paths=False, brownian_dt=None):
    """``n_paths`` of the case at ``dt`` with the base step as data, as the estimators solve (``paths``: kept), on
    the Brownian path of step ``brownian_dt`` (default ``dt``; a finer one couples solves at several steps)."""
    save = nhsde.Save(names=("energy",), n=2, paths=paths)
    return nhsde.simulate(
        case["system"],
        case["y0"],
        jax.random.key(key),
        n_paths=n_paths,
        t1=case["t1"],
        solver=solver,
        save=save,
        steps=nhsde.FixedSteps(dt, brownian_dt=dt if brownian_dt is None else brownian_dt),
    )


def timed(fn, rounds=3):
    """(first call's seconds, best warm seconds, last result)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    best = math.inf
    for _ in range(rounds):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return first, best, out


def coarsest_step(case, solver):
    """``to_accuracy``'s rule for ``h₀``, with 65536 surviving paths in place of its pilot."""
    h = case["t1"] / 4
    while not stable_step(case["system"], solver, h):
        h /= 2
    while True:
        try:
            return h, solve(case, solver, h, PROBE_PATHS)
        except nhsde.SimulationError:  # a path lost (Chaplygin's ball at h = 1 and 1/4)
            h /= 2


def scene_floors(scene, rels, compiled):
    """The rows of ``scene``; ``compiled``: the compile seconds of each plain solver's program, measured on its first
    call in this process (a later step or path count reuses the program)."""
    case = bench.CASES[scene]()
    exact = bench.BODY_REFERENCE[0] if case["exact"] is None else case["exact"]
    solver = FIRST_SOLVER[scene]
    h0, ens = coarsest_step(case, solver)
    steps0 = round(case["t1"] / h0)
    sigma2 = float(ens.cov[-1, 0, 0])
    first, warm, _ = timed(lambda: solve(case, solver, h0, RUN_PATHS, key=2, paths=True).paths)
    rate = warm / (RUN_PATHS * steps0)
    compile_s = first - warm
    # quasi-Monte Carlo's gain per second at h0 (where (t1 − t0)/h0 is a power of two: every scene here)
    qmc = dict(replicates=16, n_paths=1024)
    save = nhsde.Save(names=("energy",), n=2)
    _, q_warm, q_est = timed(
        lambda: quasi_monte_carlo(
            case["system"], case["y0"], jax.random.key(3), t1=case["t1"], dt=h0, solver=solver, save=save, **qmc
        )
    )
    n_qmc = qmc["replicates"] * qmc["n_paths"]
    _, mc_warm, mc = timed(lambda: solve(case, solver, h0, n_qmc, key=4))
    var_qmc = float(q_est.mean_se[-1, 0]) ** 2
    var_mc = float(mc.cov[-1, 0, 0]) / n_qmc
    qmc_gain = (var_mc / var_qmc) / (q_warm / mc_warm)
    best_gain = max(1.0, qmc_gain)
    levels = coupled_levels(case, solver, h0)
    biases = bias_lower_bounds(levels)
    rows = []
    for rel in rels:
        eps = rel * abs(exact)
        w_min = math.ceil(sigma2 / eps**2) * steps0
        floor_warm = w_min * rate
        p_solver, p_dt, p_paths = bench.BEST_PLAIN[(scene, rel)]
        p_first, p_warm, _ = timed(
            lambda p_solver=p_solver, p_dt=p_dt: bench.simulate(case, p_solver, p_dt, PROBE_PATHS, key=4).mean
        )
        plain_warm = p_warm * p_paths / PROBE_PATHS
        compiled.setdefault((scene, str(p_solver)), p_first - p_warm)
        plain_first = plain_warm + compiled[(scene, str(p_solver))]
        ml_all = multilevel_floor(levels, biases, eps, steps0, rate, best_gain, best_gain)
        ml_first = multilevel_floor(levels, biases, eps, steps0, rate, 1.0, best_gain)
        row = dict(
            scene=scene,
            rel=rel,
            rmse=eps,
            h0=h0,
            steps0=steps0,
            sigma2=sigma2,
            w_min=w_min,
            rate_ns=rate * 1e9,
            compile_seconds=compile_s,
            floor_warm=floor_warm,
            floor_first=floor_warm + compile_s,
            qmc_variance_ratio=var_mc / var_qmc,
            qmc_seconds_ratio=q_warm / mc_warm,
            best_gain=best_gain,
            floor_warm_reduced=floor_warm / best_gain,
            floor_first_reduced=floor_warm / best_gain + compile_s,
            plain=dict(solver=str(p_solver), dt=p_dt, n_paths=p_paths, work=p_paths * round(case["t1"] / p_dt)),
            plain_warm=plain_warm,
            plain_first=plain_first,
            levels=levels,
            bias_lower_bounds=biases,
            ml_floor_warm=ml_all[0],
            ml_floor_levels=ml_all[1:],
            ml_floor_warm_qmc_first_level=ml_first[0],
            ml_floor_first=ml_all[0] + compile_s,
        )
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def coupled_levels(case, solver, h0, levels=ML_LEVELS, n_paths=ML_PATHS):
    """Per level ``ℓ < levels`` at ``h_ℓ = h₀ 2^{−ℓ}``: the mean and variance of ``Y_ℓ = S(h_ℓ) − S(h_{ℓ−1})`` (both
    solves on one Brownian path of step ``h_ℓ``, as the multilevel estimators couple them; ``Y_0 = S(h₀)``) and the
    standard error of the mean, from ``n_paths`` paths."""
    out = []
    for ell in range(levels):
        fine = h0 / 2**ell

        def final(dt, fine=fine, ell=ell):
            ens = solve(case, solver, dt, n_paths, key=7 + ell, paths=True, brownian_dt=fine)
            return np.asarray(ens.paths[:, -1, 0], np.float64)

        y = final(fine) - (final(2 * fine) if ell else 0.0)
        out.append(
            dict(h=fine, mean=float(y.mean()), se=float(y.std(ddof=1) / math.sqrt(n_paths)), var=float(y.var(ddof=1)))
        )
    return out


def bias_lower_bounds(levels):
    """``b_L ≥ max(0, |Σ_{ℓ>L} Ŷ_ℓ| − 2 SE)``: a lower bound (at about 98 %) on ``|E S(h_L) − S|`` from the measured
    level means, the bias left at the finest measured step neglected (weak order ≥ 1: at most 1/32 of ``b_0``)."""
    out = []
    for top in range(len(levels)):
        rest = levels[top + 1 :]
        total = sum(lv["mean"] for lv in rest)
        se = math.sqrt(sum(lv["se"] ** 2 for lv in rest))
        out.append(max(0.0, abs(total) - 2 * se))
    return out


def multilevel_floor(levels, biases, eps, steps0, rate, gain_all, gain_first):
    """The least warm seconds of a multilevel estimator on these levels with oracle knowledge (the true level
    variances, no pilot, no rounding, no bias to certify beyond its lower bound): over the first level ``k`` and the
    finest ``L`` with ``b_L < ε``, ``(Σ_{ℓ=k}^{L} √(V_ℓ C_ℓ r / g_ℓ))² / (ε² − b_L²)`` (Giles 2008, §2), ``C_ℓ`` the
    path-steps per sample (``1.5 s₀ 2^ℓ`` for a coupled pair, ``s₀ 2^k`` for the first level, whose variance is
    ``V_0``'s), ``r`` seconds per path-step, ``g_k = gain_first`` and ``g_ℓ = gain_all`` beyond.  ``k = L`` is plain
    Monte Carlo (or QMC) at ``h_k``."""
    best = (math.inf, -1, -1)
    for k in range(len(levels)):
        for top in range(k, len(levels)):
            b = biases[top]
            if not b < eps:
                continue
            terms = [levels[0]["var"] * steps0 * 2**k * rate / gain_first]
            terms += [levels[ell]["var"] * 1.5 * steps0 * 2**ell * rate / gain_all for ell in range(k + 1, top + 1)]
            seconds = sum(math.sqrt(t) for t in terms) ** 2 / ((eps - b) * (eps + b))
            best = min(best, (seconds, k, top))
    return best


def cache_floor():
    """Seconds of the README's main job in fresh processes (cache cold, then warm), of ``import nhsde`` alone, and of
    the job's second run in one process."""
    command = bench.nhsde_command()
    out = {}
    with tempfile.TemporaryDirectory(prefix="nhsde-cache-") as folder:
        for state in ("cold", "warm"):
            seconds, rc, _, err = bench.fresh_process([*command, *bench.MAIN_JOB], cache=folder)
            assert rc == 0, err[-2000:]
            out[state] = seconds
    seconds, rc, _, err = bench.fresh_process([sys.executable, "-c", "import nhsde"])
    assert rc == 0, err[-2000:]
    out["import"] = seconds
    twice = (
        "import time, contextlib, io\n"
        "from nhsde.runs import main\n"
        f"argv = {bench.MAIN_JOB!r}\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    main(argv)\n"
        "    start = time.perf_counter()\n"
        "    main(argv)\n"
        "print(time.perf_counter() - start)\n"
    )
    _, rc, stdout, err = bench.fresh_process([sys.executable, "-c", twice])
    assert rc == 0, err[-2000:]
    out["second_run"] = float(stdout.split()[-1])
    out["floor"] = out["import"] + out["second_run"]
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rels", default="1e-2,1e-3")
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--no-cache", action="store_true", help="skip the persistent-cache rows")
    parser.add_argument("--out", default=str(pathlib.Path(__file__).with_name("results") / "floors.json"))
    args = parser.parse_args()
    rels = [float(r) for r in args.rels.split(",")]
    compiled = {}
    rows = [row for scene in args.scenes.split(",") for row in scene_floors(scene, rels, compiled)]
    cache = None if args.no_cache else cache_floor()
    pathlib.Path(args.out).write_text(
        json.dumps(dict(rows=rows, cache=cache, jax=jax.__version__, cpu=platform.processor()), indent=1)
    )
    print("\n| scene, ε | h₀ | σ² | W_min | rate | floor warm · first | with QMC's gain | plain warm · first |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['scene']} {r['rel']:g} | {r['h0']:g} | {r['sigma2']:.3g} | {r['w_min']:.3g} | {r['rate_ns']:.0f} ns "
            f"| {r['floor_warm']:.3g} · {r['floor_first']:.3g} s | ×{r['best_gain']:.2g}: {r['floor_warm_reduced']:.3g}"
            f" · {r['floor_first_reduced']:.3g} s | {r['plain_warm']:.3g} · {r['plain_first']:.3g} s |"
        )
    print("\n| scene, ε | plain / floor, warm | plain / floor, first |")
    print("|---|---:|---:|")
    for r in rows:
        print(
            f"| {r['scene']} {r['rel']:g} | {r['plain_warm'] / r['floor_warm_reduced']:.3g} "
            f"| {r['plain_first'] / r['floor_first_reduced']:.3g} |"
        )
    print(
        "\n| scene, ε | bias lower bounds b_0 … b_5 (units of ε) | V_ℓ/V_0, ℓ = 1 … 5 | multilevel floor warm (QMC on "
        "every level · first level only), levels k…L | first | plain / floor, warm · first |"
    )
    print("|---|---|---|---:|---:|---:|")
    for r in rows:
        b = " ".join(f"{x / r['rmse']:.2g}" for x in r["bias_lower_bounds"])
        v = " ".join(f"{lv['var'] / r['levels'][0]['var']:.2g}" for lv in r["levels"][1:])
        k, top = r["ml_floor_levels"]
        print(
            f"| {r['scene']} {r['rel']:g} | {b} | {v} | {r['ml_floor_warm']:.3g} · "
            f"{r['ml_floor_warm_qmc_first_level']:.3g} s, {k}…{top} | {r['ml_floor_first']:.3g} s | "
            f"{r['plain_warm'] / r['ml_floor_warm']:.3g} · {r['plain_first'] / r['ml_floor_first']:.3g} |"
        )
    if cache:
        print(
            f"\ncache: cold {cache['cold']:.2f} s, warm {cache['warm']:.2f} s ({cache['warm'] / cache['cold']:.2f}); "
            f"floor import {cache['import']:.2f} + second run {cache['second_run']:.2f} = {cache['floor']:.2f} s "
            f"({cache['floor'] / cache['cold']:.2f} of cold)"
        )


if __name__ == "__main__":
    main()
