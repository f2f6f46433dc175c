"""Right on every path: one generated matrix of entry points × transforms × solvers × precisions × scenes × inputs.

Every cell calls one entry point, under one transform, with one solver, precision, scene and input, and must either

- return finite values equal to the plain call's (within :data:`RTOL` of the precision; derivatives against plain
  ``jax.jacfwd``, an independent route for reverse mode, and ``jacfwd`` itself against a central difference in
  float64), or
- raise the library's error naming the cause (:func:`library_error`): its own exception type raised from nhsde's
  code, or, from inside a compiled program, a runtime error carrying the library's message.

Anything else is a defect: *silent wrong* (a non-finite value without an error, numbers other than the plain call's,
a result where the plain call refuses the input) or *foreign* (any other exception: JAX's, numpy's, diffrax's).

The axes are registries: a new entry point, transform, solver, precision or scene joins by one line.  The default
suite runs a fixed, seeded sample covering every entry point, transform, solver, precision and scene at least once
(:data:`SAMPLE`); ``pytest -m matrix tests/test_matrix.py`` runs every cell; ``python tests/test_matrix.py`` prints
the table of cells by outcome (``benchmarks/RESULTS.md``).
"""

from __future__ import annotations

import collections
import functools
import itertools
import random
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import AbstractParameters, StateLayout, StochasticSystem, parameter, sqrt_intensity
from nhsde.scenes import SCENES

sys.path.insert(0, str(Path(__file__).parent / "data"))
from knife_edge import KnifeEdge  # noqa: E402  the docs' "Your own scene", as a user writes it

KEY = jax.random.key(0)
N_PATHS, DT, T1 = 16, 0.05, 0.25
QMC_PATHS = 64  # the fewest quasi-Monte Carlo takes (a scrambled Sobol' net's power of two)
RTOL = {"float32": 2e-4, "float64": 1e-9}


# --- scenes: each shipped scene, the docs' user spec scene, a hand-written StochasticSystem ---


class OrnsteinUhlenbeckParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="friction rate")
    nu: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="noise intensity")


def _ou_drift(t, y, p):
    return -p.eps * y


def _ou_diffusion(t, y, p):
    return sqrt_intensity(p.nu) * jnp.eye(2, dtype=y.dtype)


def _ou_linear(p):
    return -p.eps * jnp.eye(2, dtype=p.eps.dtype)


def hand_written(eps, nu) -> tuple[StochasticSystem, jax.Array]:
    """The velocity of a particle in a bath, ``du = −ε u dt + √ν dW``, written directly as a system."""
    system = StochasticSystem(
        drift_fn=_ou_drift,
        diffusion_fn=_ou_diffusion,
        params=OrnsteinUhlenbeckParameters(eps=eps, nu=nu),
        layout=StateLayout(("u_x", "u_y"), ("velocity", "velocity")),
        noise_dim=2,
        additive_noise=True,
        linear_drift=_ou_linear,
    )
    return system, jnp.ones(2)


def _scene(cls, eps, nu):
    """A shipped scene at friction ``eps``, its first noise intensity (``Scene.intensities``) at ``nu``."""
    scene = cls(eps=eps, **{cls.intensities[0]: nu})
    return scene.build(), scene.initial_state()


SCENE_MAKERS: dict[str, Callable[[Any, Any], tuple[StochasticSystem, jax.Array]]] = {
    **{name: functools.partial(_scene, cls) for name, cls in SCENES.items()},
    "user-spec-knife-edge": functools.partial(_scene, KnifeEdge),
    "hand-written-system": hand_written,
}

SOLVER_NAMES = tuple(nhsde.SOLVERS)
PRECISIONS = ("float32", "float64")


# --- entry points: a scalar function of the friction eps (a parameter of every scene) ---------------------------------


class Cell(NamedTuple):
    entry: str
    transform: str
    solver: str
    precision: str
    scene: str
    input: str


def _statistic(ens) -> jax.Array:
    """A scalar of every saved moment at t1: the sum of the means and of the covariance's diagonal."""
    return jnp.sum(ens.mean[-1]) + jnp.trace(ens.cov[-1])


