"""Randomized quasi-Monte Carlo (scrambled Sobol' + Brownian bridge) against plain Monte Carlo, same scheme and step.

    python benchmarks/qmc.py [--quick] [--scenes ball,ball-fine,sleigh,chaplygin-ball-coarse,chaplygin-ball,body]

Does RQMC earn a place in the library's estimators?  For each scene of
``benchmarks/estimators.py`` (its t1, Euler–Maruyama at the middle step of its
step list; ``ball-fine`` is the ball at h = 1/64 and ``chaplygin-ball-coarse``
Chaplygin's ball at h = 1/8, to see the dimension's effect) one
jitted Euler–Maruyama loop (``lax.scan`` over steps, ``vmap`` over paths) takes a
``(N, n_steps, noise_dim)`` array of increments, fed by either sampler:

- MC: i.i.d. Gaussian increments drawn like the library's counter-based driver
  (``normal(fold_in(fold_in(key, block), step), (64, m))``);
- RQMC: ``scipy.stats.qmc.Sobol(d = n_steps·noise_dim, scramble=True)`` (LMS +
  digital shift) points → ``ndtri`` (clipped away from 0 and 1) → a Brownian
  bridge per channel on the step grid (coordinate block 0 → W(T), then midpoints
  level by level; the channels interleaved, so Sobol' dimensions ``k·m … k·m+m−1``
  are the k-th bridge node of every channel and the coarse levels get the best
  dimensions) → increments.

It measures, float64:

1. a sanity line: the loop's MC mean against ``nhsde.simulate(..., solver="euler")``
   (``--sanity-paths`` paths);
2. the per-path variance σ² of the statistic (MC, ``--mc-paths`` paths), hence
   Var_MC(N) = σ²/N, and Var_RQMC(N) as the sample variance of ``--reps``
   independent scramblings at N = 256, 1024, 4096, 16384; the variance-reduction
   factor Var_MC/Var_RQMC with a 95 % interval (χ² on R − 1 degrees of freedom),
   and the RQMC RMSE rate in N (slope of log std vs log N; MC is −1/2);
3. the cost of the samplers at the largest N, as ratios to the solve on
   pre-drawn increments: Sobol' + ndtri + bridge on the host (and the transfer),
   against the counter-based draws on the device; and against the library's own
   fused ``nhsde.simulate(solver="euler")`` at that N; and the work-normalised
   gain ratio · (t_solve + t_draws) / (t_solve + t_rqmc) (same harness, both
   samplers).  On the linear ball, Euler's exact E[x²] at the step (a covariance
   recursion) checks the bridge's scaling.

The statistics: ball E[x²(t1)] = K_xx(t1) (E[x] = 0 exactly, also for Euler),
sleigh E[H(t1)], Chaplygin's ball E[H(t1 = 4)] (≈ 3ν/(8ε)), the body on the
vibrating plane E[H(t1)] (state-dependent noise, converted to Itô).  The RMSE
is about the Euler expectation at that step (both estimators are unbiased for it).

Prints the table and writes ``results/qmc.json`` (``--quick`` writes nothing unless given ``--out``).

``--library`` measures the library's ``nhsde.statistics.quasi_monte_carlo`` instead, on the sleigh's
E[H](2) (ε 0.5, ν 1, h = 1/8), every competitor in one process, warm (best of ``--rounds``):

- κ: seconds per path-step of QMC Euler (16 scramblings) over those of plain Euler ``nhsde.simulate`` of
  the same paths and step, at 1024 and 4096 points per scrambling;
- wall time to a standard error ``--target-se`` of QMC Euler, QMC ``PlatenWeak2(increments='gaussian')``
  and plain Monte Carlo ``weak2`` (three-point) and weak2-gaussian: QMC doubles its points per scrambling
  until its reported SE is below the target; plain MC runs ``σ²/target²`` paths from a pilot's ``σ²``.
  Each row reports its bias against the closed form ``H0 e^{−4εt} + ν(1 − e^{−4εt})/(4ε)``.

Run it against an older library with ``PYTHONPATH=<old>/src`` for the "before" numbers (solvers that
library refuses are reported as such).
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
import scipy  # noqa: E402
from estimators import CASES  # noqa: E402
from scipy.special import ndtri  # noqa: E402
from scipy.stats import chi2, qmc  # noqa: E402

import nhsde  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
BLOCK = 64  # the library's paths per random block (nhsde._brownian.BLOCK)
CLIP = 2.0**-53


def scene_case(name):
    """(case of estimators.py, Euler step, statistic name) for the scene ``name``."""
    if name == "ball-fine":
        case = CASES["ball"]()
        case["name"] = "ball-fine"
        return case, 1 / 64, "x^2"
    if name == "chaplygin-ball-coarse":
        case = CASES["chaplygin-ball"]()
        case["name"] = "chaplygin-ball-coarse"
        return case, case["dts"][0], "H"
    case = CASES[name]()
    dt = case["dts"][1]
    return case, dt, ("x^2" if name == "ball" else "H")


def statistic_fn(system, stat):
    if stat == "x^2":
        obs = system.observe(("x",))
        return lambda t, y, p: obs(t, y, p)[0] ** 2
    obs = system.observe(("energy",))
    return lambda t, y, p: obs(t, y, p)[0]


def make_solve(system, y0, t1, n_steps, stat):
    """Jitted ``dw (N, n_steps, m) -> g(Y_N)`` of Euler–Maruyama for the Itô form of ``system``."""
    system = system.converted("ito")
    params, dt = system.params, t1 / n_steps
    g = statistic_fn(system, stat)

    def path(dw):
        def step(y, inp):
            k, w = inp
            t = k * dt
            return y + system.drift(t, y, params) * dt + system.diffusion(t, y, params) @ w, None

        y, _ = jax.lax.scan(step, y0, (jnp.arange(n_steps), dw))
        return g(t1, y, params)

    return jax.jit(jax.vmap(path))


def make_mc_draws(n_steps, m, dt):
    """Jitted counter-based increments ``(key, first_block, n_blocks) -> (n_blocks·64, n_steps, m)``."""

    @jax.jit
    def draws(key, first_block, n_blocks_arr):
        blocks = first_block + jnp.arange(n_blocks_arr.shape[0])

        def block(b):
            bk = jax.random.fold_in(key, b)
            z = jax.vmap(lambda k: jax.random.normal(jax.random.fold_in(bk, k), (BLOCK, m)))(jnp.arange(n_steps))
            return jnp.swapaxes(z, 0, 1)  # (BLOCK, n_steps, m)

        return math.sqrt(dt) * jax.vmap(block)(blocks).reshape(-1, n_steps, m)

    return lambda key, n: draws(key, 0, jnp.zeros(n // BLOCK))


def bridge_plan(n_steps):
    """Brownian-bridge order on grid indices 0..n: list of (index, left, right), coarse levels first (BFS)."""
    plan, queue = [(n_steps, 0, None)], [(0, n_steps)]
    while queue:
        nxt = []
        for lo, hi in queue:
            if hi - lo > 1:
                mid = (lo + hi) // 2
                plan.append((mid, lo, hi))
                nxt += [(lo, mid), (mid, hi)]
        queue = nxt
    return plan


def rqmc_increments(n_paths, n_steps, m, t1, seed, plan):
    """Scrambled Sobol' → ndtri → Brownian bridge per channel → increments ``(N, n_steps, m)`` (numpy)."""
    u = qmc.Sobol(n_steps * m, scramble=True, rng=seed).random_base2(int(math.log2(n_paths)))
    z = ndtri(np.clip(u, CLIP, 1 - CLIP)).reshape(n_paths, n_steps, m)  # z[:, k, c]: bridge node k of channel c
    h = t1 / n_steps
    w = np.zeros((n_paths, n_steps + 1, m))
    for k, (i, lo, hi) in enumerate(plan):
        if hi is None:
            w[:, i] = math.sqrt(t1) * z[:, k]
        else:
            a, b = (hi - i) / (hi - lo), (i - lo) / (hi - lo)
            w[:, i] = a * w[:, lo] + b * w[:, hi] + math.sqrt((i - lo) * (hi - i) / (hi - lo) * h) * z[:, k]
    return np.diff(w, axis=1)


