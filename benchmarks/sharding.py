"""Sharded ensembles: speed-up per device or process count, statistics equal to one device.

    python benchmarks/sharding.py [--paths N] [--steps S] [--devices 8]
    python benchmarks/sharding.py --processes 2 [--paths N] [--steps S]

Devices: runs one process with XLA_FLAGS=--xla_force_host_platform_device_count=D
host devices and times simulate on 1, 2, 4, …, D of them (same key, same chunks).
Writes benchmarks/results/sharding.json.

Processes (``--processes P``): for p = 1, 2, …, P launches p processes on
127.0.0.1 joined by ``jax.distributed`` (CPU collectives over gloo), one host
device each, every process running the same ``simulate``; process 0's best of 3
times gives traj-steps/s, and the statistics of every process are compared
bitwise with p = 1.  Writes benchmarks/results/sharding_processes.json (or
``--json``).

Host devices and processes share this machine's cores, so the attainable
speed-up is bounded by the core count (printed); on real multi-device or
multi-host hardware each device brings its own.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import socket
import subprocess
import sys

OUT = pathlib.Path(__file__).parent / "results"

CHILD = """
import json, sys, time, jax, numpy as np, nhsde
from nhsde.scenes import BallOnVibratingPlane
paths, steps = int(sys.argv[1]), int(sys.argv[2])
scene = BallOnVibratingPlane()
def run(devices):
    return nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=paths, t1=steps * 0.01,
                          dt=0.01, batching=nhsde.Batching(chunk_size=4096, devices=devices))
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


PROCESS_CHILD = """
import hashlib, json, sys, time
import jax
process_id, n_processes, port, paths, steps = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], *map(int, sys.argv[4:6])
if n_processes > 1:
    jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=n_processes, process_id=process_id)
import numpy as np, nhsde
from nhsde.scenes import BallOnVibratingPlane
scene = BallOnVibratingPlane()
chunk = max(64, min(4096, paths // 4 // 64 * 64))  # at least 4 chunks: two per process at p = 2
def run():
    ens = nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=paths, t1=steps * 0.01,
                         dt=0.01, batching=nhsde.Batching(chunk_size=chunk))
    return jax.block_until_ready(ens)
start = time.perf_counter()
ens = run()
first = time.perf_counter() - start
times = []
for _ in range(3):
    start = time.perf_counter()
    run()
    times.append(time.perf_counter() - start)
stats = b"".join(np.asarray(a).tobytes() for a in (ens.mean, ens.cov, ens.mean_se, ens.cov_se))
print(json.dumps(dict(process=process_id, devices=len(jax.devices()), chunk=chunk, first_call=first,
                      seconds=min(times), statistics_sha256=hashlib.sha256(stats).hexdigest())))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def processes(args):
    """Time the same ``simulate`` in 1, 2, … ``args.processes`` processes on 127.0.0.1 (one host device each)."""
    env = dict(os.environ, XLA_FLAGS="", JAX_PLATFORMS="cpu")
    rows, ref = [], None
    for p in range(1, args.processes + 1):
        port = str(_free_port())
        procs = [
            subprocess.Popen(
                [sys.executable, "-c", PROCESS_CHILD, str(i), str(p), port, str(args.paths), str(args.steps)],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for i in range(p)
        ]
        results = []
        for proc in procs:
            out, err = proc.communicate(timeout=3600)
            if proc.returncode:
                sys.exit(f"process {len(results)} of {p} failed:\n{err[-3000:]}")
            results.append(json.loads(out.strip().splitlines()[-1]))
        digests = {r["statistics_sha256"] for r in results}
        ref = results[0]["statistics_sha256"] if ref is None else ref
        row = dict(results[0], processes=p, loadavg=os.getloadavg())
        row["traj_steps_per_s"] = args.paths * args.steps / row["seconds"]
        row["processes_agree"] = len(digests) == 1
        row["bitwise_equal_to_one_process"] = digests == {ref}
        rows.append(row)
    base = rows[0]["seconds"]
    print(f"{args.paths} paths x {args.steps} steps, {os.cpu_count()} cores, one host device per process")
    print(f"{'processes':>9}{'seconds':>10}{'traj-steps/s':>14}{'speed-up':>10}  bitwise equal to one process")
    for r in rows:
        r["speedup"] = base / r["seconds"]
        print(
            f"{r['processes']:>9}{r['seconds']:>10.3f}{r['traj_steps_per_s']:>14,.0f}{r['speedup']:>10.2f}  "
            f"{r['bitwise_equal_to_one_process'] and r['processes_agree']}"
        )
    path = pathlib.Path(args.json) if args.json else OUT / "sharding_processes.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dict(paths=args.paths, steps=args.steps, cores=os.cpu_count(), rows=rows), indent=1))
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=32768)
    parser.add_argument("--steps", type=int, default=1000, help="Euler steps of dt = 0.01 (default 1000)")
    parser.add_argument("--devices", type=int, default=8)
    parser.add_argument(
        "--processes", type=int, help="compare 1 … P processes on 127.0.0.1 (jax.distributed) instead of devices"
    )
    parser.add_argument("--json", help="where to write the results (default benchmarks/results/…)")
    args = parser.parse_args()
    if args.processes is not None:
        if args.processes < 1:
            parser.error(f"--processes {args.processes}: expected at least 1.")
        return processes(args)
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={args.devices}", JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(args.paths), str(args.steps)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    rows = json.loads(out.stdout.strip().splitlines()[-1])
    base = rows[0]["seconds"]
    print(f"{args.paths} paths x {args.steps} steps, {os.cpu_count()} cores")
    print(f"{'devices':>8}{'seconds':>10}{'speed-up':>10}{'efficiency':>12}  bitwise equal")
    for r in rows:
        r["speedup"] = base / r["seconds"]
        r["efficiency"] = r["speedup"] / r["devices"]
        print(
            f"{r['devices']:>8}{r['seconds']:>10.3f}{r['speedup']:>10.2f}{r['efficiency']:>12.2f}  "
            f"{r['bitwise_equal_to_one_device']}"
        )
    path = pathlib.Path(args.json) if args.json else OUT / "sharding.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dict(paths=args.paths, steps=args.steps, cores=os.cpu_count(), rows=rows), indent=1))


if __name__ == "__main__":
    main()