def entry_simulate(cell: Cell, eps, nu):
    system, y0 = SCENE_MAKERS[cell.scene](eps, nu)
    y0 = jnp.asarray(y0, cell.precision)
    ens = nhsde.simulate(system, y0, KEY, n_paths=N_PATHS, t1=T1, dt=DT, solver=cell.solver)
    return _statistic(ens)


def entry_sensitivities(cell: Cell, eps, nu):
    system, y0 = SCENE_MAKERS[cell.scene](eps, nu)
    y0 = jnp.asarray(y0, cell.precision)
    sens = nhsde.statistics.moment_sensitivities(
        system, y0, KEY, wrt=("eps",), n_paths=N_PATHS, t1=T1, dt=DT, solver=cell.solver
    )
    return jnp.sum(sens.mean[-1]) + jnp.trace(sens.cov[-1]) + jnp.sum(sens.d_mean[0, -1])


def _estimate_statistic(est) -> jax.Array:
    """The estimate's value of :func:`_statistic`: its means and covariance diagonal at t1."""
    return jnp.sum(est.mean[-1]) + jnp.trace(est.cov[-1])


def entry_quasi_monte_carlo(cell: Cell, eps, nu):
    system, y0 = SCENE_MAKERS[cell.scene](eps, nu)
    y0 = jnp.asarray(y0, cell.precision)
    est = nhsde.statistics.quasi_monte_carlo(
        system, y0, KEY, n_paths=QMC_PATHS, replicates=4, t1=T1, dt=T1 / 4, solver=cell.solver
    )  # (a Brownian bridge over a power of two of steps)
    return _estimate_statistic(est)


def entry_extrapolate(cell: Cell, eps, nu):
    system, y0 = SCENE_MAKERS[cell.scene](eps, nu)
    y0 = jnp.asarray(y0, cell.precision)
    est = nhsde.statistics.extrapolate(system, y0, KEY, n_paths=N_PATHS, t1=T1, dt=DT, solver=cell.solver)
    return _estimate_statistic(est)


def entry_normal_approximation(cell: Cell, eps, nu):
    """The moment equations (no paths, no solver): the same scalar of the Gaussian closure's moments."""
    system, y0 = SCENE_MAKERS[cell.scene](eps, nu)
    y0 = jnp.asarray(y0, cell.precision)
    return _estimate_statistic(nhsde.statistics.normal_approximation(system, y0, t1=T1, dt=DT))


def entry_fit_simulated(cell: Cell, eps, nu):
    """What a fit by simulation differentiates: ``fit.Simulated``'s model moments of every component at ``t1``."""
    system, y0 = SCENE_MAKERS[cell.scene](eps, nu)
    y0 = jnp.asarray(y0, cell.precision)
    model = nhsde.fit.Simulated(y0, KEY, n_paths=N_PATHS, steps=DT, solver=cell.solver)
    mean, cov = model.moments(system, (T1,), system.layout.names)
    return jnp.sum(mean[-1]) + jnp.trace(cov[-1])


def entry_sweep(cell: Cell, eps, nu):
    """A one-point ``sweep`` over the friction (a host-level driver: under a transform it must refuse, naming it)."""
    system, y0 = SCENE_MAKERS[cell.scene](eps, nu)
    y0 = jnp.asarray(y0, cell.precision)
    ds = nhsde.sweep(system, {"eps": [eps]}, key=KEY, n_paths=N_PATHS, t1=T1, dt=DT, y0=y0, solver=cell.solver, wrt=())
    return jnp.asarray(ds["mean"].values[0, -1].sum() + np.trace(ds["cov"].values[0, -1]), cell.precision)


ENTRY_POINTS: dict[str, Callable] = {
    "simulate": entry_simulate,
    "fit_simulated": entry_fit_simulated,
    "sweep": entry_sweep,
    "moment_sensitivities": entry_sensitivities,
    "quasi_monte_carlo": entry_quasi_monte_carlo,
    "extrapolate": entry_extrapolate,
    "normal_approximation": entry_normal_approximation,
}


