"""A scene from its Lagrangian against the same scene written by hand: warm simulate, value_and_grad and jacfwd.

    python benchmarks/spec_route.py [--paths 4096] [--steps 1000] [--repeats 5] [--first-call 2]

Both run in this process, round robin, float32, Euler; each figure is the median of ``--repeats`` warm runs, and
the ratio (spec ÷ hand-written) is what to read (absolute times on a shared machine mean little).  Also the vector
fields alone: drift and diffusion of 4096 states under ``jit(vmap)``, and the first call (build, trace, compile and
run the forward ``simulate``) in a fresh process per try, alternating, median of ``--first-call`` tries.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from typing import Any

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
    cls: Any = SCENES[name]
    y0 = jnp.asarray(cls().initial_state(), jnp.float32)
    t1 = steps * 0.01

    system = cls(eps=0.5, nu=0.5).build()  # built once, outside the traced function: the spec checks its values

    def statistic(eps, nu):
        ens = nhsde.simulate(
            system.replace_params(eps=eps, nu=nu), y0, jax.random.key(0), n_paths=n_paths, t1=t1, dt=0.01
        )
        return jnp.sum(ens.mean[-1]) + jnp.trace(ens.cov[-1])

    params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), system.params)
    t0 = jnp.zeros((), jnp.float32)
    states = y0 + 0.1 * jax.random.normal(jax.random.key(1), (4096, y0.size), jnp.float32)
    fields = jax.jit(jax.vmap(lambda y: (system.drift_fn(t0, y, params), system.diffusion_fn(t0, y, params))))
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


def first_call(name: str, n_paths: int, steps: int) -> float:
    """Seconds from building the scene to the first forward ``simulate``'s result, in a fresh process."""
    code = (
        "import time, jax, jax.numpy as jnp, nhsde\n"
        "from nhsde.scenes import SCENES\n"
        f"cls = SCENES[{name!r}]\n"
        "y0 = jnp.asarray(cls().initial_state(), jnp.float32)\n"
        "start = time.perf_counter()\n"
        "ens = nhsde.simulate(cls(eps=0.5, nu=0.5).build(), y0, jax.random.key(0), "
        f"n_paths={n_paths}, t1={steps * 0.01}, dt=0.01)\n"
        "jax.block_until_ready(ens.mean)\n"
        "print(time.perf_counter() - start)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    return float(out.split()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--paths", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--first-call", type=int, default=2, help="fresh-process tries of the first call (0: skip)")
    parser.add_argument(
        "--only", nargs="*", default=None, help="workloads to time (default: all), e.g. 'forward simulate'"
    )
    args = parser.parse_args()
    print(f"{jax.devices()[0].platform}, {args.paths} paths × {args.steps} Euler steps, float32")
    print("| scene | workload | spec (s) | hand-written (s) | spec ÷ hand |\n|---|---|---:|---:|---:|")
    for label, (spec_name, hand_name) in PAIRS.items():
        if args.first_call:
            firsts = {"spec": [], "hand": []}
            for _ in range(args.first_call):
                firsts["spec"].append(first_call(spec_name, args.paths, args.steps))
                firsts["hand"].append(first_call(hand_name, args.paths, args.steps))
            s, h = float(np.median(firsts["spec"])), float(np.median(firsts["hand"]))
            print(f"| {label} | first call (fresh process) | {s:.4g} | {h:.4g} | {s / h:.2f} |", flush=True)
        spec, hand = workloads(spec_name, args.paths, args.steps), workloads(hand_name, args.paths, args.steps)
        for what in spec:
            if args.only is not None and what not in args.only:
                continue
            times = {"spec": [], "hand": []}
            for _ in range(args.repeats):  # round robin: the load falls on both alike
                times["spec"].append(_timed(spec[what], 1))
                times["hand"].append(_timed(hand[what], 1))
            s, h = float(np.median(times["spec"])), float(np.median(times["hand"]))
            print(f"| {label} | {what} | {s:.4g} | {h:.4g} | {s / h:.2f} |", flush=True)


if __name__ == "__main__":
    main()
