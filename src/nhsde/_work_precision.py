"""Speed against accuracy: work-precision measurements and the cheapest adequate setting.

For one system, each solver and step size: the strong error at ``t1`` against a
fine reference solve on the same Brownian path (``brownian_dt`` shared), the
weak error of a statistic against a reference value with its Monte-Carlo
standard error ``√(Var/N)``, the wall time of a compiled run and its peak
memory (XLA's buffer assignment).  :func:`cheapest_setting` then names, for a
requested accuracy, the fastest row that meets it — with the row as evidence.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence

import diffrax as dfx
import jax
import numpy as np

from ._ensemble import Ensemble, Save
from ._options import FixedSteps
from ._simulate import simulate
from ._solvers import solver_needs
from ._system import StochasticSystem

__all__ = ["WorkPrecisionRow", "cheapest_setting", "work_precision"]


@dataclasses.dataclass(frozen=True)
class WorkPrecisionRow:
    """One solver × step: errors, their Monte-Carlo error, cost."""

    solver: str
    dt: float
    strong_error: float  # RMS over paths of |Z_dt(t1) − Z_ref(t1)|
    weak_error: float  # |statistic − reference|
    weak_se: float  # Monte-Carlo standard error of the statistic, √(Var/N)
    seconds: float  # wall time of the compiled weak-error run
    peak_bytes: int  # temporary + output buffers of that run
    n_paths: int


def _timed(fn):
    jax.block_until_ready(fn())  # compile
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - start


def work_precision(
    system: StochasticSystem,
    y0,
    key,
    *,
    t1: float,
    solvers: Sequence[str | dfx.AbstractSolver],
    dts: Sequence[float],
    statistic: Callable[[Ensemble], tuple],
    reference: float,
    n_paths: int,
    save: Save,
    strong_paths: int = 256,
    reference_dt: float | None = None,
) -> list[WorkPrecisionRow]:
    """Measure every ``solver × dt``.

    ``statistic(ens) -> (value, standard_error)`` is computed from a run with
    ``n_paths`` paths saved as ``save``; ``reference`` is its exact (analytic or
    moment-method) value.  The strong error uses ``strong_paths`` paths against
    a reference solve at ``reference_dt`` (default ``min(dts)/16``) with SRA1
    for additive noise and Milstein otherwise, on the same Brownian path.

    Arguments:
        system: the SDE (a scene's ``build()``).
        y0: the initial state ``(d,)``.
        key: a JAX random key (the same paths for every setting).
        t1: the end time (from 0).
        solvers: diffrax SDE solvers or aliases of ``nhsde.SOLVERS``.
        dts: the steps to try.
        statistic: ``statistic(ens) -> (value, standard_error)`` of an :class:`~nhsde.Ensemble`.
        reference: the statistic's exact value.
        n_paths: paths of the weak-error run.
        save: what the weak-error run saves (:class:`~nhsde.Save`).
        strong_paths: paths of the strong-error run.
        reference_dt: the step of the reference solve (divides every ``dt``).

    Returns:
        one :class:`WorkPrecisionRow` per ``solver × dt``, for :func:`cheapest_setting`.
    """
    for solver in solvers:
        solver_needs(solver, system)  # names a solver that cannot solve this system
    reference_dt = min(dts) / 16 if reference_dt is None else reference_dt
    ref_solver = "sra1" if system.additive_noise else "milstein"
    final = Save(n=2, paths=True)

    def endpoint(solver, dt):
        ens = simulate(
            system,
            y0,
            key,
            n_paths=strong_paths,
            t1=t1,
            steps=FixedSteps(dt, brownian_dt=reference_dt),
            solver=solver,
            save=final,
        )
        assert ens.paths is not None  # Save(paths=True)
        return np.asarray(ens.paths[:, -1], np.float64)

    ref = endpoint(ref_solver, reference_dt)
    rows = []
    for solver in solvers:
        peak = None
        for dt in dts:
            strong = float(np.sqrt(np.mean(np.sum((endpoint(solver, dt) - ref) ** 2, axis=-1))))

            def run(solver=solver, dt=dt):
                return simulate(system, y0, key, n_paths=n_paths, t1=t1, dt=dt, solver=solver, save=save)

            ens, seconds = _timed(run)  # one program per solver: the step count is data
            value, se = statistic(ens)
            if peak is None:  # the buffers do not depend on the step count: one compilation per solver
                memory = jax.jit(run).lower().compile().memory_analysis()
                peak = int(memory.temp_size_in_bytes + memory.output_size_in_bytes) if memory is not None else -1
            rows.append(
                WorkPrecisionRow(
                    solver_needs(solver, system).name,
                    float(dt),
                    strong,
                    abs(float(value) - reference),
                    float(se),
                    seconds,
                    peak,
                    n_paths,
                )
            )
    return rows


def cheapest_setting(rows: Sequence[WorkPrecisionRow], tolerance: float, *, kind: str = "weak") -> WorkPrecisionRow:
    """The fastest row whose error meets ``tolerance``.

    ``kind='weak'``: the statistic's bias, counted as ``weak_error + 2·weak_se``
    (an error we cannot tell from Monte-Carlo noise is not claimed smaller);
    ``kind='strong'``: the pathwise RMS error.  Raises if no row qualifies.

    Arguments:
        rows: measurements from :func:`work_precision`.
        tolerance: the error to reach, ``> 0``.
        kind: ``'weak'`` or ``'strong'``.

    Returns:
        the qualifying :class:`WorkPrecisionRow` with the least ``seconds``.

    Examples:
        >>> import nhsde
        >>> rows = [
        ...     nhsde.WorkPrecisionRow("euler", 0.1, 0.20, 0.030, 0.002, 0.01, 10**6, 4096),
        ...     nhsde.WorkPrecisionRow("euler", 0.01, 0.06, 0.004, 0.002, 0.08, 10**7, 4096),
        ...     nhsde.WorkPrecisionRow("sra1", 0.1, 0.02, 0.003, 0.002, 0.03, 10**6, 4096),
        ... ]
        >>> best = nhsde.cheapest_setting(rows, tolerance=0.01)
        >>> best.solver, best.dt
        ('sra1', 0.1)
        >>> nhsde.cheapest_setting(rows, tolerance=0.001)
        Traceback (most recent call last):
        ...
        ValueError: no measured setting reaches weak error 0.001; the best is sra1 at dt=0.1 with 0.007 ...
    """
    if kind not in ("weak", "strong"):
        raise ValueError(f"kind={kind!r}; allowed: 'weak', 'strong'.")
    if not tolerance > 0:
        raise ValueError(f"tolerance={tolerance}; must be > 0.")

    def error(r):
        return r.weak_error + 2 * r.weak_se if kind == "weak" else r.strong_error

    ok = [r for r in rows if error(r) <= tolerance]
    if not ok:
        best = min(rows, key=error)
        raise ValueError(
            f"no measured setting reaches {kind} error {tolerance:g}; the best is {best.solver} at dt={best.dt:g} "
            f"with {error(best):.3g}" + (" (more paths shrink the Monte-Carlo part)" if kind == "weak" else "")
        )
    return min(ok, key=lambda r: r.seconds)
