"""Sharded ensembles: speed-up per device count, statistics equal to one device.

    python benchmarks/sharding.py [--paths N] [--devices 8]

Runs one process with XLA_FLAGS=--xla_force_host_platform_device_count=D host
devices and times simulate on 1, 2, 4, …, D of them (same key, same chunks).
Host devices share this machine's cores, so the attainable speed-up is bounded
by the core count (printed); on real multi-device hardware each device brings
its own. Writes benchmarks/results/sharding.json.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys

OUT = pathlib.Path(__file__).parent / "results"

CHILD = """
import json, sys, time, jax, numpy as np, nhsde
from nhsde.scenes import BallOnVibratingPlane
paths = int(sys.argv[1])
scene = BallOnVibratingPlane()
def run(devices):
    return nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=paths, t1=10.0, dt=0.01,
                          batching=nhsde.Batching(chunk_size=4096, devices=devices))
rows, ref = [], None
n = 1
while n <= len(jax.devices()):
    devices = jax.devices()[:n]
    ens = jax.block_until_ready(run(devices))
    best = min((lambda s: (jax.block_until_ready(run(devices)), time.perf_counter() - s)[1])(time.perf_counter())
               for _ in range(3))
    ref = ens if ref is None else ref
    equal = all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(ens)))
    rows.append(dict(devices=n, seconds=best, bitwise_equal_to_one_device=equal))
    n *= 2
print(json.dumps(rows))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=32768)
    parser.add_argument("--devices", type=int, default=8)
    args = parser.parse_args()
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={args.devices}", JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(args.paths)], env=env, capture_output=True, text=True, check=True
    )
    rows = json.loads(out.stdout.strip().splitlines()[-1])
    base = rows[0]["seconds"]
    print(f"{args.paths} paths x 1000 steps, {os.cpu_count()} cores")
    print(f"{'devices':>8}{'seconds':>10}{'speed-up':>10}{'efficiency':>12}  bitwise equal")
    for r in rows:
        r["speedup"] = base / r["seconds"]
        r["efficiency"] = r["speedup"] / r["devices"]
        print(
            f"{r['devices']:>8}{r['seconds']:>10.3f}{r['speedup']:>10.2f}{r['efficiency']:>12.2f}  "
            f"{r['bitwise_equal_to_one_device']}"
        )
    OUT.mkdir(exist_ok=True)
    (OUT / "sharding.json").write_text(json.dumps(dict(paths=args.paths, cores=os.cpu_count(), rows=rows), indent=1))


if __name__ == "__main__":
    main()
