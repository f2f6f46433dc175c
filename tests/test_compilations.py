"""Few programs per question: the XLA compilations of a first call, counted with ``jax_log_compiles`` in a fresh
process (a notebook user asking one question pays for every program the call compiles)."""

import json
import subprocess
import sys

COUNT = r"""
import json, logging, jax
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
counts = {}
for label, n_paths, dt in [("first", 256, 1 / 16), ("n_paths", 512, 1 / 16), ("dt", 512, 1 / 32)]:
    del compiled[:]
    nhsde.simulate(system, y0, key, n_paths=n_paths, t1=1.0, dt=dt)
    counts[label] = list(compiled)
print(json.dumps(counts))
"""


def test_simulate_compiles_few_programs():
    """On the sleigh: the first simulate compiles ≤ 8 programs (57 when the glue around the solve ran op by op),
    a new path count or step ≤ 1."""
    out = subprocess.run([sys.executable, "-c", COUNT], capture_output=True, text=True, timeout=600)
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(counts["first"]) <= 8, counts["first"]
    assert len(counts["n_paths"]) <= 1, counts["n_paths"]
    assert len(counts["dt"]) <= 1, counts["dt"]
