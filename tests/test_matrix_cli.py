"""The command line in the matrix: command × solver × precision × scene × input, generated from the registries.

A command cannot be transformed, so its cells are plain calls of :func:`nhsde.runs.main` in this process.  Each cell
must either

- exit 0 with finite numbers equal to the library's own call in Python: ``simulate`` and a run file give the same
  moments as :func:`nhsde.simulate` (same key, paths and precision), ``sweep`` the same at every grid point; an
  accuracy run (``--relative-rmse``) a value within 6 of its stated RMSE of a finer plain ``simulate``; a fit
  (``fit --data``) finite values and standard errors, and, where it says it converged, the truth within 6 SE; or
- exit 1 or 2 with one line ``nhsde COMMAND: …`` on stderr (the library's error, naming the cause).

Anything else is a defect: a traceback (an exception escaping the command), a non-finite number, numbers other than
the library's, or a result where the library refuses the input.  The axes reuse :mod:`test_matrix`'s registries
(solvers, precisions, inputs, shipped scenes and the docs' user scene as ``MODULE:CLASS``), so a new solver, scene or
input joins here too; a new command joins :data:`COMMANDS` by one line.  The default suite runs :data:`SAMPLE` (every
command, solver and precision at least once); ``pytest -m matrix tests/test_matrix_cli.py`` runs every cell.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import math
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_matrix import DT, INPUTS, N_PATHS, PRECISIONS, RTOL, SOLVER_NAMES, T1, _id, nhsde_warnings_off, whole_matrix

import nhsde
from nhsde.runs import load_run, main
from nhsde.scenes import SCENES, get_scene

DATA = Path(__file__).parent / "data"
USER_SCENE = "knife_edge:KnifeEdge"  # the docs' "Your own scene", named on the command line as a user does
CLI_SCENES = (*SCENES, USER_SCENE)


class CliCell(NamedTuple):
    command: str
    solver: str
    precision: str
    scene: str
    input: str


class Outcome(Exception):
    """A cell's verdict reached before its end."""


def _flags(cell: CliCell, eps=None) -> list[str]:
    """The options every command shares: the scene's friction and first noise intensity, solver, step, span."""
    eps, nu = INPUTS[cell.input] if eps is None else (eps, INPUTS[cell.input][1])
    intensity = get_scene(cell.scene).intensities[0]
    return ["--set", f"eps={eps!r}", "--set", f"{intensity}={nu!r}", "--solver", cell.solver, "--dt", str(DT)]


def _precision(cell: CliCell) -> list[str]:
    return ["--x64"] if cell.precision == "float64" else []


def _python_moments(cell: CliCell, eps: float, n_paths: int = N_PATHS, dt: float = DT) -> np.ndarray:
    """The library's own call: ``simulate`` of the scene from its initial state, key 0, at ``t1``: the means and the
    covariance's diagonal."""
    cls = get_scene(cell.scene)
    scene = cls(eps=eps, **{cls.intensities[0]: INPUTS[cell.input][1]})
    y0 = jnp.asarray(scene.initial_state(), cell.precision)
    ens = nhsde.simulate(scene.build(), y0, jax.random.key(0), n_paths=n_paths, t1=T1, dt=dt, solver=cell.solver)
    return np.concatenate([np.asarray(ens.mean[-1], np.float64), np.diag(np.asarray(ens.cov[-1], np.float64))])


def _moments_of(data, index=()) -> np.ndarray:
    mean, cov = np.asarray(data["mean"], np.float64)[index], np.asarray(data["cov"], np.float64)[index]
    return np.concatenate([mean[-1], np.diag(cov[-1])])


def _equal(cell: CliCell, got: np.ndarray, want: np.ndarray, what: str) -> None:
    scale = max(1.0, float(np.max(np.abs(want))))
    tol = RTOL[cell.precision]
    if got.shape != want.shape or not np.allclose(got, want, rtol=tol, atol=tol * scale):
        raise Outcome("silent wrong", f"{what}: {got} against the library's {want}")


def _finite(values, what: str) -> None:
    if not np.all(np.isfinite(np.asarray(values, np.float64))):
        raise Outcome("silent wrong", f"non-finite {what}: {values}")


def command_simulate(cell: CliCell, folder: Path):
    out = folder / "run.nc"
    argv = ["simulate", cell.scene, "--paths", str(N_PATHS), "--t1", str(T1), "--save-points", "2"]
    argv += [*_flags(cell), *_precision(cell), "--no-progress", "--out", str(out)]
    return argv, lambda stdout: _check_run(cell, out)


def _check_run(cell: CliCell, out: Path):
    got = _moments_of(load_run(out))
    _finite(got, "moments")
    return got, lambda: _python_moments(cell, INPUTS[cell.input][0])


