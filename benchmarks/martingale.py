"""The martingale control variate against plain Monte Carlo at level 0 (one solver and step), in one process.

    python benchmarks/martingale.py [--paths 16384] [--solvers euler,weak2]

For the Chaplygin sleigh (``E[x² + y²](2)``, no closed form, and ``E[H](2)``) and Chaplygin's ball
(``E[γ₃](1)``, no closed form, and ``E[H](1)``) it measures, warm (each program run once before it is timed):

1. the variance reduction at equal paths, ``Var Y / Var(Y − β·M)`` on the same paths (the estimate's
   ``variance_reduction``);
2. the reduction per second including the pilot and the fit: ``reduction · t_plain / t_mcv``, with ``t_plain``
   the wall time of plain ``simulate`` of the same paths (same solver, step and key) and ``t_mcv`` that of
   ``martingale_control_variate`` (pilot of the default ``10 K`` paths with all ``K`` controls, fit, and the run
   with the fitted combinations only).

With ``--honesty`` it checks the standard errors instead (issue 36's honesty targets), for the no-closed-form
statistics with the weak scheme: the z-scores ``(estimate − reference)/SE`` of ``--keys`` independent estimates of
4096 paths, and those of their derivatives in ε and ν (``wrt``), against a reference of the same estimator on 2¹⁷
paths of another key.  The reference's own error is common to every key: it shifts the z-scores' mean, not their
standard deviation, whose target is [0.8, 1.25] (sampling band over 16 keys: about ±18 %).

Writes ``results/martingale.json`` (``results/martingale-honesty.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import nhsde  # noqa: E402
from nhsde.scenes import ChaplyginBall, ChaplyginSleigh  # noqa: E402
from nhsde.statistics import Mean, martingale_control_variate  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"


def _r2(t, y, p):
    return y[0] ** 2 + y[1] ** 2


def cases():
    sleigh = ChaplyginSleigh()
    s = sleigh.build()
    s = dataclasses.replace(s, observables=s.observables + (("r2", _r2),))
    ball = ChaplyginBall(eps=1.0, nu=2.0)
    return [
        ("sleigh", s, sleigh.initial_state(), "r2", 2.0, 0.125),
        ("sleigh", s, sleigh.initial_state(), "energy", 2.0, 0.125),
        ("chaplygin-ball", ball.build(), ball.initial_state(), "gamma_3", 1.0, 0.0625),
        ("chaplygin-ball", ball.build(), ball.initial_state(), "energy", 1.0, 0.0625),
    ]


def timed(fn, rounds):
    fn()  # compile
    best = float("inf")
    for _ in range(rounds):
        start = time.perf_counter()
        out = fn()
        jax.block_until_ready(out.mean)
        best = min(best, time.perf_counter() - start)
    return best, out


def honesty(n_keys):
    rows = []
    for scene, system, y0, name, t1, dt in cases():
        if name == "energy":
            continue
        run = dict(t1=t1, dt=dt, solver="weak2", wrt=("eps", "nu"))
        ref = martingale_control_variate(system, y0, jax.random.key(10**6), Mean(name), n_paths=2**17, **run)
        ref_value, ref_grad = float(ref.mean[-1, 0]), np.asarray(ref.derivatives.d_mean[:, -1, 0])
        z, z_grad = [], []
        for i in range(n_keys):
            est = martingale_control_variate(system, y0, jax.random.key(i), Mean(name), n_paths=4096, **run)
            z.append((float(est.mean[-1, 0]) - ref_value) / float(est.mean_se[-1, 0]))
            d = est.derivatives
            z_grad.append((np.asarray(d.d_mean[:, -1, 0]) - ref_grad) / np.asarray(d.d_mean_se[:, -1, 0]))
        z, z_grad = np.array(z), np.array(z_grad)
        row = dict(
            scene=scene,
            statistic=f"E[{name}]({t1:g})",
            keys=n_keys,
            reference=ref_value,
            reference_se=float(ref.mean_se[-1, 0]),
            z_mean=float(z.mean()),
            z_sd=float(z.std(ddof=1)),
            rmse_over_se=float(np.sqrt(np.mean(z**2))),
            z_grad_mean=z_grad.mean(axis=0).tolist(),
            z_grad_sd=z_grad.std(axis=0, ddof=1).tolist(),
        )
        rows.append(row)
        print(
            f"{scene:15s} {row['statistic']:14s} z mean {row['z_mean']:+.2f} sd {row['z_sd']:.2f}  "
            f"∂ε, ∂ν z mean {z_grad.mean(axis=0).round(2)} sd {z_grad.std(axis=0, ddof=1).round(2)}",
            flush=True,
        )
    OUT.mkdir(exist_ok=True)
    (OUT / "martingale-honesty.json").write_text(json.dumps(rows, indent=1))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--paths", type=int, default=16384)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--solvers", default="euler,weak2")
    parser.add_argument("--honesty", action="store_true")
    parser.add_argument("--keys", type=int, default=16)
    args = parser.parse_args()
    if args.honesty:
        return honesty(args.keys)
    rows = []
    for scene, system, y0, name, t1, dt in cases():
        for solver in args.solvers.split(","):
            run = dict(n_paths=args.paths, t1=t1, dt=dt, solver=solver)
            key = jax.random.key(0)
            t_plain, _ = timed(
                lambda: nhsde.simulate(system, y0, key, save=nhsde.Save(names=(name,), n=2), **run), args.rounds
            )
            t_mcv, est = timed(lambda: martingale_control_variate(system, y0, key, Mean(name), **run), args.rounds)
            reduction = float(est.variance_reduction.mean[-1, 0])
            value, se = est.value()
            row = dict(
                scene=scene,
                statistic=f"E[{name}]({t1:g})",
                solver=solver,
                dt=dt,
                paths=args.paths,
                value=float(value),
                se=float(se),
                plain_se=float(est.plain.value()[1]),
                reduction_equal_paths=reduction,
                seconds_plain=t_plain,
                seconds_mcv=t_mcv,
                reduction_per_second=reduction * t_plain / t_mcv,
            )
            rows.append(row)
            print(
                f"{scene:15s} {row['statistic']:14s} {solver:6s} value {value:.6g} ± {se:.2g} "
                f"(plain ± {row['plain_se']:.2g})  reduction {reduction:8.1f}×  "
                f"t {t_plain:.3f}s / {t_mcv:.3f}s  per second {row['reduction_per_second']:7.1f}×",
                flush=True,
            )
    OUT.mkdir(exist_ok=True)
    (OUT / "martingale.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
