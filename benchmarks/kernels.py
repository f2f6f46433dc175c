"""The kernels of a step, counted instead of timed: the compiled programs of ``benchmarks/throughput.py``.

    python benchmarks/kernels.py [--scenes ball,sleigh,chaplygin-ball] [--steps 1000]

For each scene, the forward statistic, its ``jax.jacfwd`` in (ε, ν) and its ``jax.value_and_grad`` (the programs
``throughput.py`` times, 4096 paths, float32, Euler) are compiled on this machine's backend, and the operations in
the body of every loop that runs once per step (trip count ``--steps``) are counted by kind: ``fusion`` (a kernel),
``dot`` (a matrix product XLA left unfused), ``copy``, ``custom-call``.  On the CPU each kernel is a loop over the
paths of its own, with its inputs and outputs in memory, so the count of kernels per step is the first thing to
read when a step is slower than a hand-fused scan; unlike times, counts do not depend on the machine's load.
"""

from __future__ import annotations

import argparse
import collections
import pathlib
import re
import sys

import jax
import jax.numpy as jnp
import jax.random as jr

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import throughput  # noqa: E402  (the same programs as the throughput benchmark)

KINDS = ("fusion", "dot", "copy", "custom-call")


def computations(hlo: str) -> dict[str, list[str]]:
    """``{name: lines}`` of every computation of an HLO module's text."""
    found: dict[str, list[str]] = {}
    current = None
    for line in hlo.split("\n"):
        head = re.match(r"^(?:ENTRY )?%(\S+) ", line)
        if head and line.rstrip().endswith("{"):
            current = head.group(1)
            found[current] = []
        elif current is not None:
            found[current].append(line)
    return found


def per_step_counts(hlo: str, steps: int) -> list[dict[str, int]]:
    """The operations by kind in the body of each loop of ``steps`` iterations."""
    bodies = computations(hlo)
    counts = []
    for line in hlo.split("\n"):
        loop = re.search(r"while\(.*body=%(\S+?),.*known_trip_count\":\{\"n\":\"(\d+)\"", line)
        if loop and int(loop.group(2)) == steps:
            kinds = collections.Counter()
            for op in bodies[loop.group(1)]:
                kind = re.search(r"= \S+ ([a-z-]+)\(", op)
                if kind and kind.group(1) in KINDS:
                    kinds[kind.group(1)] += 1
            counts.append(dict(kinds))
    return counts


def programs(scene: str, n_paths: int, steps: int):
    """``{mode: compiled HLO text}``: forward, ``jacfwd`` and ``value_and_grad`` of the throughput statistic."""
    cfg = throughput.SCENES[scene]
    theta = jnp.asarray([cfg["eps"], cfg["nu"]], throughput.DTYPE)
    key = jr.key(0)
    f = throughput.nhsde_stat(scene, n_paths, steps)

    def with_aux(th, k):
        value, se = f(th, k)
        return value, (value, se)

    modes = {
        "forward": jax.jit(f),
        "jacfwd": jax.jit(jax.jacfwd(with_aux, has_aux=True)),
        "value_and_grad": jax.jit(jax.value_and_grad(f, has_aux=True)),
    }
    return {mode: str(p.lower(theta, key).compile().as_text()) for mode, p in modes.items()}


def main(argv=None):
    parser = argparse.ArgumentParser(description="The kernels of a step, counted from the compiled programs.")
    parser.add_argument("--scenes", default="ball,sleigh,chaplygin-ball")
    parser.add_argument("--paths", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args(argv)
    print(f"kernels per step: {args.paths} paths, {args.steps} Euler steps, float32, backend {jax.default_backend()}")
    print(f"{'scene':16} {'program':15} loops of {args.steps} iterations (value_and_grad: forward, backward, ...)")
    for scene in args.scenes.split(","):
        for mode, hlo in programs(scene, args.paths, args.steps).items():
            loops = " | ".join(
                ", ".join(f"{n} {k}" for k, n in sorted(c.items())) for c in per_step_counts(hlo, args.steps)
            )
            print(f"{scene:16} {mode:15} {loops}")


if __name__ == "__main__":
    main()