# --- transforms: each returns the values to compare, and how to get the reference from the plain function ------------


def _scalar(f):
    return lambda eps: f(eps)


TRANSFORMS: dict[str, Callable] = {
    "plain": lambda f: f,
    "jit": jax.jit,
    "grad": jax.grad,
    "jit∘grad": lambda f: jax.jit(jax.grad(f)),
    "jacfwd": jax.jacfwd,
    "jit∘jacfwd": lambda f: jax.jit(jax.jacfwd(f)),
    "value_and_grad": lambda f: lambda x: jnp.stack(jax.value_and_grad(f)(x)),
    "vmap": lambda f: lambda x: jax.vmap(f)(jnp.stack([x, x * 0 + 1.0])),
    "jit∘vmap∘jacfwd": lambda f: lambda x: jax.jit(jax.vmap(jax.jacfwd(f)))(jnp.stack([x, x * 0 + 1.0])),
}
DERIVATIVE = {"grad", "jit∘grad", "jacfwd", "jit∘jacfwd", "value_and_grad", "jit∘vmap∘jacfwd"}

# inputs: (eps, nu) as a user might pass them; "stability" is at εh = 1.5 (beyond every explicit solver's limit on the
# declared friction), "overflow" a friction of 1e30
INPUTS: dict[str, tuple[float, float]] = {
    "good": (1.0, 0.5),
    "stability": (1.5 / DT, 0.5),
    "nan": (float("nan"), 0.5),
    "negative": (-1.0, 0.5),
    "overflow": (1e30, 0.5),
    "noise-overflow": (1.0, 1e30),
}


def _reference(cell: Cell, f, x):
    """What the cell must equal: the plain call's value, its plain ``jacfwd`` for derivatives; lanes stacked as the
    transform stacks them."""
    one = jnp.asarray(1.0, x.dtype)
    if cell.transform in ("plain", "jit"):
        return f(x)
    if cell.transform == "vmap":
        return jnp.stack([f(x), f(one)])
    if cell.transform == "value_and_grad":
        return jnp.stack([f(x), jax.jacfwd(f)(x)])
    if cell.transform == "jit∘vmap∘jacfwd":
        return jnp.stack([jax.jacfwd(f)(x), jax.jacfwd(f)(one)])
    return jax.jacfwd(f)(x)


# --- outcomes --------------------------------------------------------------------------------------------------------

OUTCOMES = ("finite and equal", "library error", "silent wrong", "foreign exception")
RUNTIME_ERRORS = (jax.errors.JaxRuntimeError, eqx.EquinoxRuntimeError)
LIBRARY_TYPES = (ValueError, TypeError, nhsde.SimulationError, NotImplementedError)
JAX_TRACER_ERRORS = (
    jax.errors.TracerArrayConversionError,
    jax.errors.ConcretizationTypeError,
    jax.errors.TracerBoolConversionError,
    jax.errors.TracerIntegerConversionError,
)


def library_error(error: BaseException) -> bool:
    """The library's own error: one of its types raised from nhsde's code, or a runtime error from inside a compiled
    program carrying an ``eqx.error_if`` message of the library (``EquinoxRuntimeError: …`` in its text: JAX raises
    it as a ``JaxRuntimeError`` from a program's first run, as a ``ValueError`` from a compiled program run again)."""
    if isinstance(error, RUNTIME_ERRORS) or "EquinoxRuntimeError: " in str(error):
        return isinstance(error, eqx.EquinoxRuntimeError) or "EquinoxRuntimeError: " in str(error)
    if isinstance(error, JAX_TRACER_ERRORS):  # JAX's words, raised where our code met a tracer: not a clear error
        return False
    if isinstance(error, LIBRARY_TYPES):
        frames = traceback.extract_tb(error.__traceback__)
        return bool(frames) and "nhsde" in Path(frames[-1].filename).parts
    return False


def _call(fn, *args):
    try:
        return jax.block_until_ready(fn(*args)), None
    except Exception as e:  # noqa: BLE001  classified below
        return None, e


