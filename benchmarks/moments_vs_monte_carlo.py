"""Normal-approximation (moment) method against Monte Carlo on the noisy Chaplygin sleigh.

Run from the repository root::

    python benchmarks/moments_vs_monte_carlo.py           # 16384 paths, 7 values of ν
    python benchmarks/moments_vs_monte_carlo.py --quick   # 2048 paths, 3 values of ν (smoke test)

Scene: ``nhsde.scenes.ChaplyginSleigh`` (ε = 0.1, m = I = a = 1), from rest at
the origin moving at unit speed; statistics are the drift statistics of the
contact point at ``t1 = 3``: systematic drift ``m_x``, ``m_y`` and fluctuation
drift ``K_xx``, ``K_xy``, ``K_yy``.  For each noise intensity ν:

- moment method: ``normal_approximation`` (Gaussian closure, order-5
  Gauss–Hermite cubature over (θ, v, ω), Dopri8 with dt = 0.02, float64); its
  cubature and step error is measured against order 9 with dt = 0.01 and
  reported, so the error shown is the closure's, not the quadrature's;
- Monte Carlo: ``simulate`` with SRA1 (strong order 1.5 for additive noise),
  dt = 0.005, float64, with the standard errors of every statistic.

The error of the moment method is reported relative to the Monte-Carlo value
and in units of the Monte-Carlo standard error; the nonlinearity of the sleigh
(ω² and vω in the velocity equations, v cos θ in the kinematics) grows with ν,
and so does the error.  Timing: each method is a ``jax.jit`` of
``(ε, ν) → (m, K)`` at ``t1``, compiled and run once, then timed ``--repeats``
times alternately (the minimum is reported); the speed-up is the ratio of the
Monte-Carlo time to the moment-method time measured in the same run.  Results
go to ``benchmarks/results/moments_vs_monte_carlo.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np

import nhsde
from nhsde.scenes import ChaplyginSleigh
from nhsde.statistics import drift_statistics, normal_approximation

EPS, T1 = 0.1, 3.0
NAMES = ("x", "y")


def moment_method(order, dt):
    def f(eps, nu):
        scene = ChaplyginSleigh(eps=eps, nu=nu)
        ens = normal_approximation(
            scene.build(), scene.initial_state().astype(jnp.float64), t1=T1, dt=dt, save=nhsde.Save(n=2), order=order
        )
        stats = drift_statistics(ens)
        return stats.systematic[-1], stats.fluctuation[-1]

    return jax.jit(f)


def monte_carlo(n_paths):
    def f(eps, nu):
        scene = ChaplyginSleigh(eps=eps, nu=nu)
        ens = nhsde.simulate(
            scene.build(),
            scene.initial_state().astype(jnp.float64),
            jax.random.key(0),
            n_paths=n_paths,
            t1=T1,
            dt=0.005,
            solver="sra1",
            save=nhsde.Save(n=2),
        )
        stats = drift_statistics(ens)
        return stats.systematic[-1], stats.fluctuation[-1], stats.systematic_se[-1], stats.fluctuation_se[-1]

    return jax.jit(f)


def timed(fn, *args):
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--paths", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    n_paths = args.paths or (2048 if args.quick else 16384)
    nus = [0.003, 0.1, 1.0] if args.quick else [0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0]

    nam, nam_fine, mc = moment_method(5, 0.02), moment_method(9, 0.01), monte_carlo(n_paths)
    load_before = os.getloadavg()
    eps = jnp.float64(EPS)
    _, compile_nam = timed(nam, eps, jnp.float64(nus[0]))
    _, compile_mc = timed(mc, eps, jnp.float64(nus[0]))
    rows = []
    for nu in nus:
        nu_ = jnp.float64(nu)
        t_nam, t_mc = [], []
        for _ in range(args.repeats):
            (m, k), dt_nam = timed(nam, eps, nu_)
            (m_mc, k_mc, m_se, k_se), dt_mc = timed(mc, eps, nu_)
            t_nam.append(dt_nam)
            t_mc.append(dt_mc)
        m_fine, k_fine = nam_fine(eps, nu_)
        m, k, m_mc, k_mc, m_se, k_se = (np.asarray(a) for a in (m, k, m_mc, k_mc, m_se, k_se))
        iu = [(0, 0), (0, 1), (1, 1)]
        row = {
            "nu": nu,
            "moments": {"m": m.tolist(), "K": [k[i, j] for i, j in iu]},
            "monte_carlo": {
                "m": m_mc.tolist(),
                "m_se": m_se.tolist(),
                "K": [k_mc[i, j] for i, j in iu],
                "K_se": [k_se[i, j] for i, j in iu],
            },
            "error_in_se": {
                "m": (np.abs(m - m_mc) / m_se).tolist(),
                "K": [abs(k[i, j] - k_mc[i, j]) / k_se[i, j] for i, j in iu],
            },
            "relative_error": {
                "m_x": abs(m[0] - m_mc[0]) / abs(m_mc[0]),
                "K_xx": abs(k[0, 0] - k_mc[0, 0]) / k_mc[0, 0],
                "K_yy": abs(k[1, 1] - k_mc[1, 1]) / k_mc[1, 1],
            },
            "discretisation_error": float(
                max(np.max(np.abs(m - np.asarray(m_fine))), np.max(np.abs(k - np.asarray(k_fine))))
            ),
            "seconds": {"moments": min(t_nam), "monte_carlo": min(t_mc)},
            "speedup": min(t_mc) / min(t_nam),
        }
        rows.append(row)
        r = row["relative_error"]
        print(
            f"ν={nu:<6g} rel. error m_x {r['m_x']:.2e}  K_xx {r['K_xx']:.2e}  K_yy {r['K_yy']:.2e}   "
            f"|ΔK_yy|/SE {row['error_in_se']['K'][2]:6.2f}   cubature+steps {row['discretisation_error']:.1e}   "
            f"moments {min(t_nam) * 1e3:7.1f} ms  MC {min(t_mc) * 1e3:8.1f} ms  speed-up {row['speedup']:6.0f}×"
        )
    out = {
        "scene": "ChaplyginSleigh(eps=0.1, mass=1, inertia=1, offset=1), y0 = (0, 0, 0, 1, 0)",
        "t1": T1,
        "monte_carlo": {"n_paths": n_paths, "solver": "sra1", "dt": 0.005, "dtype": "float64"},
        "moments": {
            "order": 5,
            "dt": 0.02,
            "integrator": "Dopri8 (fixed steps)",
            "dtype": "float64",
            "discretisation_error": "max |difference| of m, K from order 9, dt = 0.01",
        },
        "compile_seconds": {"moments": compile_nam, "monte_carlo": compile_mc},
        "repeats": args.repeats,
        "rows": rows,
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "jax": jax.__version__,
            "load_average_before": load_before,
            "load_average_after": os.getloadavg(),
        },
    }
    path = Path(__file__).resolve().parent / "results" / "moments_vs_monte_carlo.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
