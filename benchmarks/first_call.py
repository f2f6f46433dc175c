"""Time to first answer of ``nhsde.simulate``: a fresh process per measurement, compilation included.

Run from the repository root::

    python benchmarks/first_call.py                            # this checkout, 3 rounds
    python benchmarks/first_call.py --against /path/to/src     # and another checkout's src/, alternately

Each round starts a new interpreter per variant (the variants alternate, so both see the same load) and
measures, on the sleigh's E[H] setting (``ChaplyginSleigh(drift=False)``, 4096 paths, dt 1/16, t1 10):
the first ``simulate`` (imports excluded, compilation included), the XLA programs it compiles
(``jax_log_compiles``), a call with twice the paths, one with half the step, and the warm call.  JAX's
persistent compilation cache is off.  Medians over the rounds; the ratio is variant / this checkout.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

SCRIPT = r"""
import json, logging, time
import jax
compiled = []
class Count(logging.Handler):
    def emit(self, record):
        if record.getMessage().startswith("Compiling "):
            compiled.append(record.getMessage().split(" ")[1])
logging.getLogger("jax").addHandler(Count())
logging.getLogger("jax").setLevel(logging.WARNING)
jax.config.update("jax_log_compiles", True)
import nhsde
scene = nhsde.scenes.ChaplyginSleigh(drift=False)
system, y0, key = scene.build(), scene.initial_state(), jax.random.key(0)
def run(n_paths, dt):
    del compiled[:]
    t = time.perf_counter()
    nhsde.simulate(system, y0, key, n_paths=n_paths, t1=10.0, dt=dt).mean.block_until_ready()
    return time.perf_counter() - t, len(compiled)
out = {}
out["first_s"], out["first_compilations"] = run(4096, 1 / 16)
out["more_paths_s"], out["more_paths_compilations"] = run(8192, 1 / 16)
out["smaller_step_s"], out["smaller_step_compilations"] = run(4096, 1 / 32)
out["warm_s"], _ = run(4096, 1 / 16)
print(json.dumps(out))
"""


def measure(src: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src), NHSDE_COMPILATION_CACHE="off", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--against", type=Path, help="another checkout's src/ folder, measured alternately")
    p.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "first_call.json")
    args = p.parse_args()
    variants = {"this checkout": Path(__file__).resolve().parents[1] / "src"}
    if args.against:
        variants["against"] = args.against.resolve()
    rows: dict[str, list[dict]] = {name: [] for name in variants}
    for r in range(args.rounds):
        for name, src in variants.items():
            rows[name].append(measure(src))
            print(f"round {r + 1} {name}: {rows[name][-1]}", flush=True)
    medians = {name: {k: statistics.median(row[k] for row in runs) for k in runs[0]} for name, runs in rows.items()}
    print(f"\nloadavg {os.getloadavg()}; medians over {args.rounds} rounds:")
    for name, m in medians.items():
        print(f"  {name:14s} " + "  ".join(f"{k} {v:.3g}" for k, v in m.items()))
    if args.against:
        ratio = {k: medians["against"][k] / medians["this checkout"][k] for k in medians["this checkout"]}
        print("  against / this: " + "  ".join(f"{k} {v:.2f}" for k, v in ratio.items()))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"rounds": rows, "medians": medians, "loadavg": os.getloadavg()}, indent=1))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
