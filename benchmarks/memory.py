"""Peak memory against paths and steps: ball on the vibrating plane and Chaplygin ball (issue: memory at scale).

Each (scene, paths, steps) runs in a fresh process (float32, chunks of 8192 paths, 11 save times) and reports its
peak resident set size (``ru_maxrss``) and the compiled program's temporary bytes.  The design promises memory
independent of paths and steps: the RSS should stay flat along both axes.

    python benchmarks/memory.py            # the default grid (about 10 minutes on 2 cores)
    python benchmarks/memory.py --quick    # a smaller grid
"""

import argparse
import json
import pathlib
import subprocess
import sys
import time

OUT = pathlib.Path(__file__).parent / "results"

CHILD = """
import json, resource, sys, time
import jax, jax.numpy as jnp, nhsde
from nhsde.scenes import BallOnVibratingPlane, ChaplyginBall
scene_name, paths, steps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
scene = {"ball": BallOnVibratingPlane(drift=False), "chaplygin-ball": ChaplyginBall()}[scene_name]
system, y0 = scene.build(), scene.initial_state().astype(jnp.float32)
kw = dict(n_paths=paths, t1=steps * 0.01, steps=nhsde.FixedSteps(0.01, max_steps=10**8), save=nhsde.Save(n=11),
          batching=nhsde.Batching(chunk_size=min(paths, 8192)), solver="euler")
run = lambda y: nhsde.simulate(system, y, jax.random.key(0), **kw).cov
temp = jax.jit(run).lower(y0).compile().memory_analysis().temp_size_in_bytes
start = time.perf_counter()
jax.block_until_ready(run(y0))
seconds = time.perf_counter() - start
print(json.dumps(dict(scene=scene_name, paths=paths, steps=steps, seconds=seconds, temp_bytes=temp,
                      peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    if args.quick:
        grid = [(s, 2**p, 10**3) for s in ("ball", "chaplygin-ball") for p in (10, 14)]
    else:
        grid = [(s, 2**p, 10**3) for s in ("ball", "chaplygin-ball") for p in (10, 14, 18, 20)]
        grid += [(s, 2**10, 10**k) for s in ("ball", "chaplygin-ball") for k in (4, 5, 6)]
        grid += [("ball", 2**24, 10**3)]
    rows = []
    for scene, paths, steps in grid:
        start = time.perf_counter()
        out = subprocess.run(
            [sys.executable, "-c", CHILD, scene, str(paths), str(steps)], capture_output=True, text=True
        )
        if out.returncode:  # reported, not hidden: e.g. every path failed
            rows.append(dict(scene=scene, paths=paths, steps=steps, error=out.stderr.strip().splitlines()[-1]))
            print(
                f"{scene:15s} paths 2^{paths.bit_length() - 1:<2d} steps {steps:>8d}: {rows[-1]['error']}", flush=True
            )
            continue
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(
            f"{scene:15s} paths 2^{paths.bit_length() - 1:<2d} steps {steps:>8d}:"
            f" peak RSS {r['peak_rss_mib']:7.1f} MiB,"
            f" temporaries {r['temp_bytes'] / 2**20:6.2f} MiB, run {r['seconds']:7.1f} s"
            f" (process {time.perf_counter() - start:.0f} s)",
            flush=True,
        )
    OUT.mkdir(exist_ok=True)
    (OUT / "memory.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
