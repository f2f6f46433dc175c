"""Every research notebook in ``notebooks/`` (jupytext percent ``.py``) runs end to end.

Each notebook runs as a script in a fresh interpreter (``sys.executable``), with
``NHSDE_NOTEBOOK_OUT`` pointing at a temporary directory and the Agg backend, and
must exit cleanly and write its figures there as non-empty PNG files.  The default
run sets ``NHSDE_NOTEBOOK_SIZE=small``: each notebook reads it in one cell near its
top and does less work (fewer paths, sweep points, shorter spans), every cell and
figure included; ``-m slow`` runs each at ``full`` size too, as stored in its ``.ipynb``.

The paired ``.ipynb`` (what the docs site renders, without executing it) must hold
the same cell sources and be stored executed, with an inline PNG for each figure;
these fast checks are those of the docs build (``docs/hooks.py``).
"""

from __future__ import annotations

import base64
import importlib.util
import json
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
    "finite_temperature.py": {
        "finite_temperature_drift.png",
        "finite_temperature_gibbs.png",
        "finite_temperature_limit.png",
        "finite_temperature_work_precision.png",
    },
}

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIMEOUT_S = {"small": 600, "full": 1800}  # hang bounds on a loaded 2-core machine, not timings


def test_notebooks_found():
    assert NOTEBOOKS, f"no notebooks found in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_reads_its_size(notebook: Path):
    """One place in each notebook reads the size the test runs it at (a notebook without it runs in full)."""
    reads = notebook.read_text(encoding="utf-8").count('os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")')
    assert reads == 1, f"{notebook.name} reads NHSDE_NOTEBOOK_SIZE {reads} times; once, in a cell near its top"


def _run_notebook(notebook: Path, tmp_path: Path, size: str):
    """Run ``notebook`` as a script at ``NHSDE_NOTEBOOK_SIZE=size``; check its exit and the figures it writes."""
    out = tmp_path / "figures"  # not created in advance: the notebook must create it
    env = dict(os.environ, NHSDE_NOTEBOOK_OUT=str(out), NHSDE_NOTEBOOK_SIZE=size, MPLBACKEND="Agg")
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    proc = subprocess.run(
        [sys.executable, str(notebook)],
        cwd=tmp_path,  # the notebook must not depend on the working directory
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S[size],
    )
    assert proc.returncode == 0, (
        f"{notebook.name} ({size}) exited with {proc.returncode}\n"
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


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(notebook: Path, tmp_path: Path):
    """Every cell and figure at the small size (the default run; compiling is most of its time)."""
    _run_notebook(notebook, tmp_path, "small")


@pytest.mark.slow
@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_full(notebook: Path, tmp_path: Path):
    """At the full size: the one stored in the ``.ipynb`` and shown by the docs."""
    _run_notebook(notebook, tmp_path, "full")


def _docs_hooks():
    """``docs/hooks.py``, loaded by path: the docs build and these tests share its notebook checks."""
    path = NOTEBOOK_DIR.parent / "docs" / "hooks.py"
    spec = importlib.util.spec_from_file_location("nhsde_docs_hooks", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_notebook_pairs_agree():
    pytest.importorskip("jupytext")  # in the docs and dev extras, not in test
    problems = _docs_hooks().notebook_pair_problems()
    assert not problems, "\n".join(problems)


def test_notebooks_stored_executed():
    problems = _docs_hooks().notebook_output_problems()
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_stored_with_figures(notebook: Path):
    cells = json.loads(notebook.with_suffix(".ipynb").read_text(encoding="utf-8"))["cells"]
    outputs = [o for c in cells if c["cell_type"] == "code" for o in c.get("outputs", [])]
    errors = [f"{o.get('ename')}: {o.get('evalue')}" for o in outputs if o["output_type"] == "error"]
    assert not errors, f"{notebook.stem}.ipynb is stored with errors: {errors}"
    images = [o["data"]["image/png"] for o in outputs if "image/png" in o.get("data", {})]
    expected = len(EXPECTED_PNGS.get(notebook.name, ())) or 1
    assert len(images) >= expected, f"{notebook.stem}.ipynb holds {len(images)} inline PNGs, expected {expected}"
    for image in images:
        data = base64.b64decode("".join(image) if isinstance(image, list) else image)
        assert data.startswith(PNG_SIGNATURE) and len(data) > 1000, f"{notebook.stem}.ipynb: a bad inline PNG"