def command_run_file(cell: CliCell, folder: Path):
    eps, nu = INPUTS[cell.input]
    config = folder / "run.toml"
    intensity = get_scene(cell.scene).intensities[0]
    config.write_text(
        f'scene = "{cell.scene}"\nseed = 0\nprecision = "{cell.precision}"\n'
        f"[parameters]\neps = {_toml_float(eps)}\n{intensity} = {_toml_float(nu)}\n"
        f'[solver]\nname = "{cell.solver}"\ndt = {DT}\nt1 = {T1}\n'
        f"[paths]\nn = {N_PATHS}\n[statistics]\nsave_points = 2\n"
    )
    out = folder / "run.nc"
    argv = ["simulate", "--config", str(config), "--trust-scene", "--no-progress", "--out", str(out)]
    return argv, lambda stdout: _check_run(cell, out)


def _toml_float(x: float) -> str:
    return "nan" if math.isnan(x) else ("inf" if x == math.inf else repr(float(x)))


def command_sweep(cell: CliCell, folder: Path):
    eps = INPUTS[cell.input][0]
    out = folder / "sweep.nc"
    argv = ["sweep", cell.scene, "--grid", f"eps={eps!r},1.0", "--paths", str(N_PATHS), "--t1", str(T1)]
    argv += ["--save-points", "2", *_flags(cell)[2:], *_precision(cell), "--no-progress", "--out", str(out)]

    def check(stdout: str):
        data = _open(out)
        got = np.stack([_moments_of(data, i) for i in range(2)])
        _finite(got, "moments")
        return got, lambda: np.stack([_python_moments(cell, e) for e in (eps, 1.0)])

    return argv, check


def _open(path: Path):
    import xarray as xr

    with xr.open_dataset(path) as data:
        return data.load()


def command_accuracy(cell: CliCell, folder: Path):
    out = folder / "estimate.json"
    argv = ["simulate", cell.scene, "--relative-rmse", "0.2", "--t1", str(T1), *_flags(cell), *_precision(cell)]
    argv += ["--no-progress", "--out", str(out)]

    def check(stdout: str):
        result = json.loads(out.read_text())
        value, rmse = float(result["value"]), float(result["rmse_estimated"])
        _finite([value, rmse], "estimate")
        if not rmse > 0:
            raise Outcome("silent wrong", f"estimated RMSE {rmse}")
        return np.array([value]), lambda: _reference_statistic(cell, result, rmse)

    return argv, check


def _reference_statistic(cell: CliCell, result: dict, rmse: float):
    """A finer plain ``simulate`` of the statistic the run estimated, and the band ±6 × (its RMSE and the reference's
    standard error) the estimate must fall in (returned as the reference when it does)."""
    cls = get_scene(cell.scene)
    scene = cls(eps=INPUTS[cell.input][0], **{cls.intensities[0]: INPUTS[cell.input][1]})
    system = scene.build()
    kind, *names = result["statistic"].split()
    ens = nhsde.simulate(
        system,
        jnp.asarray(scene.initial_state(), cell.precision),
        jax.random.key(1),
        n_paths=4096,
        t1=T1,
        dt=DT / 4,
        solver=cell.solver,
        save=nhsde.Save(names=tuple(dict.fromkeys(names)), n=2),
    )
    index = [list(dict.fromkeys(names)).index(n) for n in names]
    if kind == "mean":
        ref, se = float(ens.mean[-1][index[0]]), float(ens.mean_se[-1][index[0]])
    else:
        ref, se = float(ens.cov[-1][index[0], index[1]]), float(ens.cov_se[-1][index[0], index[1]])
    band = 6 * math.hypot(rmse, se)
    value = float(result["value"])
    return np.array([value if abs(value - ref) <= band else ref])


def command_fit(cell: CliCell, folder: Path):
    """``fit --data`` of the friction from a run file the command wrote at the good input, started at the cell's."""
    data = folder / "data.nc"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
        good = cell._replace(input="good")
        argv = ["simulate", cell.scene, "--paths", "256", "--t1", str(2 * DT * 2), "--save-points", "3"]
        if main([*argv, *_flags(good), *_precision(cell), "--no-progress", "--out", str(data)]) != 0:
            raise Outcome("library error", f"the data run: {err.getvalue().strip()[:160]}")
    truth = INPUTS["good"][0]
    argv = ["fit", "--data", str(data), "--scene", cell.scene, "--fit", "eps", *_flags(cell)[:4], "--paths", "64"]
    argv += ["--solver", cell.solver, "--dt", str(DT), "--max-steps", "3", "--json"]

    def check(stdout: str):
        result = json.loads(stdout)
        value, se = float(result["eps"]["value"]), float(result["eps"]["se"])
        _finite([value, se], "fit")
        if not se > 0:
            raise Outcome("silent wrong", f"eps = {value} ± {se}")
        if result["converged"] and abs(value - truth) > 6 * se:
            raise Outcome("silent wrong", f"converged to eps = {value} ± {se}; the data's eps is {truth}")
        return None

    return argv, check


COMMANDS: dict[str, Callable] = {
    "simulate": command_simulate,
    "run-file": command_run_file,
    "sweep": command_sweep,
    "accuracy": command_accuracy,
    "fit": command_fit,
}