def euler_linear_x2(system, y0, t1, n_steps):
    """E[x²] of Euler–Maruyama for a linear system with additive noise, exactly (covariance recursion)."""
    params, h = system.params, t1 / n_steps
    a = jax.jacfwd(lambda y: system.drift(0.0, y, params))(y0)
    b = system.diffusion(0.0, y0, params)
    step = jnp.eye(y0.size) + h * a
    mean, cov = y0, jnp.zeros((y0.size, y0.size))
    for _ in range(n_steps):
        mean, cov = step @ mean, step @ cov @ step.T + h * b @ b.T
    i = system.layout.index("x")
    return float(cov[i, i] + mean[i] ** 2)


def best_seconds(fn, rounds):
    jax.block_until_ready(fn())
    best = math.inf
    for _ in range(rounds):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best


def sanity(case, system, gs, dt, stat, n_paths):
    """z-score of the loop's MC mean (the samples ``gs``) against ``nhsde.simulate(..., solver="euler")``."""
    ens = nhsde.simulate(
        system,
        case["y0"],
        jax.random.key(12),
        n_paths=n_paths,
        t1=case["t1"],
        dt=dt,
        solver="euler",
        save=case["save"],
    )
    mean, cov, mean_se, cov_se = ens.select(case["save"].names)
    if stat == "x^2":  # E[x²] = K_xx + E[x]²
        ref, ref_se = float(cov[-1, 0, 0] + mean[-1, 0] ** 2), float(cov_se[-1, 0, 0])
    else:
        ref, ref_se = float(mean[-1, 0]), float(mean_se[-1, 0])
    ours, ours_se = float(gs.mean()), float(gs.std(ddof=1) / math.sqrt(gs.size))
    z = (ours - ref) / math.hypot(ours_se, ref_se)
    return dict(loop=ours, loop_se=ours_se, simulate=ref, simulate_se=ref_se, z=z)