@functools.lru_cache(maxsize=4)
def _functions(cell: Cell, nu: float):
    """The cell's scalar function of ``eps`` and its transform, shared by the cells of its group (entry point ×
    transform × solver × precision × scene) with this ``nu``: under ``jit`` they share one compiled program, as a
    user's calls at several values do."""
    f = functools.partial(ENTRY_POINTS[cell.entry], cell._replace(input=""), nu=jnp.asarray(nu, cell.precision))
    return f, TRANSFORMS[cell.transform](f)


def run_cell(cell: Cell) -> tuple[str, str]:
    """``(outcome, detail)`` of one cell."""
    eps, nu = INPUTS[cell.input]
    f, transformed = _functions(cell._replace(input=""), nu)
    x = jnp.asarray(eps, cell.precision)
    with jax.numpy_dtype_promotion("standard"), nhsde_warnings_off():
        got, error = _call(transformed, x)
        want, plain_error = _call(functools.partial(_reference, cell, f), x)
    if error is not None:
        if library_error(error):  # its message; from a compiled program, the one inside JAX's text
            lines = str(error).splitlines()
            message = next((line for line in lines if "EquinoxRuntimeError: " in line), lines[0])
            return "library error", message.split("EquinoxRuntimeError: ", 1)[-1][:160]
        return "foreign exception", f"{type(error).__name__}: {str(error).splitlines()[0][:200] if str(error) else ''}"
    got = np.asarray(got, np.float64)
    if not np.all(np.isfinite(got)):
        return "silent wrong", f"non-finite {got}"
    if plain_error is not None:
        return "silent wrong", f"{got} where the plain call refuses: {str(plain_error).splitlines()[0][:160]}"
    want = np.asarray(want, np.float64)
    scale = max(1.0, float(np.max(np.abs(want))))
    if not np.allclose(got, want, rtol=RTOL[cell.precision], atol=RTOL[cell.precision] * scale):
        return "silent wrong", f"{got} against the plain call's {want}"
    if cell.transform == "jacfwd" and cell.precision == "float64" and cell.input == "good":
        h = 1e-6
        fd = (float(f(x + h)) - float(f(x - h))) / (2 * h)
        if not np.isclose(float(got), fd, rtol=1e-5, atol=1e-6 * scale):
            return "silent wrong", f"jacfwd {float(got)} against the central difference {fd}"
    return "finite and equal", ""


class nhsde_warnings_off:
    """The stationary-variance warning is advice, not an outcome."""

    def __enter__(self):
        import warnings

        self._catch = warnings.catch_warnings()
        self._catch.__enter__()
        warnings.simplefilter("ignore", nhsde.StationaryVarianceWarning)

    def __exit__(self, *exc):
        self._catch.__exit__(*exc)


# --- the matrix and its sample ---------------------------------------------------------------------------------------

AXES = (tuple(ENTRY_POINTS), tuple(TRANSFORMS), SOLVER_NAMES, PRECISIONS, tuple(SCENE_MAKERS), tuple(INPUTS))
ALL_CELLS = [Cell(*c) for c in itertools.product(*AXES)]


# the dearest scenes (to compile: the spec scenes, the rolling bodies) meet the cheapest transforms in the default
# sample
BY_COST = {
    "scene": (
        "hand-written-system", "ball-on-vibrating-plane", "chaplygin-sleigh-in-bath", "vertical-rolling-disk-in-bath",
        "chaplygin-sleigh", "contact-oscillator", "vertical-rolling-disk", "beghin-plate", "bead-on-rotating-rod",
        "user-spec-knife-edge", "ball-from-lagrangian", "rolling-disk", "chaplygin-sleigh-from-spec",
        "body-on-vibrating-plane", "chaplygin-ball",
    ),
    "transform": (
        "jit∘vmap∘jacfwd", "value_and_grad", "jit∘grad", "grad", "jit∘jacfwd", "jacfwd", "vmap", "jit", "plain",
    ),
    "entry": (
        "extrapolate", "quasi_monte_carlo", "moment_sensitivities", "fit_simulated", "normal_approximation", "sweep",
        "simulate",
    ),
}  # fmt: skip