def run_cli_cell(cell: CliCell) -> tuple[str, str]:
    """``(outcome, detail)`` of one cell (the outcomes of :data:`test_matrix.OUTCOMES`)."""
    with (
        tempfile.TemporaryDirectory() as tmp,
        contextlib.chdir(DATA),  # the user's scene module is in the folder the command runs in, as a user has it
        jax.numpy_dtype_promotion("standard"),
        nhsde_warnings_off(),
    ):
        stdout, stderr = io.StringIO(), io.StringIO()
        try:
            argv, check = COMMANDS[cell.command](cell, Path(tmp))
            with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
                status = main(argv)
            if status != 0:
                lines = [line for line in stderr.getvalue().splitlines() if line.startswith("nhsde ")]
                if status in (1, 2) and lines:
                    return "library error", lines[-1][:160]
                return "foreign exception", f"status {status}: {stderr.getvalue().strip()[-200:]}"
            got = check(stdout.getvalue())
            if got is None:
                return "finite and equal", ""
            got, reference = got
            try:
                want = reference()
            except (ValueError, nhsde.SimulationError) as e:
                return "silent wrong", f"{got} where the library refuses: {str(e).splitlines()[0][:160]}"
            _equal(cell, np.asarray(got, np.float64), np.asarray(want, np.float64), cell.command)
            return "finite and equal", ""
        except Outcome as o:
            return o.args
        except Exception as e:  # noqa: BLE001  an exception escaping the command is the defect
            return "foreign exception", f"{type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}"


# --- the matrix and its sample ---------------------------------------------------------------------------------------

AXES = (tuple(COMMANDS), SOLVER_NAMES, PRECISIONS, CLI_SCENES, tuple(INPUTS))
ALL_CELLS = [CliCell(*c) for c in itertools.product(*AXES)]
CHEAP_SCENES = ("ball-on-vibrating-plane", "chaplygin-sleigh", "contact-oscillator", USER_SCENE)


def covering_sample() -> list[CliCell]:
    """Every command, solver, precision and input at least once (cell ``i`` takes each axis's ``i``-th value,
    cycling), and every command once more at the good input, on the scenes cheapest to compile, the user's among
    them."""
    length = max(len(AXES[a]) for a in (0, 1, 2, 4))
    cycled = [
        CliCell(
            AXES[0][i % len(AXES[0])],
            AXES[1][i % len(AXES[1])],
            AXES[2][i % len(AXES[2])],
            CHEAP_SCENES[i % len(CHEAP_SCENES)],
            AXES[4][i % len(AXES[4])],
        )
        for i in range(length)
    ]
    good = [
        CliCell(command, "euler", PRECISIONS[i % 2], CHEAP_SCENES[(i + 1) % len(CHEAP_SCENES)], "good")
        for i, command in enumerate(AXES[0])
    ]
    return list(dict.fromkeys(cycled + good))


SAMPLE = covering_sample()


@pytest.mark.parametrize("cell", SAMPLE, ids=_id)
def test_cli_cell(cell):
    outcome, detail = run_cli_cell(cell)
    assert outcome in ("finite and equal", "library error"), f"{outcome}: {detail}"


def pytest_generate_tests(metafunc):
    whole_matrix(metafunc, test_whole_cli_matrix, ALL_CELLS, SAMPLE)


@pytest.mark.matrix
def test_whole_cli_matrix(cell):
    outcome, detail = run_cli_cell(cell)
    assert outcome in ("finite and equal", "library error"), f"{outcome}: {detail}"


def test_the_cli_sample_covers_every_command_solver_precision_and_input():
    for axis in (0, 1, 2, 4):
        assert {c[axis] for c in SAMPLE} == set(AXES[axis])
    assert {c.scene for c in SAMPLE} >= {USER_SCENE}


if __name__ == "__main__":  # the table of cells by outcome: python tests/test_matrix_cli.py [N | all]
    import collections
    import random
    import sys
    import time

    jax.config.update("jax_enable_x64", True)
    rng = random.Random(0)
    n = len(ALL_CELLS) if sys.argv[1:] == ["all"] else int(sys.argv[1]) if sys.argv[1:] else len(SAMPLE)
    cells = list(SAMPLE) if n >= len(SAMPLE) else [c for c in SAMPLE if c.input == "good"][:n]
    while len(cells) < n:
        cells = list(dict.fromkeys([*cells, rng.choice(ALL_CELLS)]))
    counts: collections.Counter = collections.Counter()
    start = time.monotonic()
    for i, cell in enumerate(cells):
        began = time.monotonic()
        outcome, detail = run_cli_cell(cell)
        counts[outcome] += 1
        print(f"  {_id(cell)}: {outcome} ({time.monotonic() - began:.1f} s) {detail}", flush=True)
    print(f"\n{len(cells)} cells in {time.monotonic() - start:.0f} s")
    print("| outcome | cells |\n|---|---:|")
    for outcome, count in sorted(counts.items()):
        print(f"| {outcome} | {count} |")
