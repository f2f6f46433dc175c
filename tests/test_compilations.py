"""Few programs per question: the XLA compilations of a first call, counted with ``jax_log_compiles`` in a fresh
process (a notebook user asking one question pays for every program the call compiles)."""

import json
import subprocess
import sys

COUNTER = r"""
import json, logging, jax
compiled = []
class Count(logging.Handler):
    def emit(self, record):
        if record.getMessage().startswith("Compiling "):
            compiled.append(record.getMessage().split(" ")[1])
logging.getLogger("jax").addHandler(Count())
logging.getLogger("jax").setLevel(logging.WARNING)
jax.config.update("jax_log_compiles", True)
"""

PRELUDE = (
    COUNTER
    + r"""
import nhsde
scene = nhsde.scenes.ChaplyginSleigh(drift=False)
system, y0, key = scene.build(), scene.initial_state(), jax.random.key(0)
del compiled[:]  # the scene and the key are the user's
"""
)

COUNT = (
    PRELUDE
    + r"""
counts = {}
for label, n_paths, dt in [("first", 256, 1 / 16), ("n_paths", 512, 1 / 16), ("dt", 512, 1 / 32)]:
    del compiled[:]
    nhsde.simulate(system, y0, key, n_paths=n_paths, t1=1.0, dt=dt)
    counts[label] = list(compiled)
print(json.dumps(counts))
"""
)


def counted(script: str):
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_simulate_compiles_few_programs():
    """On the sleigh: the first simulate compiles ≤ 8 programs (57 when the glue around the solve ran op by op),
    a new path count ≤ 1 (a new chunk shape), a new step none (the step count and the step are data)."""
    counts = counted(COUNT)
    assert len(counts["first"]) <= 8, counts["first"]
    assert len(counts["n_paths"]) <= 1, counts["n_paths"]
    assert counts["dt"] == [], counts["dt"]


ESTIMATOR = (
    PRELUDE
    + r"""
import sys
if sys.argv[1] in ("multilevel", "derivatives"):
    r = nhsde.statistics.multilevel_monte_carlo(
        system, y0, key, t1=1.0, dt=0.25, statistic=("mean", "energy"), rmse=1e-2, save=nhsde.Save(names=("energy",)),
        wrt=("eps", "nu") if sys.argv[1] == "derivatives" else None,
    )
    levels = len(r.n_paths_per_level)
else:
    r = nhsde.statistics.to_accuracy(system, y0, key, t1=1.0, statistic=("mean", "energy"), relative_rmse=1e-2)
    levels = r.choice
print(json.dumps({"compiled": list(compiled), "levels": levels}))
"""
)


def test_first_multilevel_monte_carlo_compiles_few_programs():
    """On the sleigh's E[energy] to 1e-2: ≤ 12 programs for all levels (157 when each level's solve and every
    statistic compiled its own): the step, the base step, the path offset and the reflection are data, and the
    per-path statistics are reduced on the host."""
    counts = counted(ESTIMATOR.replace("sys.argv[1]", "'multilevel'"))
    assert counts["levels"] >= 3
    assert len(counts["compiled"]) <= 12, counts["compiled"]
    assert counts["compiled"].count("jit(_run)") == 1, counts["compiled"]


def test_first_multilevel_monte_carlo_with_derivatives_compiles_few_programs():
    """The same with forward-mode derivatives in (ε, ν): ≤ 24 programs (53 when the forward mode's reshaping compiled
    per path count, and the runs were sliced and joined under it, 4 levels of 256 … 36864 samples): each run is
    differentiated whole, so the reshaping compiles per run size, and the runs are joined on the host."""
    counts = counted(ESTIMATOR.replace("sys.argv[1]", "'derivatives'"))
    assert counts["levels"] >= 3
    assert len(counts["compiled"]) <= 24, counts["compiled"]
    assert counts["compiled"].count("jit(_run)") == 1 and "jit(concatenate)" not in counts["compiled"], counts
    assert counts["compiled"].count("jit(transpose)") <= 2, counts["compiled"]


def test_first_to_accuracy_compiles_few_programs():
    """On the sleigh's E[energy] to 1 %: ≤ 16 programs for the pilots of both solvers, the control variate's and
    quasi-Monte Carlo's pilots and the chosen run (136 before)."""
    counts = counted(ESTIMATOR.replace("sys.argv[1]", "'accuracy'"))
    assert len(counts["compiled"]) <= 16, counts["compiled"]


COMMAND = (
    COUNTER
    + r"""
import contextlib, io
from nhsde.runs import main
with contextlib.redirect_stdout(io.StringIO()) as out:
    rc = main(["simulate", "ball-on-vibrating-plane", "--paths", "256", "--t1", "1", "--dt", "0.05"])
print(json.dumps({"rc": rc, "compiled": compiled, "out": out.getvalue()}))
"""
)


def test_the_main_job_compiles_few_programs():
    """The README's main job, small: ≤ 20 programs for the run, its derivatives and everything it prints (106 when
    the printed statistics, the effective diffusion and the closed form ran op by op, one program per operation)."""
    counts = counted(COMMAND)
    assert counts["rc"] == 0 and "closed form (S0 (3.1))" in counts["out"]
    assert len(counts["compiled"]) <= 20, counts["compiled"]
    assert counts["compiled"].count("jit(_sensitivities)") == 1, counts["compiled"]


NORMAL_APPROXIMATION = (
    PRELUDE
    + r"""
counts = {}
for label in ("first", "again"):
    del compiled[:]
    nhsde.statistics.normal_approximation(system, y0, t1=1.0, dt=0.25)
    counts[label] = list(compiled)
print(json.dumps(counts))
"""
)


def test_a_repeated_normal_approximation_compiles_nothing():
    """The closure's structure probe (second-order autodiff of the vector fields, seconds on a spec scene) is
    compiled once per system, not once per call."""
    counts = counted(NORMAL_APPROXIMATION)
    assert counts["again"] == [], counts["again"]