def _ordered(axis: int) -> tuple[str, ...]:
    """An axis's values, the known ones in :data:`BY_COST`'s order, new ones (a new scene or solver) first."""
    values = AXES[axis]
    known = BY_COST.get(Cell._fields[axis], ())
    return tuple(v for v in values if v not in known) + tuple(v for v in known if v in values)


def covering_sample() -> list[Cell]:
    """The fewest cells in which every value of every axis appears: cell ``i`` takes each axis's ``i``-th value,
    cycling the solvers, precisions and inputs, and padding the transforms and entry points with their cheapest."""
    axes = [_ordered(a) for a in range(len(AXES))]
    cyclic = {"solver", "precision", "input"}
    cells = []
    for i in range(max(len(v) for v in axes)):
        cells.append(
            Cell(
                *(
                    v[i % len(v)] if name in cyclic or name == "scene" else v[min(i, len(v) - 1)]
                    for name, v in zip(Cell._fields, axes)
                )
            )
        )
    return cells


def sample(n: int, seed: int = 0) -> list[Cell]:
    """The covering sample and random cells up to ``n``, fixed by ``seed``."""
    rng = random.Random(seed)
    picked = covering_sample()
    while len(picked) < n:
        picked.append(rng.choice(ALL_CELLS))
    return list(dict.fromkeys(picked))


SAMPLE = covering_sample()


def _id(cell: tuple[str, ...]) -> str:
    return "-".join(cell)


@pytest.mark.parametrize("cell", SAMPLE, ids=_id)
def test_cell(cell):
    outcome, detail = run_cell(cell)
    assert outcome in ("finite and equal", "library error"), f"{outcome}: {detail}"


def whole_matrix(metafunc, test, cells, sample) -> None:
    """Parametrise ``test`` with the ``cells`` beyond the ``sample`` only when ``-m`` selects the matrix: collecting
    about 80k cells costs every other run (each xdist worker collects the suite) most of a minute."""
    if metafunc.function is test:
        selected = "matrix" in metafunc.config.option.markexpr.replace("not matrix", "")
        metafunc.parametrize("cell", [c for c in cells if c not in sample] if selected else [], ids=_id)


def pytest_generate_tests(metafunc):
    whole_matrix(metafunc, test_whole_matrix, ALL_CELLS, SAMPLE)


@pytest.mark.matrix
def test_whole_matrix(cell):
    outcome, detail = run_cell(cell)
    assert outcome in ("finite and equal", "library error"), f"{outcome}: {detail}"


def test_the_sample_covers_every_axis():
    for axis, values in enumerate(AXES):
        assert {c[axis] for c in SAMPLE} == set(values)
    assert len(ALL_CELLS) >= 2000


def test_library_error_tells_ours_from_foreign():
    """The classifier itself: a ValueError raised by nhsde is ours, numpy's is not; an error_if message is ours."""
    _, ours = _call(lambda: nhsde.scenes.BallOnVibratingPlane(eps=-1.0))
    _, foreign = _call(lambda: np.concatenate([]))
    checked = jax.jit(lambda x: eqx.error_if(x, x > 0, "the library's cause"))
    _, runtime = _call(checked, 1.0)
    _, again = _call(checked, 2.0)  # the compiled program run again
    assert ours is not None and library_error(ours)
    assert foreign is not None and not library_error(foreign)
    assert runtime is not None and library_error(runtime)
    assert again is not None and library_error(again)


