"""``import nhsde`` leaves the heavy optional parts (``nhsde.fit`` with optax, ``nhsde.sweep`` with xarray and pandas)
until first used, and every public name is still there: ``nhsde.fit.…``, ``from nhsde import sweep``, ``dir``.
The command leaves xarray and pandas until it reads or writes a run file."""

import subprocess
import sys

CHECK = """
import sys
import nhsde
assert not {"optax", "xarray", "pandas", "nhsde.fit", "nhsde._sweep"} & set(sys.modules), sorted(sys.modules)
assert {"fit", "sweep", "simulate"} <= set(dir(nhsde))
from nhsde import sweep
assert sweep.__module__ == "nhsde._sweep" and "xarray" in sys.modules
assert nhsde.fit.estimate.__module__ == "nhsde.fit._estimate"
from nhsde.fit import Observations
try:
    nhsde.no_such_name
except AttributeError as e:
    assert "no_such_name" in str(e)
else:
    raise AssertionError("nhsde.no_such_name")
"""


def test_fit_and_sweep_are_imported_when_first_used():
    out = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr


COMMAND = """
import contextlib, io, sys
from nhsde.runs import main
assert not {"optax", "xarray", "pandas"} & set(sys.modules), sorted(sys.modules)
with contextlib.redirect_stdout(io.StringIO()):
    assert main(["simulate", "ball-on-vibrating-plane", "--paths", "64", "--t1", "0.5", "--dt", "0.05"]) == 0
assert not {"optax", "xarray", "pandas"} & set(sys.modules), sorted(sys.modules)
from nhsde.runs import load_run
"""


def test_the_command_imports_xarray_only_for_run_files():
    """The main job without ``--out`` prints from the moment sums: about 0.3 s of import less (xarray, pandas)."""
    out = subprocess.run([sys.executable, "-c", COMMAND], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
