"""The control variate against plain Monte Carlo at the same solver and step, in one process.

    python benchmarks/control_variate.py [--paths 8192] [--rounds 3] [--scenes ball,sleigh,chaplygin-ball]

For each scene of ``benchmarks/estimators.py`` it reads, from
``results/estimators.json``, the best plain Monte-Carlo setting (solver, step,
paths) for RMSE = 1e-3·|value| and measures here, interleaved and warm:

1. the wall time per path of plain ``simulate`` and of ``control_variate`` with that
   solver and step (the control costs a second solve and a Jacobian-vector product);
2. the per-path variance of the target with and without the control (``N`` paths);
3. the time the control variate needs for the same Monte-Carlo error,
   ``N_plain · (σ²_cv/σ²_plain) · (seconds per path, cv)``, against the plain setting's
   ``N_plain · (seconds per path, plain)``, and the bias of the control-variate
   estimate against the exact value (with ``--bias-paths`` paths).

Writes ``results/control_variate.json``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402
from estimators import CASES, GAUSS, pick  # noqa: E402

import nhsde  # noqa: E402
from nhsde.statistics import control_variate  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"


def solver_object(name):
    return GAUSS if name == "weak2-gauss" else name


def seconds_per_path(fn, n_paths, rounds):
    jax.block_until_ready(fn())
    best = np.inf
    for _ in range(rounds):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best / n_paths


def run_case(case, plain_setting, args):
    solver, dt, n_plain = plain_setting["solver"], plain_setting["dt"], plain_setting["n_paths"]
    dt = case["t1"] / round(case["t1"] / dt)
    common = dict(t1=case["t1"], dt=dt, solver=solver_object(solver), save=case["save"])

    def plain(n, key=0):
        return nhsde.simulate(case["system"], case["y0"], jax.random.key(key), n_paths=n, **common)

    def cv(n, key=0):
        return control_variate(case["system"], case["y0"], jax.random.key(key), n_paths=n, **common)

    n = args.paths
    t_plain = seconds_per_path(lambda: plain(n).mean, n, args.rounds)
    t_cv = seconds_per_path(lambda: cv(n).mean, n, args.rounds)
    est = cv(n, key=1)
    _, se_cv = pick(case, est)
    _, se_plain = pick(case, est.plain)
    reduction = (se_plain / se_cv) ** 2 if se_cv > 0 else float("inf")
    cv_paths = max(64, int(np.ceil(n_plain / reduction)))  # an exact control (the linear ball) still samples 64
    big = cv(args.bias_paths, key=2)
    value, se = pick(case, big)
    exact = case["exact"]
    row = dict(
        solver=solver,
        dt=dt,
        plain_paths=n_plain,
        plain_seconds=n_plain * t_plain,
        cv_paths=cv_paths,
        cv_seconds=cv_paths * t_cv,
        variance_reduction=reduction,
        cost_ratio_per_path=t_cv / t_plain,
        cv_bias=None if exact is None else value - exact,
        cv_bias_se=se,
        target_rmse=plain_setting["eps"],
    )
    row["speedup"] = row["plain_seconds"] / row["cv_seconds"]
    print(
        f"{case['name']}: {solver} dt={dt:.4g}: variance reduced {reduction:.1f}×, cost per path {t_cv / t_plain:.2f}× "
        f"→ {row['plain_seconds']:.3g} s plain vs {row['cv_seconds']:.3g} s control variate ({row['speedup']:.1f}×); "
        + ("" if exact is None else f"CV bias {value - exact:+.2e} ± {se:.1e} (target RMSE {row['target_rmse']:.1e})"),
        flush=True,
    )
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="ball,sleigh,chaplygin-ball")
    parser.add_argument("--paths", type=int, default=8192)
    parser.add_argument("--bias-paths", type=int, default=1 << 18)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    recorded = {c["name"]: c for c in json.loads((OUT / "estimators.json").read_text())["cases"]}
    start = time.perf_counter()
    rows = {}
    for name in args.scenes.split(","):
        case = CASES[name]()
        best = recorded[name]["summary"]["best_plain"]
        rows[name] = run_case(case, best, args)
    machine = dict(
        loadavg_end=list(__import__("os").getloadavg()),
        wall_seconds=time.perf_counter() - start,
        versions=dict(jax=jax.__version__, nhsde=nhsde.__version__),
    )
    (OUT / "control_variate.json").write_text(json.dumps(dict(machine=machine, args=vars(args), cases=rows), indent=1))


if __name__ == "__main__":
    main()
