"""A scene from its Lagrangian against the same scene written by hand: warm simulate, value_and_grad and jacfwd.

    python benchmarks/spec_route.py [--paths 4096] [--steps 1000] [--repeats 5]

Both run in this process, round robin, float32, Euler; each figure is the median of ``--repeats`` warm runs, and
the ratio (spec ÷ hand-written) is what to read (absolute times on a shared machine mean little).  Also the vector
fields alone: drift and diffusion of 4096 states under ``jit(vmap)``.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import nhsde
from nhsde.scenes import SCENES

PAIRS = {"sleigh": ("chaplygin-sleigh-from-spec", "chaplygin-sleigh")}


def _timed(f, repeats: int) -> float:
    jax.block_until_ready(f())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def workloads(name: str, n_paths: int, steps: int):
    """``{what: thunk}`` for one scene: the vector fields, forward simulate, value_and_grad, jacfwd in (ε, ν)."""
    cls = SCENES[name]
    y0 = jnp.asarray(cls().initial_state(), jnp.float32)
    t1 = steps * 0.01

    def statistic(eps, nu):
        ens = nhsde.simulate(cls(eps=eps, nu=nu).build(), y0, jax.random.key(0), n_paths=n_paths, t1=t1, dt=0.01)
        return jnp.sum(ens.mean[-1]) + jnp.trace(ens.cov[-1])

    system = cls(eps=0.5, nu=0.5).build()
    params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), system.params)
    states = y0 + 0.1 * jax.random.normal(jax.random.key(1), (4096, y0.size), jnp.float32)
    fields = jax.jit(jax.vmap(lambda y: (system.drift_fn(0.0, y, params), system.diffusion_fn(0.0, y, params))))
    forward = jax.jit(statistic)
    value_and_grad = jax.jit(jax.value_and_grad(statistic, argnums=(0, 1)))
    jacfwd = jax.jit(jax.jacfwd(statistic, argnums=(0, 1)))
    eps, nu = jnp.float32(0.5), jnp.float32(0.5)
    return {
        "vector fields (4096 states)": lambda: fields(states),
        "forward simulate": lambda: forward(eps, nu),
        "value_and_grad": lambda: value_and_grad(eps, nu),
        "jacfwd": lambda: jacfwd(eps, nu),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--paths", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(f"{jax.devices()[0].platform}, {args.paths} paths × {args.steps} Euler steps, float32")
    print("| scene | workload | spec (s) | hand-written (s) | spec ÷ hand |\n|---|---|---:|---:|---:|")
    for label, (spec_name, hand_name) in PAIRS.items():
        spec, hand = workloads(spec_name, args.paths, args.steps), workloads(hand_name, args.paths, args.steps)
        for what in spec:
            times = {"spec": [], "hand": []}
            for _ in range(args.repeats):  # round robin: the load falls on both alike
                times["spec"].append(_timed(spec[what], 1))
                times["hand"].append(_timed(hand[what], 1))
            s, h = float(np.median(times["spec"])), float(np.median(times["hand"]))
            print(f"| {label} | {what} | {s:.4g} | {h:.4g} | {s / h:.2f} |", flush=True)


if __name__ == "__main__":
    main()