def run_case(name, args):
    case, dt, stat = scene_case(name)
    system, t1 = case["system"], case["t1"]
    n_steps, m = round(t1 / dt), case["system"].noise_dim
    d = n_steps * m
    if d > 21201:
        raise ValueError(f"{name}: d = {d} exceeds scipy's Sobol' limit 21201.")
    y0 = case["y0"].astype(jnp.float64)
    solve = make_solve(system, y0, t1, n_steps, stat)
    mc_draws = make_mc_draws(n_steps, m, dt)
    plan = bridge_plan(n_steps)
    print(f"\n[{name}] E[{stat}(t1={t1:g})], Euler h = {dt:g}: n_steps {n_steps} × noise_dim {m} = d {d}")

    # MC per-path variance σ², in chunks of the largest N
    chunk = max(args.ns)
    keys = [jax.random.fold_in(jax.random.key(1), c) for c in range(args.mc_paths // chunk)]
    gs = np.concatenate([np.asarray(solve(mc_draws(k, chunk))) for k in keys])
    sigma2 = float(gs.var(ddof=1))
    sigma2_se = float(np.std((gs - gs.mean()) ** 2, ddof=1) / math.sqrt(gs.size))
    mc_mean, mc_se = float(gs.mean()), math.sqrt(sigma2 / gs.size)
    print(f"  MC: mean {mc_mean:.6g} ± {mc_se:.2g}, σ² {sigma2:.4g} ± {sigma2_se:.1g} ({gs.size} paths)")
    check = sanity(case, system, gs, dt, stat, args.sanity_paths)
    print(
        f"  sanity: loop (MC) {check['loop']:.5g} ± {check['loop_se']:.2g} vs simulate(euler, {args.sanity_paths} "
        f"paths) {check['simulate']:.5g} ± {check['simulate_se']:.2g}  (z = {check['z']:+.2f})"
    )

    euler_exact = euler_linear_x2(system, y0, t1, n_steps) if stat == "x^2" else None
    if euler_exact is not None:
        print(f"  Euler's exact E[x²] at this step {euler_exact:.6g} (the bridge's check)")
    rows = []
    r = args.reps
    lo_q, hi_q = chi2.ppf(0.025, r - 1), chi2.ppf(0.975, r - 1)
    for n in args.ns:
        ests = np.array(
            [
                float(jnp.mean(solve(jnp.asarray(rqmc_increments(n, n_steps, m, t1, 1000 * n + s, plan)))))
                for s in range(r)
            ]
        )
        var_rqmc = float(ests.var(ddof=1))
        var_mc = sigma2 / n
        ratio = var_mc / var_rqmc
        rows.append(
            dict(
                N=n,
                R=r,
                mean_rqmc=float(ests.mean()),
                var_mc=var_mc,
                var_rqmc=var_rqmc,
                ratio=ratio,
                ratio_95=[ratio * lo_q / (r - 1), ratio * hi_q / (r - 1)],
                rmse_rqmc=math.sqrt(var_rqmc),
            )
        )
        print(
            f"  N {n:>6}: Var_MC {var_mc:.3e}  Var_RQMC {var_rqmc:.3e}  ratio {ratio:7.2f} "
            f"[{rows[-1]['ratio_95'][0]:.2f}, {rows[-1]['ratio_95'][1]:.2f}]  RQMC mean {ests.mean():.6g}"
        )
    ns = np.array([row["N"] for row in rows], float)
    rate = float(np.polyfit(np.log(ns), np.log([row["rmse_rqmc"] for row in rows]), 1)[0])
    print(f"  RQMC RMSE ∝ N^{rate:.2f} (MC: N^-0.50)")

    # sampling cost at the largest N, relative to the solve on pre-drawn increments
    n = max(args.ns)
    dw = mc_draws(jax.random.key(3), n)
    t_solve = best_seconds(lambda: solve(dw), args.rounds)
    t_mc = best_seconds(lambda: mc_draws(jax.random.key(4), n), args.rounds)

    def host_sobol():
        return qmc.Sobol(d, scramble=True, rng=5).random_base2(int(math.log2(n)))

    def host_all():
        return jnp.asarray(rqmc_increments(n, n_steps, m, t1, 5, plan))

    def library():
        return nhsde.simulate(
            system, case["y0"], jax.random.key(6), n_paths=n, t1=t1, dt=dt, solver="euler", save=case["save"]
        ).mean

    t_sobol = best_seconds(host_sobol, args.rounds)
    t_rqmc = best_seconds(host_all, args.rounds)
    t_sim = best_seconds(library, args.rounds)
    gain = rows[-1]["ratio"] * (t_solve + t_mc) / (t_solve + t_rqmc)
    timings = dict(
        N=n,
        simulate_s=t_sim,
        solve_s=t_solve,
        mc_draws_s=t_mc,
        sobol_points_s=t_sobol,
        rqmc_total_s=t_rqmc,
        mc_draws_over_solve=t_mc / t_solve,
        rqmc_over_solve=t_rqmc / t_solve,
        sobol_points_over_solve=t_sobol / t_solve,
        rqmc_over_simulate=t_rqmc / t_sim,
        work_normalised_gain=gain,
    )
    print(
        f"  cost at N {n}: solve {t_solve * 1e3:.1f} ms; counter-based draws {t_mc / t_solve:.2f}× the solve; "
        f"Sobol'+ndtri+bridge+transfer {t_rqmc / t_solve:.2f}× (Sobol' points alone {t_sobol / t_solve:.2f}×)\n"
        f"    nhsde.simulate(euler) {t_sim * 1e3:.1f} ms; RQMC generation / simulate {t_rqmc / t_sim:.2f}; "
        f"work-normalised gain ratio·(t_solve + t_draws)/(t_solve + t_rqmc) {gain:.1f}"
    )
    return dict(
        scene=name,
        statistic=f"E[{stat}(t1)]",
        t1=t1,
        dt=dt,
        n_steps=n_steps,
        noise_dim=m,
        d=d,
        exact=case["exact"],
        euler_exact=euler_exact,
        sanity=check,
        mc=dict(n_paths=int(gs.size), mean=mc_mean, se=mc_se, sigma2=sigma2, sigma2_se=sigma2_se),
        rows=rows,
        rate=rate,
        timings=timings,
    )


def library(args):
    """The library's QMC on the sleigh's E[H](2): κ against plain Euler and wall time to ``args.target_se`` (module)."""
    from estimators import sleigh_case

    from nhsde.statistics import quasi_monte_carlo

    case = sleigh_case()
    system, y0, t1, save, exact = case["system"], case["y0"], case["t1"], case["save"], case["exact"]
    dt, replicates = 1 / 8, 16
    steps = round(t1 / dt)
    gaussian = nhsde.PlatenWeak2(increments="gaussian")

    def qmc(n, solver="euler", key=0):
        return quasi_monte_carlo(
            system, y0, jax.random.key(key), n_paths=n, t1=t1, dt=dt, replicates=replicates, solver=solver, save=save
        )

    def mc(n, solver, key=0):
        return nhsde.simulate(system, y0, jax.random.key(key), n_paths=n, t1=t1, dt=dt, solver=solver, save=save)

    def timed(fn):
        return best_seconds(lambda: fn().mean, args.rounds)

    print(f"[library] sleigh E[H(2)] = {exact:.6g}, h = {dt:g} ({steps} steps), {replicates} scramblings")
    kappa = {}
    for n in (1024, 4096):
        t_q, t_e = timed(lambda n=n: qmc(n)), timed(lambda n=n: mc(replicates * n, "euler"))
        kappa[n] = t_q / t_e
        print(
            f"  κ at {n} points × {replicates}: QMC {t_q * 1e3:.1f} ms, plain Euler {t_e * 1e3:.1f} ms, "
            f"κ {t_q / t_e:.2f}"
        )

    rows = []
    for label, solver in (("QMC euler", "euler"), ("QMC weak2-gaussian", gaussian)):
        n, res = BLOCK, None
        try:
            while (res := qmc(n, solver)).mean_se[-1, 0] > args.target_se:
                n *= 2
        except ValueError as e:
            print(f"  {label}: refused ({str(e).splitlines()[0][:120]})")
            continue
        seconds = timed(lambda n=n, solver=solver: qmc(n, solver, key=1))
        rows.append((label, replicates * n, float(res.mean_se[-1, 0]), float(res.mean[-1, 0]) - exact, seconds))
    for label, solver in (("MC weak2", "weak2"), ("MC weak2-gaussian", gaussian)):
        pilot = mc(1 << 14, solver)
        n = BLOCK * math.ceil(float(pilot.mean_se[-1, 0]) ** 2 * (1 << 14) / args.target_se**2 / BLOCK)
        res = mc(n, solver, key=1)
        seconds = timed(lambda n=n, solver=solver: mc(n, solver, key=1))
        rows.append((label, n, float(res.mean_se[-1, 0]), float(res.mean[-1, 0]) - exact, seconds))
    print(f"  to SE {args.target_se:g}:")
    for label, n, se, bias, seconds in rows:
        ratio = seconds / rows[-1][-1]
        print(
            f"    {label:<20} {n:>9} paths  SE {se:.2e}  error {bias:+.2e}  {seconds * 1e3:8.1f} ms "
            f"({ratio:.3f}× MC weak2-gaussian)"
        )
    return kappa, rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="R = 16, N ≤ 4096, fewer MC paths")
    parser.add_argument("--scenes", default="ball,ball-fine,sleigh,chaplygin-ball-coarse,chaplygin-ball,body")
    parser.add_argument("--reps", type=int, default=32, help="independent scramblings R per N")
    parser.add_argument("--mc-paths", type=int, default=1 << 17)
    parser.add_argument("--sanity-paths", type=int, default=1 << 16)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default=None, help="JSON path (default results/qmc.json; none with --quick)")
    parser.add_argument("--library", action="store_true", help="time the library's QMC on the sleigh (module)")
    parser.add_argument("--target-se", type=float, default=1e-4, help="--library: the standard error to reach")
    args = parser.parse_args()
    if args.library:
        library(args)
        return
    args.ns = [256, 1024, 4096] if args.quick else [256, 1024, 4096, 16384]
    if args.quick:
        args.reps, args.mc_paths, args.sanity_paths = 16, 1 << 14, 1 << 14
    start = time.perf_counter()
    cases = [run_case(name, args) for name in args.scenes.split(",")]

    print(
        "\nscene                  statistic   d    "
        + "".join(f"  Var_MC/Var_RQMC@{n:<6}" for n in args.ns)
        + "  RQMC rate  gen/simulate  gain@N_max"
    )
    for c in cases:
        cells = [f"  {r['ratio']:<8.3g}[{r['ratio_95'][0]:.3g},{r['ratio_95'][1]:.3g}]".ljust(24) for r in c["rows"]]
        tm = c["timings"]
        print(
            f"{c['scene']:<22} {c['statistic']:<11} {c['d']:<4} "
            + "".join(cells)
            + f"  N^{c['rate']:<7.2f}  {tm['rqmc_over_simulate']:<12.2f}  {tm['work_normalised_gain']:.3g}"
        )
    machine = dict(
        platform=platform.platform(),
        cpus=os.cpu_count(),
        loadavg_end=list(os.getloadavg()),
        wall_seconds=time.perf_counter() - start,
        versions=dict(jax=jax.__version__, scipy=scipy.__version__, nhsde=nhsde.__version__),
    )
    out = args.out or (None if args.quick else OUT / "qmc.json")
    if out is not None:
        pathlib.Path(out).write_text(json.dumps(dict(machine=machine, args=vars(args), cases=cases), indent=1))
    print(f"\n{machine['wall_seconds']:.0f} s" + (f"; wrote {out}" if out else ""))


if __name__ == "__main__":
    main()
