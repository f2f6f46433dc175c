"""``import nhsde`` leaves the heavy optional parts (``nhsde.fit`` with optax, ``nhsde.sweep`` with xarray and pandas)
until first used, and every public name is still there: ``nhsde.fit.…``, ``from nhsde import sweep``, ``dir``."""

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