def groups(n: int, seed: int = 0) -> list[Cell]:
    """About ``n`` cells as whole groups, fixed by ``seed``: every input of a random entry point × transform × solver ×
    precision × scene, adjacent, so that a group's inputs share its compiled programs (one compile serves six cells)."""
    heads = list(dict.fromkeys(c[:-1] for c in ALL_CELLS))
    random.Random(seed).shuffle(heads)
    return [Cell(*head, i) for head in heads[: -(-n // len(INPUTS))] for i in INPUTS]


if __name__ == "__main__":  # the table of cells by outcome: python tests/test_matrix.py [N | all] [--groups]
    import argparse
    import json
    import os
    import subprocess
    import threading
    import time

    parser = argparse.ArgumentParser()
    parser.add_argument("n", nargs="?", default=str(len(SAMPLE)), help="a number of cells, or 'all'")
    parser.add_argument("--groups", action="store_true", help="whole groups of inputs, sharing compiled programs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--jsonl",
        help="append one line per cell (cell, outcome, detail, seconds, commit) to this file; the cells it holds "
        "already are not run again (a long run resumes where it stopped), but are counted in the table",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=300.0,
        help="seconds a cell may run without using the CPU (a slow compilation, at low priority too, is not a hang): "
        "past them the cell is recorded as a hang and the process exits with status 3 (a deadlocked XLA program "
        "cannot be interrupted): run the same command again to go on",
    )
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    if args.n == "all":
        cells = ALL_CELLS
    else:
        cells = (groups if args.groups else sample)(int(args.n), args.seed)
    counts: collections.Counter = collections.Counter()
    done: dict[str, str] = {}
    if args.jsonl and Path(args.jsonl).exists():
        done = {row["cell"]: row["outcome"] for row in map(json.loads, Path(args.jsonl).read_text().splitlines())}
    counts.update(done[c] for c in map(_id, cells) if c in done)
    cells = [c for c in cells if _id(c) not in done]
    here = Path(__file__).parent
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True).stdout
    start = time.monotonic()

    def record(cell: Cell, outcome: str, detail: str, seconds: float) -> None:
        if args.jsonl:
            with open(args.jsonl, "a") as f:
                row = {"cell": _id(cell), "outcome": outcome, "detail": detail, "s": round(seconds, 2)}
                f.write(json.dumps({**row, "commit": commit.strip()}) + "\n")

    def watch(cell: Cell, done: threading.Event) -> None:
        """A deadlock's signature: no answer, and the process's CPU time (all threads) standing still."""
        began, cpu = time.monotonic(), time.process_time()
        while not done.wait(args.timeout):
            if time.process_time() - cpu < 0.01 * args.timeout:
                waited = time.monotonic() - began
                print(f"{_id(cell)}: hang (no CPU used in {args.timeout:.0f} s); run again to go on", flush=True)
                record(cell, "hang", f"no answer in {waited:.0f} s, no CPU used in the last {args.timeout:.0f}", waited)
                os._exit(3)
            cpu = time.process_time()

    for i, cell in enumerate(cells):
        if i % len(INPUTS) == 0 and args.groups:
            jax.clear_caches()  # a group's programs are shared within it; memory stays flat over thousands of cells
            _functions.cache_clear()
        began = time.monotonic()
        answered = threading.Event()
        threading.Thread(target=watch, args=(cell, answered), daemon=True).start()
        try:
            outcome, detail = run_cell(cell)
        except Exception as e:  # noqa: BLE001  outside the entry point's call: still a cell that failed foreignly
            outcome, detail = "foreign exception", f"{type(e).__name__} in the comparison: {e}"[:200]
        finally:
            answered.set()
        seconds = time.monotonic() - began
        print(f"  {_id(cell)}: {outcome} ({seconds:.1f} s)", flush=True)
        counts[outcome] += 1
        if outcome not in ("finite and equal", "library error"):
            print(f"[{i}] {_id(cell)}: {outcome}: {detail}", flush=True)
        record(cell, outcome, detail, seconds)
        if i % 25 == 0:
            print(f"{i}/{len(cells)} cells, {time.monotonic() - start:.0f} s: {dict(counts)}", flush=True)
    print(f"\n{len(cells)} cells in {time.monotonic() - start:.0f} s, {len(done)} recorded before")
    print("| outcome | cells |\n|---|---:|")
    for outcome in (*OUTCOMES, *sorted(set(counts) - set(OUTCOMES))):  # and any recorded by hand (a "hang")
        print(f"| {outcome} | {counts[outcome]} |")
