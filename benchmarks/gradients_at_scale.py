"""Gradients of a drift statistic with respect to (ε, ν): cost against steps and paths.

    python benchmarks/gradients_at_scale.py [--quick]

For the ball on the vibrating plane and K_xx(t1): forward run, reverse mode with
per-interval checkpointing (simulate's default), reverse mode storing every step
(checkpoint=False), and forward mode (jax.jacfwd over the two parameters).
Reports wall time (best of 3, after compilation) and XLA's peak buffer memory
(temporary + output) of each compiled program, as ratios to the forward run,
and writes benchmarks/results/gradients_at_scale.json.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp

import nhsde
from nhsde.scenes import BallOnVibratingPlane

OUT = pathlib.Path(__file__).parent / "results"


def measure(fn, *args, repeats=3):
    compiled = jax.jit(fn).lower(*args).compile()
    memory = compiled.memory_analysis()
    jax.block_until_ready(compiled(*args))
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - start)
    return best, int(memory.temp_size_in_bytes + memory.output_size_in_bytes)


def statistic(steps, paths, checkpoint):
    def k_xx(eps, nu):
        scene = BallOnVibratingPlane(eps=eps, nu=nu)
        ens = nhsde.simulate(
            scene.build(),
            scene.initial_state(),
            jax.random.key(0),
            n_paths=paths,
            t1=steps * 0.01,
            dt=0.01,
            save=nhsde.Save(names=("x",), n=11),
            batching=nhsde.Batching(chunk_size=min(paths, 4096), checkpoint=checkpoint),
        )
        return ens.cov[-1, 0, 0]

    return k_xx


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    grid = [(250, 1024), (1000, 1024)] if args.quick else [(250, 4096), (1000, 4096), (4000, 4096), (1000, 16384)]
    eps, nu = jnp.float32(1.0), jnp.float32(1.0)
    rows = []
    print(f"{'steps':>6}{'paths':>7}  {'mode':<28}{'seconds':>9}{'x fwd':>7}{'peak MB':>9}{'x fwd':>7}")
    for steps, paths in grid:
        fwd = statistic(steps, paths, True)
        modes = {
            "forward": fwd,
            "reverse, checkpointed": jax.value_and_grad(fwd, argnums=(0, 1)),
            "reverse, every step stored": jax.value_and_grad(statistic(steps, paths, False), argnums=(0, 1)),
            "forward mode (jacfwd)": jax.jacfwd(fwd, argnums=(0, 1)),
        }
        base = None
        for mode, fn in modes.items():
            seconds, peak = measure(fn, eps, nu)
            base = base or (seconds, peak)
            rows.append(
                dict(
                    steps=steps,
                    paths=paths,
                    mode=mode,
                    seconds=seconds,
                    peak_bytes=peak,
                    time_ratio=seconds / base[0],
                    memory_ratio=peak / base[1],
                )
            )
            print(
                f"{steps:>6}{paths:>7}  {mode:<28}{seconds:>9.3f}{seconds / base[0]:>7.2f}"
                f"{peak / 2**20:>9.1f}{peak / base[1]:>7.1f}"
            )
    OUT.mkdir(exist_ok=True)
    (OUT / "gradients_at_scale.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
