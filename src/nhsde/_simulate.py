"""Ensemble integration of a :class:`StochasticSystem` on diffrax: :func:`simulate`.

Fixed steps: one loop over steps of a diffrax solver (``solver.step``),
vmapped over blocks of paths and their lanes, each block's noise drawn once per
step by the system's driver.  The step count, the step and the driver's base step
are data of the compiled program (``_Grid``), so one program serves every step;
where a reverse-mode trace may differentiate the run (inside a user's ``jit`` or
``grad``) they are static and the loops are scans.  (``diffeqsolve``'s own loop on a batched state
took 2.0× the time of a hand-fused scan in the design measurement recorded in
``benchmarks/RESULTS.md``.)  Adaptive steps: ``diffeqsolve`` with a
``PIDController`` and a ``VirtualBrownianTree`` per path.

Paths run in chunks (``lax.scan`` over chunks), so memory is bounded by the
chunk size whatever ``n_paths``; each chunk reduces its observations to moment
sums (:class:`~nhsde.MomentSums`), so only ``n_save × k`` numbers per statistic
survive unless per-path values are asked for.  Reverse mode recomputes each save
interval (``jax.checkpoint``) when storing every step would cost more than
about 1 GiB, so its memory is bounded by the steps per save interval.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import warnings
from collections.abc import Callable
from typing import Any, Literal, NamedTuple, cast

import diffrax as dfx
import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from ._brownian import BLOCK, StepIncrement, block_keys
from ._ensemble import (
    MIN_PATHS,
    Ensemble,
    MomentSums,
    Save,
    SimulationResult,
    StationaryVarianceWarning,
    check_result,
    failure_result,
    scale_cause,
)
from ._interrupt import POLL_ABOVE, POLL_STEPS, poll, watching
from ._misc import cast_floats, check_key, check_number, is_concrete, real_state, under_trace
from ._options import AbstractSteps, AdaptiveSteps, Batching, FixedSteps, RunOptions, run_options
from ._params import (
    check_ranges,
    checked_on_host,
    concrete_primal,
    differentiated_nonzero,
    parameters_checked_on_host,
    validated,
)
from ._solvers import SOLVERS, ExponentialEuler, SolverNeeds, solver_needs
from ._system import StochasticSystem
from ._weak import WeakIncrement

__all__ = ["MAX_PATH_INDEX", "MIN_PATHS", "check_on_host", "simulate", "stable_step"]

MAX_PATH_INDEX = 2**31 - 1
"""Paths ``0 … MAX_PATH_INDEX − 1`` of a key have distinct noise (path indices are 32-bit integers)."""
BLOW_UP = 1e4
"""A path fails where its state's size (largest component) exceeds this times the largest it had, two steps running:
a finite-time blow-up (or a step far too large for the dynamics), whose finite values are rounding, not a solution.
From rest (size 0) a first kick does not count, and a path that came near zero is measured against its largest size;
a false alarm needs two first draws in a row 1e4 times smaller than typical (about 1e-8 of the paths started at 0)."""
ANGLE_RESOLUTION = 1e-3
"""A path fails where an angle of its layout (:class:`~nhsde.StateLayout`'s ``angles``) passes this divided by the
precision's ``eps`` (8.4e3 rad in float32, 4.5e12 in float64): beyond it ``sin``/``cos`` of the angle carry absolute
errors of more than this, and the rotation's gyroscopic terms (products of rates that cancel) relative errors of
``eps·∫|ω| dt``, the same size.  A vertical disk kicked by ν = 1e30 turns 1e14 rad in 0.25 s, where its derivatives
in ε are rounding."""


@dataclasses.dataclass(frozen=True)
class _Plan:
    """The static shape of one run: what the compiled program depends on."""

    n_paths: int
    n_chunks: int
    chunk: int
    n_steps: int  # 0 where the steps are data (``_Grid``): one program then serves every step
    n_save: int
    t0: float
    t1: float
    names: tuple[str, ...]
    adaptive: bool
    rtol: float
    atol: float
    max_steps: int
    keep_paths: bool
    per_path_y0: bool
    devices: tuple
    checkpoint: bool
    raise_on_failure: bool
    traced_stability: bool
    poll: bool  # Ctrl-C polled in the step loop (a host callback: the program cannot enter the persistent cache)
    # steps per block of static trip count inside a loop whose trip count is data; 1: no blocks.  On a GPU a loop
    # of data trip count reads its predicate back to the host at every iteration (65536 paths: 7.6x the fused scan)
    step_block: int
    params_checked: bool  # concrete parameters (or their tangents), their ranges checked before the run
    # no differentiated parameter is 0, checked before the run: traced in `checked_on_host` (part of every cache
    # key), √ν's derivative carries no run-time check (a host callback, which keeps a program out of the cache)
    nonzero_checked: bool

    @property
    def intervals(self) -> int:
        """Save intervals per chunk: the progress meter's ticks per chunk."""
        return self.n_save - 1


class _Grid(NamedTuple):
    """The fixed step as data of the compiled run: ``per_save`` steps (int32) per save interval of ``dt`` (the
    state's dtype), ``work_dt`` the step in the stability check's precision, ``substeps`` base steps of the driver
    per step (int32 data where ``brownian_dt`` is given, so that solves at several steps on one path share a
    program).  Static (Python numbers) where a reverse-mode trace needs static trip counts."""

    per_save: Any
    dt: Any
    work_dt: Any
    substeps: Any


def _resolved_angles(layout, dtype):
    """``y ↦`` whether every angle of ``layout`` is within :data:`ANGLE_RESOLUTION` of the precision (``True``
    where the layout has none: no work).  Static slices, not a gather: they fuse into the step."""
    if not layout.angles:
        return lambda y: True
    index = [layout.index(n) for n in layout.angles]
    bound = ANGLE_RESOLUTION / float(jnp.finfo(dtype).eps)

    def resolved(y):
        turned = functools.reduce(jnp.maximum, [jnp.abs(y[..., i]) for i in index])
        return jax.lax.stop_gradient(turned) <= bound

    return resolved


def _fixed_chunk(
    system, params, needs: SolverNeeds, plan: _Plan, grid: _Grid, y0, key, first_path, chunk_index, meter, meter_state
):
    """Observations ``(chunk, n_save, k)``, failure flags and meter state of one chunk, fixed steps."""
    solver = needs.solver
    nb = plan.chunk // BLOCK
    blocks = (first_path // BLOCK + chunk_index * nb + jnp.arange(nb)).astype(jnp.int32)  # global block indices
    keys = block_keys(key, first_path // BLOCK + chunk_index * nb, nb)
    dtype = y0.dtype
    t0 = jnp.asarray(plan.t0, dtype)
    dt = jnp.asarray(grid.dt, dtype)
    base_dt = dt / jnp.asarray(grid.substeps, dtype)
    per_save = grid.per_save  # a Python int (static trip counts) or int32 data (one program for every step)
    observe = jax.vmap(jax.vmap(system.observe(plan.names), in_axes=(None, 0, None)), in_axes=(None, 0, None))
    total_ticks = plan.n_chunks * plan.intervals
    resolved = _resolved_angles(system.layout, dtype)

    def terms(increment, t_start):
        # the solver steps over (0, dt), so its step is exactly dt whatever the magnitude of the time
        # (float32 at t = 1e5 would round t + dt − t); the vector fields see the absolute time
        path = StepIncrement(increment=increment, levy_area=needs.levy_area)
        drift = dfx.ODETerm(lambda t, y, args: system.drift_fn(t_start + t, y, args))
        return dfx.MultiTerm(drift, dfx.ControlTerm(lambda t, y, args: system.diffusion_fn(t_start + t, y, args), path))

    def lane_step(y, y_start, alive, grew, peak, t, increment):
        # A failed lane keeps its last finite state and is excluded from every statistic.  It is no
        # longer stepped from that state (where the step overflows) but from its constant start, so
        # its zero cotangents meet finite Jacobians: reverse-mode gradients equal forward mode's.
        y_in = jnp.where(alive, y, jax.lax.stop_gradient(y_start))
        y1, _, _, _, result = solver.step(terms(increment, t), 0.0 * dt, dt, y_in, params, solver_state, False)
        # a blow-up: the state's size beyond BLOW_UP times the largest it had, two steps running (a growth rate r
        # with r·dt ≳ 9 sustained); a path near zero is measured against the size it had before
        size = jax.lax.stop_gradient(jnp.max(jnp.abs(y1)))  # nan where y1 has one: one reduction tests both
        grows = (size > BLOW_UP * peak) & (peak > 0)
        good = (result == dfx.RESULTS.successful) & (size < jnp.inf) & ~(grows & grew) & resolved(y1)
        return jnp.where(good & alive, y1, y), good, grows, jnp.maximum(peak, size)

    def block_step(y, y_start, alive, grew, peak, k, block_key, block):
        # one draw per block; each lane gets its row through vmap
        increments = system.noise.block_increment(
            block_key, block, k, base_dt, (system.noise_dim,), grid.substeps, needs.levy_area
        )
        t = t0 + k.astype(dtype) * dt
        return jax.vmap(lane_step, in_axes=(0, 0, 0, 0, 0, None, 0))(y, y_start, alive, grew, peak, t, increments)

    step = jax.vmap(block_step, in_axes=(0, 0, 0, 0, 0, None, 0, 0))

    def interval(carry, j):
        y, ok, grew, peak, meter_state = carry

        def body(_, state):
            y, ok, grew, peak, k = state
            y1, good, grows, peak = step(y, y_start, ok, grew, peak, k, keys, blocks)
            return y1, ok & good, grows, peak, k + 1

        def polled(_, state):  # Ctrl-C: the host is asked once per POLL_STEPS steps, outside the step loop
            jax.debug.callback(poll)
            return jax.lax.fori_loop(0, POLL_STEPS, body, state)

        def steps(n, state):  # n steps: whole blocks of static trip count, then the rest one by one
            if plan.step_block > 1:
                block = functools.partial(jax.lax.fori_loop, 0, plan.step_block, body)
                state = jax.lax.fori_loop(0, n // plan.step_block, lambda _, s: block(s), state)
                n = n % plan.step_block
            return jax.lax.fori_loop(0, n, body, state)

        # the step counter rides in the carry: no per-step arrays, memory independent of steps (with trip counts
        # as data the loops are while loops, with static ones scans)
        state = (y, ok, grew, peak, j.astype(jnp.int32) * per_save)
        if plan.poll:  # both loops always, an empty one included: the program does not depend on the steps
            state = jax.lax.fori_loop(0, per_save // POLL_STEPS, polled, state)
            jax.debug.callback(poll)
            y, ok, grew, peak, _ = steps(per_save % POLL_STEPS, state)
        else:
            y, ok, grew, peak, _ = steps(per_save, state)
        done = chunk_index * plan.intervals + j + 1
        meter_state = meter.step(meter_state, jnp.asarray(done, dtype) / total_ticks)
        t = t0 + ((j + 1).astype(jnp.int32) * per_save).astype(dtype) * dt
        return (y, ok, grew, peak, meter_state), observe(t, y, params)

    y = y_start = y0.reshape(nb, BLOCK, -1)
    # The solvers used here keep no state between steps: init runs diffrax's checks and computes what depends on the
    # parameters and the step only (ExponentialEuler's matrices of the linear flow), once per solve.
    first = system.noise.block_increment(
        keys[0], blocks[0], jnp.int32(0), base_dt, (system.noise_dim,), grid.substeps, needs.levy_area
    )
    state = solver.init(terms(jax.tree_util.tree_map(lambda a: a[0], first), t0), 0.0 * dt, dt, y[0, 0], params)
    solver_state = state if isinstance(solver, ExponentialEuler) else None  # others: per-lane state, or none
    ok = jnp.all(jnp.isfinite(y), axis=-1)
    first_obs = observe(t0, y, params)
    interval = jax.checkpoint(interval) if plan.checkpoint else interval
    grew, peak = jnp.zeros(ok.shape, bool), jax.lax.stop_gradient(jnp.max(jnp.abs(y), axis=-1))
    carry = (y, ok, grew, peak, meter_state)
    (_, ok, _, _, meter_state), rest = jax.lax.scan(interval, carry, jnp.arange(plan.intervals))
    obs = jnp.concatenate([first_obs[None], rest], axis=0)  # (n_save, nb, BLOCK, k)
    obs = jnp.moveaxis(obs, 0, 2).reshape(plan.chunk, plan.n_save, -1)
    return obs, ~ok.reshape(plan.chunk), meter_state


def _adaptive_chunk(
    system, params, needs: SolverNeeds, plan: _Plan, grid: _Grid, y0, key, first_path, chunk_index, meter, meter_state
):
    """As :func:`_fixed_chunk`, with adaptive steps (``diffeqsolve`` + ``VirtualBrownianTree``)."""
    solver = needs.solver if needs.embedded_error else dfx.HalfSolver(needs.solver)
    dtype = y0.dtype
    ts = jnp.linspace(plan.t0, plan.t1, plan.n_save, dtype=dtype)
    dt0 = (plan.t1 - plan.t0) / plan.n_steps
    observe = jax.vmap(system.observe(plan.names), in_axes=(0, 0, None))
    ids = first_path + chunk_index * plan.chunk + jnp.arange(plan.chunk)
    resolved = _resolved_angles(system.layout, dtype)  # at the saved times

    def one(y0_, path_id):
        path = dfx.VirtualBrownianTree(
            plan.t0,
            plan.t1,
            tol=dt0 / 1024,
            shape=(system.noise_dim,),
            key=jr.fold_in(key, path_id),
            levy_area=needs.levy_area,
        )
        terms = dfx.MultiTerm(dfx.ODETerm(system.drift_fn), dfx.ControlTerm(system.diffusion_fn, path))
        sol = dfx.diffeqsolve(
            terms,
            solver,
            plan.t0,
            plan.t1,
            dt0,
            y0_,
            params,
            saveat=dfx.SaveAt(ts=ts),
            stepsize_controller=dfx.PIDController(rtol=plan.rtol, atol=plan.atol),
            max_steps=plan.max_steps,
            throw=False,
        )
        ys = cast(jax.Array, sol.ys)  # saved at ts: an array
        ys = jnp.where(jnp.isfinite(ys), ys, jnp.nan)
        bad = (sol.result != dfx.RESULTS.successful) | ~jnp.all(jnp.isfinite(ys)) | ~jnp.all(resolved(ys))
        return observe(ts, ys, params), bad

    if plan.poll:
        jax.debug.callback(poll)  # Ctrl-C, between chunks
    obs, bad = jax.vmap(one)(y0, ids)
    meter_state = meter.step(meter_state, jnp.asarray(chunk_index + 1, dtype) / plan.n_chunks)
    return obs, bad, meter_state


@eqx.filter_jit
def _run(system: StochasticSystem, needs: SolverNeeds, y0, key, first_path, grid: _Grid, about, plan: _Plan, meter):
    # Compute in the state's precision: float leaves follow y0's dtype.
    # traced parameters get their range checks here; concrete ones were checked before the run (the check is a
    # host callback, which keeps the program out of the persistent cache)
    params = cast_floats(system.params if plan.params_checked else validated(system.params), y0.dtype)
    unstable = jnp.asarray(False)
    if plan.traced_stability:  # traced parameters: the stability limit is checked here, with the eager check's cause
        step = jnp.asarray(grid.work_dt, _work_dtype(y0.dtype))
        unstable, off, _ = _linear_modes(system.linear_drift, needs, jax.lax.stop_gradient(params), step)
        if not plan.params_checked:  # (the estimators' forward-mode tangents: their own steps, their bias measured)
            jax.debug.callback(functools.partial(_warn_variance, solver=needs.name), off, step)
        # on the parameters the run reads, not only on its outputs: `jit(grad(f))` returns derivatives alone, and
        # XLA removes a check that rides on the primal outputs only
        params = eqx.error_if(params, unstable, f"simulate: {SimulationResult[SimulationResult.unstable_step]}")
    chunk_fn = _adaptive_chunk if plan.adaptive else _fixed_chunk
    total = plan.n_chunks * plan.chunk
    # every path's initial state, the chunks' surplus paths starting from the first's (a common state: y0 itself)
    y0_all = (
        jnp.concatenate([y0, jnp.broadcast_to(y0[:1], (total - plan.n_paths, y0.shape[1]))]) if plan.per_path_y0 else y0
    )

    def run(c, size, meter, meter_state):
        """Observations, failure flags, validity and meter state of the ``size`` paths of chunk ``c``."""
        if plan.per_path_y0:
            y0c = jax.lax.dynamic_slice_in_dim(y0_all, c * plan.chunk, size)
        else:  # a common initial state is broadcast per chunk: no buffer that grows with the paths
            y0c = jnp.broadcast_to(y0, (size, y0.shape[0]))
        sized = dataclasses.replace(plan, chunk=size)
        obs, bad, meter_state = chunk_fn(
            system, params, needs, sized, grid, y0c, key, first_path, c, meter, meter_state
        )
        # A path whose saved values are too large for fourth moments in this precision
        # (e.g. escaping to infinity) counts as failed rather than overflowing the sums.
        bad = bad | ~jnp.all(jnp.isfinite(obs.reshape(size, -1) ** 4), axis=1)
        index = c * plan.chunk + jnp.arange(size)
        bad = bad & (index < plan.n_paths)  # padding is neither valid nor failed
        valid = (index < plan.n_paths) & ~bad
        return obs, bad, valid, meter_state

    def tally(failures, bad, first_index):
        """Failure count and first failed path, carried through the loop: memory independent of the paths."""
        count, first = failures
        index = first_index + jnp.arange(bad.size)
        first = jnp.minimum(first, jnp.min(jnp.where(bad.reshape(-1), index, MAX_PATH_INDEX)))
        return count + jnp.sum(bad, dtype=jnp.int32), first

    meter_state = meter.init()
    n_dev = len(plan.devices)
    none_failed = (jnp.zeros((), jnp.int32), jnp.asarray(MAX_PATH_INDEX, jnp.asarray(first_path).dtype))
    keep = plan.keep_paths  # per-path values and flags are kept only when asked for

    def first_shift(obs, valid):
        # Sums are taken about the first path, a point within the spread of the
        # ensemble, so float32 second moments do not cancel.
        return jax.lax.stop_gradient(jnp.where(valid[0], obs[0], 0.0)) if about is None else about.astype(obs.dtype)

    def observed_dtype():
        """The observations' dtype, without tracing a solve."""
        t, y = jnp.asarray(plan.t0, y0.dtype), y0 if y0.ndim == 1 else y0[0]
        return jax.eval_shape(system.observe(plan.names), t, y, params).dtype

    obs_all = bad_all = None  # the per-path values and failure flags, where kept
    if n_dev == 1 and plan.n_chunks == 1:
        obs0, bad0, valid0, meter_state = run(0, plan.chunk, meter, meter_state)
        sums = MomentSums.zeros(first_shift(obs0, valid0)).add_paths(obs0, valid0)
        failures = tally(none_failed, bad0, 0)
        obs_all, bad_all = obs0[None], bad0[None]
    elif n_dev == 1:  # every chunk in one loop, so the solve is traced (and differentiated) once

        def scan_body(carry, c):
            sums, failures, meter_state = carry
            obs, bad, valid, meter_state = run(c, plan.chunk, meter, meter_state)
            # the shift is set by chunk 0, where the sums are still zero
            sums = dataclasses.replace(sums, shift=jnp.where(c == 0, first_shift(obs, valid), sums.shift))
            carry = (sums.add_paths(obs, valid), tally(failures, bad, c * plan.chunk), meter_state)
            return carry, (obs, bad) if keep else None

        zeros = MomentSums.zeros(jnp.zeros((plan.n_save, len(plan.names)), observed_dtype()))
        (sums, failures, meter_state), rest = jax.lax.scan(
            scan_body, (zeros, none_failed, meter_state), jnp.arange(plan.n_chunks)
        )
        if rest is not None:
            obs_all, bad_all = rest
    else:
        if about is None:  # the first block alone gives the shift before the devices start
            obs0, _, valid0, _ = run(0, BLOCK, dfx.NoProgressMeter(), None)
            zeros = MomentSums.zeros(first_shift(obs0, valid0))
        else:
            zeros = MomentSums.zeros(about.astype(observed_dtype()))
        mesh = jax.sharding.Mesh(np.asarray(plan.devices), ("paths",))
        spec = jax.sharding.PartitionSpec("paths")

        def device_sums(c):
            obs, bad, valid, _ = run(c[0], plan.chunk, dfx.NoProgressMeter(), None)
            out = (zeros.block_sums(obs, valid), obs if keep else None, bad)
            return jax.tree_util.tree_map(lambda a: a[None], out)

        sharded = jax.shard_map(device_sums, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)

        def round_body(carry, r):
            sums, failures, meter_state = carry
            block_sums, obs, bad = sharded(r * n_dev + jnp.arange(n_dev))
            # devices in order, and blocks in order within each: path order
            sums = sums.add_blocks(jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), block_sums))
            failures = tally(failures, bad, r * n_dev * plan.chunk)
            meter_state = meter.step(meter_state, (r + 1).astype(y0.dtype) / (plan.n_chunks // n_dev))
            return (sums, failures, meter_state), (obs, bad) if keep else None

        (sums, failures, meter_state), rest = jax.lax.scan(
            round_body, (zeros, none_failed, meter_state), jnp.arange(plan.n_chunks // n_dev)
        )
        if rest is not None:
            obs_all, bad_all = rest
            obs_all = obs_all.reshape(-1, *obs_all.shape[2:])
    meter.close(meter_state)
    failed = paths = None
    if keep:
        assert obs_all is not None and bad_all is not None
        failed = bad_all.reshape(-1)[: plan.n_paths]
        paths = obs_all.reshape(total, plan.n_save, -1)[: plan.n_paths]
    ts = jnp.linspace(plan.t0, plan.t1, plan.n_save, dtype=y0.dtype)
    return ts, sums, failures, failed, paths, unstable


def _index(i: int):
    """A path index as data: ``device_put``, which compiles nothing (``jnp.asarray`` compiles a program)."""
    return jax.device_put(np.asarray(i, jax.dtypes.canonicalize_dtype(np.int64)))


def _on_one_device(x):
    """``x`` on this process's first device (the replicated value of an array spread over processes)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        x = x.addressable_data(0)
    return jax.device_put(x, jax.local_devices()[0])


@eqx.filter_jit
def _result(moments, n_used, n_failed, unstable, raise_on_failure: bool):
    """The run's :class:`~nhsde.SimulationResult` from its moments and counts (one small program)."""
    return failure_result(
        unstable=unstable,
        n_failed=n_failed,
        n_used=n_used,
        raise_on_failure=raise_on_failure,
        overflow=~jnp.all(jnp.array([jnp.all(jnp.isfinite(m)) for m in moments])),
    )


def _zero_increment(levy_area: type, dt, w, h):
    """A step's increment of the driver's type with Brownian part ``w`` and space-time Lévy area ``h``."""
    if levy_area is dfx.SpaceTimeLevyArea:
        return dfx.SpaceTimeLevyArea(dt=dt, W=w, H=h)
    if issubclass(levy_area, WeakIncrement):
        return levy_area(dt=dt, W=w, V=jnp.zeros((w.shape[0],) * 2, w.dtype))
    return w


def _mode_step(needs: SolverNeeds, lam, dt, z, w, h):
    """One step of the solver on ``dz = λ z dt + dW`` for a complex ``λ``: the real 2 × 2 system of ``(Re z, Im z)``."""
    x, y = jnp.real(lam).astype(dt.dtype), jnp.imag(lam).astype(dt.dtype)
    m = jnp.stack([jnp.stack([x, -y]), jnp.stack([y, x])])
    path = StepIncrement(increment=_zero_increment(needs.levy_area, dt, w, h), levy_area=needs.levy_area)
    terms = dfx.MultiTerm(
        dfx.ODETerm(lambda t, z, args: m @ z),
        dfx.ControlTerm(lambda t, z, args: jnp.eye(2, dtype=z.dtype), path),
    )
    return needs.solver.step(terms, 0.0 * dt, dt, z, None, None, False)[0]


_DAMPED = -1e-3
"""A mode with ``Re(λ)·h`` below this is damped enough that any consistent solver damps it at small steps."""


@eqx.filter_jit
def _linear_modes(linear_drift: Callable | None, needs: SolverNeeds, params, dt):
    """``(unstable, variance factor, largest gain)`` of the solver on the declared linear drift ``A``.

    Per eigenvalue ``λ = x + iy`` of ``A``: ``R(λh)`` is the solver's amplification on
    ``dz = λ z dt + dW`` (one noiseless step).  Unstable: ``|R| ≥ 1`` on a mode the exact flow
    damps (the limit included), or ``|R| > 1`` on any mode while the exact flow decays.  On a
    stably damped mode the scheme's stationary variance is ``q/(1 − |R|²)``, ``q`` the variance
    one step adds, against the exact ``1/(2|x|)``; the factor returned is the ratio furthest
    from 1 (Euler–Maruyama on a real ``λ``: ``1/(1 − |λ|h/2)``, 2× at the ball's ``ε·dt = 1/2``).
    """
    a = cast(Callable, linear_drift)(cast_floats(params, dt.dtype)).astype(dt.dtype)  # the declared linear drift
    lams = jnp.linalg.eigvals(a)

    def one(lam):
        # the step is linear in (state, W, H): the steps from the six unit inputs, one traced step for all three
        units = jnp.eye(6, dtype=dt.dtype)
        steps = jax.vmap(lambda e: _mode_step(needs, lam, dt, e[:2], e[2:4], e[4:]))(units)
        propagator, jw, jh = steps[:2].T, steps[2:4], steps[4:]
        gain = jnp.sqrt(jnp.abs(jnp.linalg.det(propagator)))  # R(λh)·rotation: |det| = |R|²
        added = (dt * jnp.sum(jw**2) + dt / 12 * jnp.sum(jh**2)) / 2  # W ~ N(0, h), H ~ N(0, h/12) per channel
        x = jnp.real(lam).astype(dt.dtype)
        factor = added / jnp.maximum(1 - gain**2, jnp.finfo(dt.dtype).tiny) * 2 * jnp.abs(x)
        return x * dt, gain, factor

    xh, gain, factor = jax.vmap(one)(lams)
    decays = jnp.max(xh) <= 0
    unstable = decays & (jnp.any((xh < _DAMPED) & (gain >= 1 - 1e-7)) | jnp.any(gain > 1 + 1e-6))
    fine = (xh < _DAMPED) & (gain < 1 - 1e-7)
    off = jnp.where(fine, factor, 1.0)[jnp.argmax(jnp.where(fine, jnp.abs(jnp.log(factor)), -1.0))]
    return unstable, off, jnp.max(gain)


def _checks_linear(system: StochasticSystem, needs: SolverNeeds) -> bool:
    return system.linear_drift is not None and not isinstance(needs.solver, ExponentialEuler)


def _work_dtype(dtype):
    return jnp.float64 if jnp.finfo(dtype).bits > 32 else jnp.float32


def _check_linear_stability(
    system: StochasticSystem, needs: SolverNeeds, dt: float, dtype, stacklevel: int = 3, warn: bool = True
) -> None:
    """Refuse a step at which the solver does not damp the declared linear drift (friction) that the exact flow
    damps, and warn where its stationary variance there is off by more than 10 %.

    Euler–Maruyama on ``u̇ = −2εu`` multiplies by ``1 − 2εdt`` per step: from ``ε·dt = 1`` on the paths
    no longer decay although the friction damps them; known before the run from
    ``StochasticSystem.linear_drift``.  Parameters known only in the run (under ``jit``, ``grad``, ``vmap``) are
    checked inside it with the same cause and fix (:class:`~nhsde.SimulationResult`); forward-mode tangents over
    concrete values are checked here, on their primal values.
    """
    primal = concrete_primal(system.params)
    if not _checks_linear(system, needs) or primal is None:
        return
    system = eqx.tree_at(lambda s: s.params, system, primal)
    work = _work_dtype(dtype)
    # concrete parameters: known now, also under an outer jit (where the helper is evaluated op by op)
    with jax.ensure_compile_time_eval() if under_trace() else contextlib.nullcontext():
        unstable, off, gain = _linear_modes(system.linear_drift, needs, system.params, np.asarray(dt, work))
        if bool(unstable):
            fix = SimulationResult[SimulationResult.unstable_step].split("; ", 1)[1]
            raise ValueError(
                f"dt={dt}: solver {needs.name!r} is unstable on this system's linear friction at this step (at or "
                f"beyond its stability limit: one step multiplies a mode by up to {float(gain):.3g} while the exact "
                f"flow damps it); {fix}"
            )
        if warn and abs(float(off) - 1) > 0.1:
            warnings.warn(
                _variance_message(system, needs, dt, float(off), work), StationaryVarianceWarning, stacklevel=stacklevel
            )


def check_on_host(system: StochasticSystem, y0, *, n_paths: int, solver: str | dfx.AbstractSolver, dt: float):
    """The checks a plain :func:`simulate` of ``system`` makes before its run, for a caller that traces ``simulate``
    with concrete parameters made tangents (``moment_sensitivities``, in :func:`~nhsde._params.checked_on_host`):
    ``y0``, the parameters' ranges in the state's precision, the step's stability on the declared linear drift (the
    same messages, and the stationary-variance warning, pointing at the caller's caller).  Returns ``y0`` checked.
    """
    needs = solver_needs(solver, system)
    y0 = _check_y0(system, y0, n_paths)
    check_ranges(cast_floats(system.params, y0.dtype))  # a radius of 1e-50 is 0 in float32
    _check_linear_stability(system, needs, dt, y0.dtype, stacklevel=4)
    return y0


def stable_step(system: StochasticSystem, solver: str | dfx.AbstractSolver, dt: float) -> bool:
    """Whether ``solver`` damps every mode of the declared linear drift that the exact flow damps, at step ``dt``
    (strictly inside its stability limit); ``True`` where no linear drift is declared or the parameters are traced."""
    needs = solver_needs(solver, system)
    primal = concrete_primal(system.params)
    if not _checks_linear(system, needs) or primal is None:
        return True
    work = jnp.result_type(float)  # float64 where enabled
    with jax.ensure_compile_time_eval() if under_trace() else contextlib.nullcontext():
        return not bool(_linear_modes(system.linear_drift, needs, primal, np.asarray(dt, work))[0])


def _variance_message(system: StochasticSystem, needs: SolverNeeds, dt: float, off: float, work) -> str:
    """The warning for a stationary variance off by more than 10 %: the factor, the step and the solvers that
    bring it within 10 %."""

    def within(n: SolverNeeds, step: float) -> bool:
        unstable, off, _ = _linear_modes(system.linear_drift, n, system.params, np.asarray(step, work))
        return not bool(unstable) and abs(float(off) - 1) <= 0.1

    step = next((dt / 2**k for k in range(1, 30) if within(needs, dt / 2**k)), dt / 2**30)
    others = []
    for name in SOLVERS:
        try:
            other = solver_needs(name, system)
        except ValueError:
            continue
        if name != needs.name and _checks_linear(system, other) and within(other, dt):
            others.append(repr(name))
    alternative = f", or solver={' / '.join(others)} at this step" if others else ""
    return (
        f"dt={dt}: solver {needs.name!r} has a stationary variance {off:.3g}× the exact one on this system's "
        f"linear friction (off by more than 10 %); dt ≤ {step:.3g} brings it within 10 %{alternative}."
    )


def _warn_variance(off, dt, solver: str) -> None:
    """Host side of the traced variance check: warn once per place where the factor is off by more than 10 %."""
    worst = np.asarray(off, np.float64).reshape(-1)
    worst = worst[np.argmax(np.abs(np.log(worst)))]
    if abs(worst - 1) > 0.1:
        warnings.warn(
            f"dt={float(np.asarray(dt).reshape(-1)[0]):.6g}: solver {solver!r} has a stationary variance "
            f"{worst:.3g}× the exact one on this system's linear friction (off by more than 10 %); take dt smaller "
            "(the warning called plainly names the step).",
            StationaryVarianceWarning,
            stacklevel=2,
        )


def _residuals_too_large(steps_per_save, chunk, state_dim, dtype) -> bool:
    return 10 * steps_per_save * chunk * state_dim * jnp.dtype(dtype).itemsize > 2**30


def step_block(platform: str) -> int:
    """Steps per block of static trip count in a loop whose trip count is data (``_Plan.step_block``): 1 (no blocks)
    on a CPU, where the loop's predicate is read where it is computed; 32 on an accelerator, where it is read back
    to the host at each iteration.  The rest of a save interval, fewer steps, runs one by one."""
    return 1 if platform == "cpu" else 32


def default_chunk_size(n_paths: int, n_devices: int, platform: str) -> int:
    """Paths per chunk when :class:`Batching` names none: each device's even share of the paths (whole blocks), at
    most 8192 on a CPU (a chunk's state stays in cache) and 2²⁰ on an accelerator, where a step of 8192 paths is
    bound by kernel launches, not by the paths (65536 paths in chunks of 8192 ran 7.6× slower than one fused scan
    on an H200)."""
    share = BLOCK * math.ceil(n_paths / (BLOCK * n_devices))
    return min(share, 8192 if platform == "cpu" else 2**20)


def _check_y0(system, y0, n_paths):
    y0 = real_state("y0", y0)
    if jnp.finfo(y0.dtype).bits < 32:
        raise TypeError(
            f"y0 has dtype {y0.dtype}; simulate computes in the state's precision, and fourth moments overflow "
            "below float32: use float32 or float64."
        )
    d = system.state_dim
    if y0.shape not in ((d,), (n_paths, d)):
        raise ValueError(
            f"y0 has shape {y0.shape}; expected ({d},) or ({n_paths}, {d}) for the state {system.layout.names}."
        )
    if not isinstance(y0, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(y0))):
        raise ValueError("y0 contains non-finite values.")
    return y0


def simulate(
    system: StochasticSystem,
    y0,
    key,
    *,
    n_paths: int,
    t1: float | None = None,
    dt: float | None = None,
    t0: float | None = None,
    solver: str | dfx.AbstractSolver | None = None,
    steps: AbstractSteps | None = None,
    save: Save | None = None,
    batching: Batching | None = None,
    run: RunOptions | None = None,
    on_failure: Literal["raise", "exclude"] = "raise",
    progress_meter: dfx.AbstractProgressMeter | None = None,
    first_path: int = 0,
) -> Ensemble:
    """Integrate ``n_paths`` independent paths of ``system`` from ``y0``: the ensemble of S0 (1.15).

    Arguments:
        system: the SDE (a scene's ``build()``).
        y0: ``(d,)`` for a common initial state or ``(n_paths, d)``.
        key: a JAX random key; the same key gives bitwise the same result, whatever the batching.
        n_paths: the number of paths.
        t0, t1: the time interval (``t0`` default 0).
        dt: fixed step, shorthand for ``steps=FixedSteps(dt)``.
        solver: a diffrax SDE solver object (``diffrax.ShARK()``, …) or an alias of
            ``nhsde.SOLVERS`` (default ``'euler'``); a system written in the other calculus is converted first.
        steps: :class:`~nhsde.FixedSteps` (with ``brownian_dt``, a step budget) or
            :class:`~nhsde.AdaptiveSteps` (tolerances).
        save: what to keep (:class:`~nhsde.Save`); default every state component at ≤ 11 times.
        batching: chunk size, devices, reverse-mode checkpointing (:class:`~nhsde.Batching`).
        run: all of the above at once, :class:`~nhsde.RunOptions` (then none of ``t0`` … ``batching``).
        on_failure: ``'raise'`` raises :class:`~nhsde.SimulationError` (under a JAX
            transformation, a run-time error) if any path fails; ``'exclude'``
            leaves failed paths out of the statistics and marks them in ``Ensemble.failed``.
        progress_meter: a diffrax progress meter (``diffrax.TqdmProgressMeter()``,
            ``diffrax.TextProgressMeter()``); it reports under ``jit``, ``grad`` and ``vmap``.
        first_path: index of the first path (a multiple of 64): paths
            ``first_path … first_path + n_paths − 1`` of the ensemble ``key`` defines,
            so a long run can be computed piecewise and resumed.

    Returns:
        an :class:`~nhsde.Ensemble` of means, covariances, their standard errors and failure flags.

    Examples:
        The ball of S0 (3.1) from rest, 64 paths, velocity variance against its exact value
        ``νδ²(1 − e^{−4εt})/(4ε)`` (:func:`~nhsde.scenes.ball_covariances`):

        >>> import jax
        >>> import nhsde
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=0.5, nu=1.0)
        >>> ens = nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=64, t1=1.0, dt=0.1)
        >>> ens.names, ens.ts.shape, ens.mean.shape, ens.cov.shape
        (('x', 'y', 'u_x', 'u_y'), (11,), (11, 4), (11, 4, 4))
        >>> k_uu = nhsde.scenes.ball_covariances(1.0, 0.5, 1.0, 5 / 7)[2]
        >>> bool(abs(ens.cov[-1, 2, 2] - k_uu) < 3 * ens.cov_se[-1, 2, 2])
        True
    """
    run = run_options(
        "simulate", run, t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, batching=batching, adaptive=True
    )
    return simulate_run(
        system,
        y0,
        key,
        run,
        n_paths=n_paths,
        on_failure=on_failure,
        progress_meter=progress_meter,
        first_path=first_path,
    )


def simulate_run(
    system: StochasticSystem,
    y0,
    key,
    run: RunOptions,
    *,
    n_paths: int,
    on_failure: Literal["raise", "exclude"] = "raise",
    progress_meter: dfx.AbstractProgressMeter | None = None,
    first_path: int = 0,
    forward_only: bool = False,
    priced_steps: bool = False,
) -> Ensemble:
    """:func:`simulate` with its run options checked already (``run``): what the estimators' solves call.

    ``forward_only``: the caller differentiates this run in forward mode only, with concrete primal parameters
    (``jax.jvp``/``jax.jacfwd``), so the step count may be data (a while loop, which has no reverse mode) and the
    parameters count as checked.  ``priced_steps``: the steps are an estimator's own, whose bias it measures and
    prices, so the stationary-variance warning is neither raised nor worked out (its message compiles a check per
    solver)."""
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if on_failure not in ("raise", "exclude"):
        raise ValueError(f"on_failure={on_failure!r}; allowed: 'raise', 'exclude'.")
    needs = solver_needs(run.solver, system)
    steps = run.steps
    adaptive = isinstance(steps, AdaptiveSteps)
    if adaptive and not system.noise.continuous:
        raise ValueError("adaptive steps need a Wiener driver (VirtualBrownianTree); use FixedSteps.")
    n_paths = check_number("n_paths", n_paths, integer=True)
    if n_paths < MIN_PATHS:
        raise ValueError(f"n_paths={n_paths}; must be ≥ {MIN_PATHS} (a covariance and its standard error need 4).")
    first_path = check_number("first_path", first_path, integer=True)
    if first_path < 0 or first_path % BLOCK:
        raise ValueError(f"first_path={first_path}; must be a non-negative multiple of {BLOCK}.")
    if first_path + n_paths > MAX_PATH_INDEX:
        raise ValueError(
            f"first_path + n_paths = {first_path + n_paths} exceeds {MAX_PATH_INDEX}, the paths a key indexes; "
            "use another key for more paths."
        )
    t0, t1, n_steps, substeps, step = run.t0, run.t1, run.n_steps, run.substeps, float(steps.dt)
    y0 = _check_y0(system, y0, n_paths)
    key = check_key(key)
    save = Save() if run.save is None else run.save
    names = system.layout.names if save.names is None else save.names
    system.observe(names)  # checks the names
    n_save = save.n
    if n_save is None:
        n_save = max(k for k in range(2, 12) if n_steps % (k - 1) == 0)
    n_save = check_number("save.n", n_save, integer=True)
    if n_steps % (n_save - 1):
        raise ValueError(f"save.n={n_save}: n − 1 must divide the {n_steps} steps.")
    about = None
    if save.about is not None:
        about = jnp.asarray(save.about, y0.dtype)
        if about.shape != (n_save, len(names)):
            raise ValueError(f"save.about has shape {about.shape}; expected ({n_save}, {len(names)}).")
    batching = run.batching
    devices = tuple(jax.devices()) if batching.devices is None else tuple(batching.devices)
    platform = devices[0].platform if devices else jax.default_backend()
    chunk_size = batching.chunk_size
    if chunk_size is None:
        chunk_size = default_chunk_size(n_paths, len(devices), platform)
    # never more than the paths need: padding is simulated work that no statistic uses
    chunk_size = min(check_number("chunk_size", chunk_size, integer=True), BLOCK * math.ceil(n_paths / BLOCK))
    check_ranges(cast_floats(system.params, y0.dtype))  # a radius of 1e-50 is 0 in float32
    _check_linear_stability(system, needs, step, y0.dtype, warn=not priced_steps)
    # Called in `checked_on_host` (by `moment_sensitivities`, whose parameters are concrete): the caller checked the
    # parameters' ranges and the step's stability on the host, and checks the run's outcome there itself, so a traced
    # run carries neither check (host callbacks, which keep its program out of the persistent compilation cache).
    outcome_by_caller = parameters_checked_on_host()
    if needs.interpretation not in ("any", system.interpretation):
        system = system.converted(needs.interpretation)
    n_chunks = math.ceil(n_paths / chunk_size)
    if len(devices) > 1:
        n_chunks = len(devices) * math.ceil(n_chunks / len(devices))
    # The steps are data, so that one compiled program serves every step, unless a reverse-mode trace may need
    # static trip counts: plain calls, and calls whose callers differentiate in forward mode only.
    steps_as_data = not adaptive and (forward_only or (is_concrete(system, y0) and not under_trace()))
    checkpoint = batching.checkpoint
    if checkpoint is None:  # reverse mode's memory: only where it can run
        checkpoint = not steps_as_data and _residuals_too_large(
            n_steps // (n_save - 1), chunk_size, system.state_dim, y0.dtype
        )
    per_save = n_steps // (n_save - 1)
    dt_used = (t1 - t0) / n_steps
    work = _work_dtype(y0.dtype)
    if steps_as_data:
        shared_path = isinstance(steps, FixedSteps) and steps.brownian_dt is not None
        grid = _Grid(
            np.asarray(per_save, np.int32),
            np.asarray(dt_used, y0.dtype),
            np.asarray(dt_used, work),
            np.asarray(substeps, np.int32) if shared_path else substeps,
        )
    else:
        grid = _Grid(per_save, dt_used, dt_used, substeps)
    plan = _Plan(
        n_paths=n_paths,
        n_chunks=n_chunks,
        chunk=chunk_size,
        n_steps=0 if steps_as_data else n_steps,
        n_save=n_save,
        t0=t0,
        t1=t1,
        names=names,
        adaptive=adaptive,
        rtol=float(getattr(steps, "rtol", 0.0)),
        atol=float(getattr(steps, "atol", 0.0)),
        max_steps=int(steps.max_steps),
        keep_paths=bool(save.paths),
        per_path_y0=y0.ndim == 2,
        devices=devices,
        checkpoint=bool(checkpoint),
        raise_on_failure=on_failure == "raise",
        # checked before the run where the primal values are known (`_check_linear_stability`), and in
        # `checked_on_host` by the caller on the host
        traced_stability=_checks_linear(system, needs)
        and concrete_primal(system.params) is None
        and not outcome_by_caller,
        poll=n_paths * n_steps * system.state_dim > POLL_ABOVE,
        step_block=step_block(platform) if steps_as_data else 1,
        # forward mode of concrete values (the estimators' tangents): the primal values were checked when built
        params_checked=is_concrete(system.params) or forward_only or parameters_checked_on_host(),
        nonzero_checked=parameters_checked_on_host()
        or (forward_only and not is_concrete(system.params) and differentiated_nonzero(system.params)),
    )
    meter = dfx.NoProgressMeter() if progress_meter is None else progress_meter
    if not isinstance(meter, dfx.AbstractProgressMeter):
        raise TypeError(
            f"progress_meter={meter!r}; expected a diffrax progress meter, e.g. diffrax.TqdmProgressMeter()."
        )
    with watching():  # Ctrl-C stops the compiled run within POLL_STEPS steps
        # (only the run in the checked setting: the small programs after it are the same either way)
        with checked_on_host() if plan.nonzero_checked else contextlib.nullcontext():
            ts, sums, (n_failed, first_failed), failed, paths, unstable = _run(
                system, needs, y0, key, _index(first_path), grid, about, plan, meter
            )
        if is_concrete(sums, n_failed, unstable):  # one program for the statistics whatever devices ran the paths
            sums, n_failed, unstable = jax.tree_util.tree_map(_on_one_device, (sums, n_failed, unstable))
        moments = sums.statistics()
        outputs = (*moments, failed, paths)
        if outcome_by_caller and not is_concrete(moments):
            result = None  # unchecked: the caller checks the outcome (too few paths, overflow) on the host
        else:
            result = _result(moments, sums.count, n_failed, unstable, plan.raise_on_failure)
        if not under_trace():
            jax.block_until_ready(moments)
    if result is not None:
        details = ""
        if is_concrete(n_failed) and int(n_failed) > 0:
            details = f"{int(n_failed)} of {n_paths} paths failed, first path {int(first_failed)}: "
        outputs = check_result(outputs, result, "simulate", details, scale_cause(system.params, y0) if details else "")
    mean, cov, mean_se, cov_se, failed, paths = outputs
    roles = tuple(
        system.layout.roles[system.layout.index(n)] if n in system.layout.names else "observable" for n in names
    )
    return Ensemble(
        ts=ts,
        mean=mean,
        cov=cov,
        mean_se=mean_se,
        cov_se=cov_se,
        n_used=sums.count,
        n_failed=n_failed,
        failed=failed,
        paths=paths,
        sums=sums,
        names=names,
        roles=roles,
        solver=needs.name,
        dt=dt_used,
    )
