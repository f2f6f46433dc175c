"""Seconds of ``quasi_monte_carlo`` (weak order 2 with Gaussian increments, 16 scramblings), first call and warm,
on the sleigh and Chaplygin's ball at two sizes; one JSON line.  Compare two versions in alternating fresh
processes, the other one's sources first on the path::

    python benchmarks/qmc_speed.py
    PYTHONPATH=/tmp/old/src python benchmarks/qmc_speed.py   # after: git archive REV src | tar -x -C /tmp/old
"""

import json
import time

import jax
import jax.numpy as jnp

import nhsde
from nhsde.scenes import ChaplyginBall, ChaplyginSleigh
from nhsde.statistics import quasi_monte_carlo

jax.config.update("jax_enable_x64", True)
GAUSS = nhsde.PlatenWeak2(increments="gaussian")


def main():
    ball = ChaplyginBall(eps=1.0, nu=2.0)
    scenes = {
        "sleigh": (ChaplyginSleigh(eps=0.5, nu=1.0, drift=False).build(), jnp.array([1.0, 0.5]), 2.0),
        "chaplygin-ball": (ball.build(), ball.initial_state(), 4.0),
    }
    save = nhsde.Save(names=("energy",), n=2)
    out = {}
    for scene, (system, y0, t1) in scenes.items():
        for n, steps in [(1024, 32), (8192, 128)]:

            def call(k, system=system, y0=y0, t1=t1, n=n, steps=steps):
                r = quasi_monte_carlo(
                    system, y0, jax.random.key(k), n_paths=n, t1=t1, dt=t1 / steps, solver=GAUSS, save=save
                )
                jax.block_until_ready(r.mean)
                return r

            start = time.perf_counter()
            call(0)
            first = time.perf_counter() - start
            warm = []
            for k in (1, 2):
                start = time.perf_counter()
                r = call(k)
                warm.append(time.perf_counter() - start)
            out[f"{scene} 16x{n} {steps} steps"] = dict(first=first, warm=min(warm), se=float(r.mean_se[-1, 0]))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
