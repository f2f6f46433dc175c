"""Every research notebook in ``notebooks/`` (jupytext percent ``.py``) runs end to end.

Each notebook runs as a script in a fresh interpreter (``sys.executable``), with
``NHSDE_NOTEBOOK_OUT`` pointing at a temporary directory and the Agg backend, and
must exit cleanly and write its figures there as non-empty PNG files.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(p for p in NOTEBOOK_DIR.glob("*.py") if not p.name.startswith("_"))

# Figures each known notebook must produce; any other notebook must produce at least one PNG.
EXPECTED_PNGS = {
    "ball_on_vibrating_plane.py": {
        "ball_covariances.png",
        "ball_gradients.png",
        "ball_u_histogram.png",
    },
    "fitting_friction_noise.py": {
        "fitting_ball_covariances.png",
        "fitting_ball_landscape.png",
        "fitting_calibration.png",
        "fitting_sleigh.png",
    },
    "work_precision.py": {"work_precision.png"},
    "controlled_systems.py": {"rod_energy_work.png", "gauss_compulsion.png", "beghin_servo_vs_contact.png"},
    "rubber_rolling_hierarchy.py": {"poincare_integrable.png", "poincare_unbalanced_gravity.png"},
    "body_of_revolution_vibrating_plane.py": {"nutation_density_spheroid.png", "nutation_density_routh_sphere.png"},
    "rattleback.py": {"rattleback_growth_rates.png", "rattleback_growth_fit.png", "rattleback_reversal.png"},
}

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIMEOUT_S = 600


def test_notebooks_found():
    assert NOTEBOOKS, f"no notebooks found in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(notebook: Path, tmp_path: Path):
    out = tmp_path / "figures"  # not created in advance: the notebook must create it
    env = dict(os.environ, NHSDE_NOTEBOOK_OUT=str(out), MPLBACKEND="Agg")
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    proc = subprocess.run(
        [sys.executable, str(notebook)],
        cwd=tmp_path,  # the notebook must not depend on the working directory
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    assert proc.returncode == 0, (
        f"{notebook.name} exited with {proc.returncode}\n"
        f"--- stdout (tail) ---\n{proc.stdout[-4000:]}\n--- stderr (tail) ---\n{proc.stderr[-8000:]}"
    )

    assert out.is_dir(), f"{notebook.name} did not create NHSDE_NOTEBOOK_OUT={out}"
    pngs = {p.name: p for p in out.glob("*.png")}
    expected = EXPECTED_PNGS.get(notebook.name)
    if expected is None:
        assert pngs, f"{notebook.name} wrote no PNG into {out}"
    else:
        missing = expected - pngs.keys()
        assert not missing, f"{notebook.name} did not write {sorted(missing)}; wrote {sorted(pngs)}"
    for name, path in pngs.items():
        data = path.read_bytes()
        assert len(data) > 1000, f"{name} is suspiciously small ({len(data)} bytes)"
        assert data.startswith(PNG_SIGNATURE), f"{name} is not a PNG file"
