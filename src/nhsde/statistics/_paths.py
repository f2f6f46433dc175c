"""Per-path values of estimator runs and their statistics: the core every estimator shares.

Statistics of paired paths (:func:`paired_moments`).  Sets ``Z_a`` of per-path
values on the same paths and weights ``w_a`` give ``Σ_a w_a mean(Z_a)`` and
``Σ_a w_a cov(Z_a)``; the standard error of the first is that of the per-path
values ``Σ_a w_a Z_a``, of the second that of the per-path products
``ψ = Σ_a w_a (Z_a − m_a)(Z_a − m_a)ᵀ``, ``Var ψ_ij = E ψ_ij² − (E ψ_ij)²`` with
``E ψ_ij² = Σ_{a,b} w_a w_b E[(F_a,i F_b,i)(F_a,j F_b,j)]``, ``F = Z − m``, plus the
centring term ``Σ_{a,b} w_a w_b (C^{ab}_ii C^{ab}_jj + C^{ab}_ij C^{ab}_ji)/(n(n − 1))``
of the cross-covariances ``C^{ab}`` (exact for unbiased sample covariances; for one
set ``simulate``'s ``covariance_variance``), never zero for a non-degenerate sample.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._ensemble import MIN_PATHS, Save
from .._misc import check_number, fold_key, is_concrete, under_trace
from .._options import FixedSteps, RunOptions
from .._simulate import simulate_run
from .._system import StochasticSystem
from .._weak import PlatenWeak2
from ._estimate import Values
from ._variance_reduction import antithetic as reflected, signed


def array_module(*trees):
    """The array module for statistics of kept per-path values: NumPy (float64, on the host) when every value is
    concrete, so that no XLA program is compiled per path count; ``jax.numpy`` under JAX transformations."""
    return np if is_concrete(*trees) else jnp


def on_device(tree, dtype):
    """``tree`` with its host (NumPy) floating-point leaves as JAX arrays of ``dtype``: a transfer, no program."""

    def move(x):
        host = isinstance(x, (np.ndarray, np.generic)) and np.issubdtype(x.dtype, np.floating)
        return jax.device_put(np.asarray(x, dtype)) if host else x  # (jnp.asarray compiles a program per shape)

    return jax.tree.map(move, tree)


def safe_sqrt(v):
    xp = array_module(v)
    pos = v > 0
    return xp.where(pos, xp.sqrt(xp.where(pos, v, 1.0)), 0.0)


def paired_moments(paths: Sequence[Values], weights: Sequence, cov_weights: Sequence | None = None):
    """``(mean, cov, mean_var, cov_var)`` of ``Σ_a w_a S(Z_a)``, ``Z_a`` ``(N, n, k)`` values of the same paths.

    ``S`` is the sample mean or the unbiased sample covariance; ``*_var`` are the
    squared standard errors (see the module).  Weights are numbers or arrays per entry (``(n, k)`` for the mean,
    ``(n, k, k)`` for the covariance: ``cov_weights``, default ``weights``).  Concrete values are reduced on the
    host in float64 (:func:`array_module`).
    """
    cov_weights = weights if cov_weights is None else cov_weights
    xp = array_module(paths, weights, cov_weights)
    if xp is np:
        paths = [np.asarray(z, np.float64) for z in paths]
    n = paths[0].shape[0]
    combined = sum(w * z for w, z in zip(weights, paths, strict=True))
    mean = xp.mean(combined, axis=0)
    mean_var = xp.var(combined, axis=0, ddof=1) / n
    centred = [z - xp.mean(z, axis=0) for z in paths]
    cov = xp.zeros(mean.shape + mean.shape[-1:], mean.dtype)
    second, pair = xp.zeros_like(cov), xp.zeros_like(cov)
    for w, f in zip(cov_weights, centred, strict=True):
        cov = cov + w * xp.einsum("pni,pnj->nij", f, f) / (n - 1)
    for wa, fa in zip(cov_weights, centred, strict=True):
        for wb, fb in zip(cov_weights, centred, strict=True):
            prod = fa * fb
            second = second + wa * wb * xp.einsum("pni,pnj->nij", prod, prod) / n
            cross = xp.einsum("pni,pnj->nij", fa, fb) / n  # C^{ab}_ij = cov(Z_a,i, Z_b,j), central
            diag = xp.diagonal(cross, axis1=-2, axis2=-1)
            pair = pair + wa * wb * (diag[..., :, None] * diag[..., None, :] + cross * xp.swapaxes(cross, -1, -2))
    # covariance_variance (simulate's) for the combination: (m₂₂ − m²)/n + Σ_ab w_a w_b (C^ab_ii C^ab_jj +
    # C^ab_ij C^ab_ji)/(n(n − 1)), the exact covariance of unbiased sample covariances, with central moments
    m = cov * (n - 1) / n
    cov_var = xp.maximum(second - m**2, 0.0) / n + pair / (n * (n - 1))
    return mean, cov, mean_var, cov_var


def paired_sensitivities(
    paths: Sequence[Values], tangents: Sequence[Values], weights: Sequence, cov_weights: Sequence | None = None
):
    """``(d_mean, d_cov, d_mean_var, d_cov_var)``: derivatives of :func:`paired_moments`' mean and covariance, with
    squared standard errors, from per-path tangents ``T_a (p, N, n, k)`` of the values ``Z_a`` (pathwise, as
    :func:`~nhsde.statistics.moment_sensitivities`): ``∂mean = Σ_a w_a mean(T_a)``, ``∂cov = Σ_a w'_a/(N−1) Σ_i ψ_a,i``
    with ``ψ_a,i = (T_a,i − ∂m_a)F_a,iᵀ + F_a,i(T_a,i − ∂m_a)ᵀ``; the errors are those of the per-path sums over
    ``a`` (the paths are shared).  Weights are numbers or arrays per entry (``(n, k)`` for the mean, ``(n, k, k)``
    for the covariance: ``cov_weights`` ``w'``, default ``weights``)."""
    cov_weights = weights if cov_weights is None else cov_weights
    xp = array_module(paths, tangents, weights, cov_weights)
    if xp is np:
        paths, tangents = ([np.asarray(z, np.float64) for z in zs] for zs in (paths, tangents))
    n = paths[0].shape[0]
    combined = sum(w * t for w, t in zip(weights, tangents, strict=True))
    d_mean = xp.mean(combined, axis=1)
    d_mean_var = xp.var(combined, axis=1, ddof=1) / n
    psi = 0.0
    for w, z, t in zip(cov_weights, paths, tangents, strict=True):
        f = z - xp.mean(z, axis=0)
        tc = t - xp.mean(t, axis=1, keepdims=True)
        tf = xp.einsum("apni,pnj->apnij", tc, f)
        psi = psi + w * (tf + xp.swapaxes(tf, -1, -2))
    d_cov = xp.sum(psi, axis=1) / (n - 1)
    d_cov_var = (n / (n - 1)) ** 2 * xp.var(psi, axis=1, ddof=1) / n
    return d_mean, d_cov, d_mean_var, d_cov_var


def checked_paths(name: str, value, *, per_level: bool = False) -> tuple[int, ...]:
    """The path counts of argument ``name`` as ints: ``value`` one count, or with ``per_level`` a sequence of one
    per level.  The one check every estimator makes of its counts: each at least ``MIN_PATHS`` (4), the fewest
    :func:`~nhsde.simulate` runs, for a covariance and its standard error need 4 (with fewer, the unbiased
    covariance divides by ``n − 1 = 0`` and its standard error reads 0)."""
    if not per_level:
        (n,) = counts = (check_number(name, value, integer=True),)
        if n < MIN_PATHS:
            raise ValueError(f"{name}={value}; must be ≥ {MIN_PATHS} (a covariance and its standard error need 4).")
        return counts
    if not isinstance(value, Sequence) or isinstance(value, str) or not len(value):
        raise TypeError(f"{name}={value!r}; expected one count per level, (N_0, …, N_L).")
    counts = tuple(check_number(name, n, integer=True) for n in value)
    low = [(level, n) for level, n in enumerate(counts) if n < MIN_PATHS]
    if low:
        level, n = low[0]
        raise ValueError(
            f"{name}={tuple(value)!r}: level {level} has {n} path{'s' * (n != 1)}; each level needs ≥ {MIN_PATHS} "
            "(a covariance and its standard error need 4)."
        )
    return counts


def paths_save(save: Save | None, n_steps: int, names: tuple[str, ...]) -> Save:
    """``save`` with per-path values kept, its names ``names`` where it names none, and its number of times fixed on
    a grid of ``n_steps`` (the coarsest)."""
    save = Save(names=names, n=2) if save is None else save
    if not isinstance(save, Save):
        raise TypeError(f"save={save!r}; expected nhsde.Save(...).")
    n = save.n
    if n is None:
        n = max(k for k in range(2, 12) if n_steps % (k - 1) == 0)
    elif n_steps % (n - 1):
        raise ValueError(f"save.n={n}: n − 1 must divide the {n_steps} steps of the coarsest step.")
    return Save(names=names if save.names is None else save.names, n=n, paths=True)


def coupling_solver(solver):
    """``solver`` if solves at different steps on one Brownian path have the law of plain solves; else raises."""
    three_point = isinstance(solver, PlatenWeak2) and solver.increments == "three-point"
    if three_point or (isinstance(solver, str) and solver == "weak2"):
        raise ValueError(
            f"solver={solver!r}: sums of three-point increments are not three-point, so a coarse solve on a shared "
            "path does not have the law of a plain one; use nhsde.PlatenWeak2(increments='gaussian')."
        )
    return solver


def with_tangents(fn: Callable[[StochasticSystem], Any], system: StochasticSystem, wrt: tuple[str, ...]):
    """``(fn(system), tangents)``: with parameter names ``wrt``, ``∂fn/∂θ_a`` by forward mode (``jax.jacfwd``, the
    parameters replaced through ``system.replace_params``) stacked on a leading axis ``a`` of every output leaf;
    ``None`` without ``wrt``."""
    if not wrt:
        return fn(system), None

    def both(*theta):
        value = fn(system.replace_params(**dict(zip(wrt, theta, strict=True))))
        return value, value

    values = tuple(jnp.asarray(getattr(system.params, name)) for name in wrt)
    d, value = jax.jacfwd(both, argnums=tuple(range(len(wrt))), has_aux=True)(*values)
    return value, jax.tree.map(lambda _, per_parameter: array_module(per_parameter).stack(per_parameter), value, d)


KEY_PATHS = 2**30
"""Paths drawn from one key: path ``i`` of a run is path ``i mod 2^30`` of ``key`` for ``i < 2^30``, else of
``fold_in(key, i // 2^30)``, so that runs of any size stay within the paths a key indexes."""


def key_segments(key, first_path: int, n_paths: int):
    """``(key, first, n)`` runs covering paths ``first_path … first_path + n_paths − 1`` (:data:`KEY_PATHS`)."""
    while n_paths > 0:
        segment, first = divmod(first_path, KEY_PATHS)
        size = min(n_paths, KEY_PATHS - first)
        yield (key if segment == 0 else fold_key(key, segment)), first, size
        first_path, n_paths = first_path + size, n_paths - size


RUN_PATHS = 1024
"""Paths per :func:`~nhsde.simulate` call of the estimators' small counts: every count runs as whole runs (the last
run's surplus, the next paths of the same key, is dropped), so one compiled program serves every count."""

LARGE_RUN_PATHS = 8192
"""Paths per call of the estimators' large counts, from :data:`LARGE_RUNS_FROM` paths on: a second program whose
calls carry 8× the paths of a small run, each small call costing its dispatch (about 3 ms) besides its paths."""

LARGE_RUNS_FROM = 2**21
"""Counts from which whole large runs are used (the rest in small runs): below, the large program's compilation
(2–4 s) costs more than it saves.  Measured (``benchmarks/RESULTS.md``): ``to_accuracy``'s multilevel level 0 of
2²⁰ paths × 32 steps on Chaplygin's ball ran 1.3 s faster in large runs (20.4 s against 21.7 s warm) after
compiling for 3.8 s; 229376 paths × 4 steps on the body on the vibrating plane, no faster (2.96 s against
2.87 s) after 2.5 s."""


def runs(n_paths: int) -> list[int]:
    """The sizes of the runs that cover ``n_paths`` paths in order: whole :data:`LARGE_RUN_PATHS` runs from
    :data:`LARGE_RUNS_FROM` paths on, then :data:`RUN_PATHS` runs, the last one's surplus dropped."""
    large = n_paths // LARGE_RUN_PATHS if n_paths >= LARGE_RUNS_FROM else 0
    rest = n_paths - large * LARGE_RUN_PATHS
    return [LARGE_RUN_PATHS] * large + [RUN_PATHS] * -(-rest // RUN_PATHS)


_SOLVED = [0]
_SOLVED_LOCK = threading.Lock()


def solved_path_steps() -> int:
    """The path-steps of every estimator solve started in this process so far (whole runs, surplus paths and failed
    runs included: the work done).  A meter: the work of a span of code is the difference of two readings (solves
    in other threads meanwhile are counted too)."""
    return _SOLVED[0]


def solve_paths(system: StochasticSystem, y0, key, run: RunOptions, *, first_path: int, n_paths: int) -> Values:
    """Per-path saved values of paths ``first_path … first_path + n_paths − 1`` (:data:`KEY_PATHS` per key) by
    :func:`~nhsde.simulate` with the options ``run`` (whose ``save`` keeps the paths), in the runs of :func:`runs`;
    concrete values are gathered on the host (:func:`array_module`)."""
    return _joined(*_solve_runs(system, y0, key, run, first_path=first_path, n_paths=n_paths))


def solve_paths_with_tangents(
    system: StochasticSystem, y0, key, run: RunOptions, wrt: tuple[str, ...], *, first_path: int, n_paths: int
) -> tuple[Values, Values | None]:
    """:func:`solve_paths` and the paths' tangents ``(len(wrt), n_paths, n, k)`` in the parameters ``wrt`` (forward
    mode, :func:`with_tangents`; ``None`` without ``wrt``).  The runs are differentiated whole and joined after, on
    the host where concrete: the forward mode's reshaping then compiles a few programs per run size (two), not per
    path count."""
    keeps: list[int] = []
    # concrete parameters: only this forward-mode pass differentiates the solves, so their steps may be data
    forward_only = bool(wrt) and is_concrete(system) and not under_trace()

    def whole_runs(solved: StochasticSystem):
        parts, kept = _solve_runs(
            solved, y0, key, run, first_path=first_path, n_paths=n_paths, forward_only=forward_only
        )
        keeps[:] = kept
        return parts

    parts, tangents = with_tangents(whole_runs, system, wrt)
    return _joined(parts, keeps), None if tangents is None else _joined(tangents, keeps, axis=1)


def _solve_runs(
    system: StochasticSystem, y0, key, run: RunOptions, *, first_path: int, n_paths: int, forward_only: bool = False
):
    """The saved paths of each whole run of :func:`solve_paths`, and how many of each run's paths it keeps
    (``forward_only``: as :func:`~nhsde._simulate.simulate_run`'s)."""
    parts, keeps = [], []
    system = signed(system)  # one program for the paths and their reflections
    if isinstance(run.steps, FixedSteps) and run.steps.brownian_dt is None:  # the base step as data: one program
        run = run.at(run.steps.dt, brownian_dt=run.steps.dt)
    rows = np.ndim(y0) == 2  # a state per path: each run takes its rows, its surplus paths start from the last
    if rows and np.shape(y0)[0] != n_paths:
        raise ValueError(f"y0 has shape {np.shape(y0)}; expected ({n_paths}, {np.shape(y0)[1]}): one row per path.")
    done = 0
    for k, first, size in key_segments(key, first_path, n_paths):
        start = first
        for size_of_run in runs(size):
            keep = min(size_of_run, first + size - start)
            start_states = y0
            if rows:
                xp = array_module(y0)
                part = y0[done : done + keep]
                start_states = xp.concatenate([part, xp.repeat(part[-1:], size_of_run - keep, axis=0)])
            with _SOLVED_LOCK:  # counted before the solve: a run that fails was done all the same
                _SOLVED[0] += size_of_run * run.n_steps
            ens = simulate_run(
                system,
                start_states,
                k,
                run,
                n_paths=size_of_run,
                first_path=start,
                forward_only=forward_only,
                priced_steps=True,
            )
            assert ens.paths is not None
            parts.append(ens.paths)
            keeps.append(keep)
            done += keep
            start += size_of_run
    return parts, keeps


def _joined(parts, keeps: list[int], axis: int = 0):
    """The kept paths of each run (the first ``keep`` along ``axis``), joined in order; on the host where concrete."""
    xp = array_module(parts)
    cut = (slice(None),) * axis
    kept = [(np.asarray(p) if xp is np else p)[(*cut, slice(0, keep))] for p, keep in zip(parts, keeps, strict=True)]
    return kept[0] if len(kept) == 1 else xp.concatenate(kept, axis=axis)


def coupled_paths(
    system: StochasticSystem,
    y0,
    key,
    run: RunOptions,
    *,
    dts: Sequence[float],
    brownian_dt: float,
    n_paths: int,
    antithetic: bool,
    first_path: int = 0,
    wrt: tuple[str, ...] = (),
) -> tuple[list[Array], list[Array]]:
    """Per-path saved values ``(n_paths, n, k)`` of paths ``first_path …`` (:data:`KEY_PATHS` per key) solved with
    the options ``run`` at each of ``dts`` on one Brownian path of step ``brownian_dt``; with ``antithetic``, then
    the same for the reflected paths.  With parameter names ``wrt``, also their tangents ``(len(wrt), n_paths, n,
    k)`` (forward mode); else an empty list."""
    systems = (system, reflected(system)) if antithetic else (system,)
    out, tangents = [], []
    for s in systems:
        for dt in dts:
            z, t = solve_paths_with_tangents(
                s, y0, key, run.at(dt, brownian_dt=brownian_dt), wrt, first_path=first_path, n_paths=n_paths
            )
            out.append(z)
            if wrt:
                tangents.append(t)
    return out, tangents


def roles_of(system: StochasticSystem, names: tuple[str, ...]) -> tuple[str, ...]:
    """The state role of each name, ``'observable'`` for derived observables."""
    layout = system.layout
    return tuple(layout.roles[layout.index(n)] if n in layout.names else "observable" for n in names)
