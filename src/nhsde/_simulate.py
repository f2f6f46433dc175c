"""Ensemble integration of a :class:`StochasticSystem` on diffrax.

Fixed steps: one ``lax.scan`` over steps of a diffrax solver (``solver.step``),
vmapped over blocks of paths and their lanes, each block's noise drawn once per
step by the system's driver (``nhsde.noise``).  (``diffeqsolve``'s own loop on a
batched state took 2.0× the time of a hand-fused scan in the design measurement
recorded in ``benchmarks/RESULTS.md``.)  Adaptive steps: ``diffeqsolve`` with a
``PIDController`` and a ``VirtualBrownianTree`` per path.

Paths run in chunks (``lax.scan`` over chunks), so memory is bounded by the
chunk size whatever ``n_paths``; each chunk reduces its observations to sums
for the first and second moments, so only ``n_save × k`` numbers per statistic
survive unless per-path values are asked for.  Reverse mode recomputes each save
interval (``jax.checkpoint``) when storing every step would cost more than
about 1 GiB, so its memory is bounded by the steps per save interval.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._params import validated
from ._solvers import ExponentialEuler
from ._system import StochasticSystem
from .noise._brownian import BLOCK, StepIncrement, Wiener, block_keys

__all__ = ["SOLVERS", "Ensemble", "Save", "SimulationError", "SolverInfo", "simulate"]


@dataclasses.dataclass(frozen=True)
class SolverInfo:
    """A solver nhsde offers: its diffrax class and what it converges to."""

    make: Callable[[StochasticSystem], dfx.AbstractSolver]
    interpretation: Literal["ito", "stratonovich", "any"]
    additive_only: bool
    levy_area: type
    strong_order: float  # general (commutative) noise
    strong_order_additive: float
    doc: str


def _exponential(system):
    if system.linear_drift is None:
        raise ValueError(
            "solver='exponential' needs the system's linear drift part (StochasticSystem.linear_drift); "
            "this system does not declare one."
        )
    return ExponentialEuler(system.linear_drift)


SOLVERS: dict[str, SolverInfo] = {
    "euler": SolverInfo(lambda s: dfx.Euler(), "ito", False, dfx.BrownianIncrement, 0.5, 1.0, "Euler–Maruyama (Itô)"),
    "milstein": SolverInfo(
        lambda s: dfx.ItoMilstein(), "ito", False, dfx.BrownianIncrement, 1.0, 1.0, "Milstein (Itô)"
    ),
    "heun": SolverInfo(
        lambda s: dfx.EulerHeun(),
        "stratonovich",
        False,
        dfx.BrownianIncrement,
        0.5,
        1.0,
        "Euler–Heun (Stratonovich): Euler in the drift, Heun in the noise",
    ),
    "heun2": SolverInfo(
        lambda s: dfx.Heun(),
        "stratonovich",
        False,
        dfx.BrownianIncrement,
        0.5,
        1.0,
        "Heun's method (Stratonovich): Heun in drift and noise, second order in the drift",
    ),
    "sra1": SolverInfo(
        lambda s: dfx.SRA1(scan_kind="lax"),
        "any",
        True,
        dfx.SpaceTimeLevyArea,
        1.5,
        1.5,
        "SRA1 stochastic Runge–Kutta (additive noise)",
    ),
    "exponential": SolverInfo(
        _exponential,
        "ito",
        False,
        dfx.BrownianIncrement,
        0.5,
        1.0,
        "exponential Euler–Maruyama, exact in the linear friction: stable for any ε·dt",
    ),
}


class SimulationError(RuntimeError):
    """Paths failed (non-finite state or a solver error code) and ``on_failure='raise'``."""


@dataclasses.dataclass(frozen=True)
class Save:
    """What ``simulate`` keeps: which components, at how many times, per path or not.

    - ``names``: state components or system observables; ``None`` = the whole state.
    - ``n``: number of equally spaced save times from ``t0`` to ``t1`` inclusive;
      ``n − 1`` must divide the number of steps (``None``: the largest such ``n ≤ 11``).
    - ``paths``: also keep the per-path values, ``(n_paths, n, k)``.
    """

    names: tuple[str, ...] | None = None
    n: int | None = None
    paths: bool = False


@dataclasses.dataclass(frozen=True)
class _Config:
    n_paths: int
    first_path: int
    n_chunks: int
    chunk: int
    n_steps: int
    n_save: int
    t0: float
    t1: float
    substeps: int
    names: tuple[str, ...]
    solver: str
    adaptive: bool
    rtol: float
    atol: float
    max_steps: int
    keep_paths: bool
    per_path_y0: bool
    progress: bool
    devices: tuple
    checkpoint: bool


class Ensemble(eqx.Module):
    """Result of :func:`simulate`: moments of the saved quantities over the paths.

    ``mean[i]``, ``cov[i]`` are the sample mean and (unbiased) covariance over the
    paths that did not fail, at ``ts[i]``; ``mean_se``, ``cov_se`` their
    Monte-Carlo standard errors.  ``failed[p]`` marks path ``p`` (non-finite state,
    a solver error code, or saved values whose fourth power overflows the
    precision); failed paths never enter a statistic.
    """

    ts: Float[Array, " n"]
    mean: Float[Array, "n k"]
    cov: Float[Array, "n k k"]
    mean_se: Float[Array, "n k"]
    cov_se: Float[Array, "n k k"]
    n_used: Int[Array, ""]
    failed: Bool[Array, " paths"]
    paths: Float[Array, "paths n k"] | None
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    solver: str = eqx.field(static=True)
    dt: float = eqx.field(static=True)

    @property
    def n_failed(self):
        return jnp.sum(self.failed)

    def select(self, names: tuple[str, ...]):
        """``(mean, cov, mean_se, cov_se)`` restricted to ``names``."""
        idx = []
        for n in names:
            if n not in self.names:
                raise ValueError(f"{n!r} was not saved; saved: {self.names}.")
            idx.append(self.names.index(n))
        idx = np.asarray(idx)
        ix = np.ix_(idx, idx)
        return (
            self.mean[:, idx],
            self.cov[:, ix[0], ix[1]],
            self.mean_se[:, idx],
            self.cov_se[:, ix[0], ix[1]],
        )


# ----------------------------------------------------------------------------- checks


def _number(name, value, *, positive=False, integer=False):
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{name} must be a concrete Python number (it fixes array shapes), not a traced value.")
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float, np.integer, np.floating))
        and not (isinstance(value, (np.ndarray, jax.Array)) and np.ndim(value) == 0)
    ):
        raise TypeError(f"{name}={value!r}; expected a number.")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name}={v}; must be finite.")
    if integer and v != int(v):
        raise ValueError(f"{name}={value}; must be a whole number.")
    if positive and v <= 0:
        raise ValueError(f"{name}={value}; must be > 0.")
    return int(v) if integer else v


def _steps(name, span, step):
    n = round(span / step)
    if n < 1 or abs(n * step - span) > 1e-9 * span:
        raise ValueError(f"{name}={step} must divide t1 − t0 = {span} into a whole number of steps.")
    return n


def _key(key):
    if isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if key.shape != ():
            raise ValueError(f"key has shape {key.shape}; pass a single key, e.g. jax.random.key(0).")
        return key
    if isinstance(key, (jax.Array, np.ndarray)) and key.shape == (2,) and key.dtype == jnp.uint32:
        return jr.wrap_key_data(key)
    raise TypeError(f"key={key!r}; expected a JAX random key, e.g. jax.random.key(0).")


# ----------------------------------------------------------------------------- progress

_BAR = None


def _tick(n):
    if _BAR is not None:
        _BAR.update(int(n))


# ----------------------------------------------------------------------------- chunks


def _fixed_chunk(system, params, cfg, y0, key, chunk_index):
    """Observations ``(chunk, n_save, k)`` and failure flags of one chunk, fixed steps."""
    info = SOLVERS[cfg.solver]
    solver = info.make(system)
    nb = cfg.chunk // BLOCK
    keys = block_keys(key, cfg.first_path // BLOCK + chunk_index * nb, nb)
    dtype = y0.dtype
    t0 = jnp.asarray(cfg.t0, dtype)
    dt = jnp.asarray((cfg.t1 - cfg.t0) / cfg.n_steps, dtype)
    base_dt = dt / cfg.substeps
    per_save = cfg.n_steps // (cfg.n_save - 1)
    observe = jax.vmap(jax.vmap(system.observe(cfg.names), in_axes=(None, 0, None)), in_axes=(None, 0, None))

    def terms(increment):
        path = StepIncrement(increment, info.levy_area)
        return dfx.MultiTerm(dfx.ODETerm(system.drift_fn), dfx.ControlTerm(system.diffusion_fn, path))

    def lane_step(y, t, increment):
        y1, _, _, _, result = solver.step(terms(increment), t, t + dt, y, params, None, False)
        return y1, result == dfx.RESULTS.successful

    def block_step(y, k, block_key):
        # one draw per block; each lane gets its row through vmap
        increments = system.noise.block_increment(
            block_key, k, base_dt, (system.noise_dim,), cfg.substeps, info.levy_area
        )
        t = t0 + k.astype(dtype) * dt
        return jax.vmap(lane_step, in_axes=(0, None, 0))(y, t, increments)

    step = jax.vmap(block_step, in_axes=(0, None, 0))

    def interval(carry, j):
        y, ok = carry

        def body(state, _):
            y, ok, k = state
            y1, good = step(y, k, keys)
            return (y1, ok & good, k + 1), None

        # the step counter rides in the carry: no per-step arrays, memory independent of steps
        start = (j * per_save).astype(jnp.int32)
        (y, ok, _), _ = jax.lax.scan(body, (y, ok, start), None, length=per_save)
        ok = ok & jnp.all(jnp.isfinite(y), axis=-1)
        if cfg.progress:
            jax.debug.callback(_tick, per_save)
        return (y, ok), observe(t0 + ((j + 1) * per_save).astype(dtype) * dt, y, params)

    y = y0.reshape(nb, BLOCK, -1)
    # The offered solvers keep no state between steps; init only runs diffrax's checks.
    first = system.noise.block_increment(
        keys[0], jnp.int32(0), base_dt, (system.noise_dim,), cfg.substeps, info.levy_area
    )
    solver.init(terms(jax.tree_util.tree_map(lambda a: a[0], first)), t0, t0 + dt, y[0, 0], params)
    ok = jnp.all(jnp.isfinite(y), axis=-1)
    first_obs = observe(t0, y, params)
    interval = jax.checkpoint(interval) if cfg.checkpoint else interval
    (_, ok), rest = jax.lax.scan(interval, (y, ok), jnp.arange(cfg.n_save - 1))
    obs = jnp.concatenate([first_obs[None], rest], axis=0)  # (n_save, nb, BLOCK, k)
    obs = jnp.moveaxis(obs, 0, 2).reshape(cfg.chunk, cfg.n_save, -1)
    return obs, ~ok.reshape(cfg.chunk)


def _adaptive_chunk(system, params, cfg, y0, key, chunk_index):
    """As :func:`_fixed_chunk`, with adaptive steps (diffeqsolve + VirtualBrownianTree)."""
    info = SOLVERS[cfg.solver]
    solver = info.make(system)
    if not isinstance(solver, dfx.SRA1):
        solver = dfx.HalfSolver(solver)  # step doubling gives the error estimate
    dtype = y0.dtype
    ts = jnp.linspace(cfg.t0, cfg.t1, cfg.n_save, dtype=dtype)
    dt0 = (cfg.t1 - cfg.t0) / cfg.n_steps
    observe = jax.vmap(system.observe(cfg.names), in_axes=(0, 0, None))
    ids = cfg.first_path + chunk_index * cfg.chunk + jnp.arange(cfg.chunk)

    def one(y0_, path_id):
        path = dfx.VirtualBrownianTree(
            cfg.t0,
            cfg.t1,
            tol=dt0 / 1024,
            shape=(system.noise_dim,),
            key=jr.fold_in(key, path_id),
            levy_area=info.levy_area,
        )
        terms = dfx.MultiTerm(dfx.ODETerm(system.drift_fn), dfx.ControlTerm(system.diffusion_fn, path))
        sol = dfx.diffeqsolve(
            terms,
            solver,
            cfg.t0,
            cfg.t1,
            dt0,
            y0_,
            params,
            saveat=dfx.SaveAt(ts=ts),
            stepsize_controller=dfx.PIDController(rtol=cfg.rtol, atol=cfg.atol),
            max_steps=cfg.max_steps,
            throw=False,
        )
        ys = jnp.where(jnp.isfinite(sol.ys), sol.ys, jnp.nan)
        bad = (sol.result != dfx.RESULTS.successful) | ~jnp.all(jnp.isfinite(ys))
        return observe(ts, ys, params), bad

    obs, bad = jax.vmap(one)(y0, ids)
    if cfg.progress:
        jax.debug.callback(_tick, cfg.n_steps)
    return obs, bad


# ----------------------------------------------------------------------------- moments


def _block_sums(obs, valid, shift):
    """Moment sums of each block of ``BLOCK`` paths, about ``shift``.

    Every block is reduced by the same fixed-shape loop body, and the blocks are
    then added one after another in path order (:func:`_accumulate`), so every
    addition happens in the same order for any chunk size or device count: the
    statistics are bitwise independent of both.
    """

    def one(_, block):
        obs_b, valid_b = block
        z = jnp.where(valid_b[:, None, None], obs_b - shift, 0.0)
        zz = jnp.einsum("cni,cnj->cnij", z, z)
        z_zz = jnp.einsum("cni,cnj->cnij", z, z * z)
        return None, (
            jnp.sum(z, 0),
            jnp.sum(zz, 0),
            jnp.sum(z_zz, 0),
            jnp.sum(zz * zz, 0),
            jnp.sum(valid_b, dtype=jnp.int32),
        )

    blocks = (obs.reshape(-1, BLOCK, *obs.shape[1:]), valid.reshape(-1, BLOCK))
    return jax.lax.scan(one, None, blocks)[1]


def _accumulate(carry, block_sums):
    def add(acc, block):
        return jax.tree_util.tree_map(jnp.add, acc, block), None

    return jax.lax.scan(add, carry, block_sums)[0]


def _central_product_moment(a, m2, m3, m4):
    """``E[(z_i − a_i)² (z_j − a_j)²]`` from moments about the shift.

    ``a = E z``, ``m2_ij = E z_i z_j``, ``m3_ij = E z_i z_j²``, ``m4_ij = E z_i² z_j²``;
    the variance of the product of the centred components is this minus ``cov²``.
    """
    ai, aj = a[:, :, None], a[:, None, :]
    d = jnp.diagonal(m2, axis1=1, axis2=2)
    return (
        m4
        - 2 * ai * m3
        - 2 * aj * jnp.swapaxes(m3, 1, 2)
        + aj**2 * d[:, :, None]
        + ai**2 * d[:, None, :]
        + 4 * ai * aj * m2
        - 3 * ai**2 * aj**2
    )


def _safe_sqrt(v):
    pos = v > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, v, 1.0)), 0.0)


@eqx.filter_jit
def _run(system: StochasticSystem, y0, key, cfg: _Config):
    params = validated(system.params)
    # Compute in the state's precision: float leaves follow y0's dtype.
    params = jax.tree_util.tree_map(
        lambda p: p.astype(y0.dtype) if jnp.issubdtype(jnp.result_type(p), jnp.floating) else p, params
    )
    chunk_fn = _adaptive_chunk if cfg.adaptive else _fixed_chunk
    total = cfg.n_chunks * cfg.chunk
    if cfg.per_path_y0:
        y0_all = jnp.concatenate([y0, jnp.broadcast_to(y0[:1], (total - cfg.n_paths, y0.shape[1]))])
    else:
        y0_all = jnp.broadcast_to(y0, (total, y0.shape[0]))

    def run(c, size):
        """Observations, failure flags and validity of the ``size`` paths of chunk ``c``."""
        y0c = jax.lax.dynamic_slice_in_dim(y0_all, c * cfg.chunk, size)
        obs, bad = chunk_fn(system, params, dataclasses.replace(cfg, chunk=size), y0c, key, c)
        # A path whose saved values are too large for fourth moments in this precision
        # (e.g. escaping to infinity) counts as failed rather than overflowing the sums.
        bad = bad | ~jnp.all(jnp.isfinite(obs.reshape(size, -1) ** 4), axis=1)
        valid = (c * cfg.chunk + jnp.arange(size) < cfg.n_paths) & ~bad
        return obs, bad, valid

    def chunk(c):
        return run(c, cfg.chunk)

    n_dev = len(cfg.devices)
    if n_dev == 1:
        obs0, bad0, valid0 = chunk(0)
    else:  # the first block alone gives the shift before the devices start
        obs0, bad0, valid0 = run(0, BLOCK)
    # Sums are taken about the first path, a point within the spread of the
    # ensemble, so float32 second moments do not cancel.
    shift = jax.lax.stop_gradient(jnp.where(valid0[0], obs0[0], 0.0))
    k = obs0.shape[-1]
    zeros = (
        jnp.zeros((cfg.n_save, k), obs0.dtype),
        jnp.zeros((cfg.n_save, k, k), obs0.dtype),
        jnp.zeros((cfg.n_save, k, k), obs0.dtype),
        jnp.zeros((cfg.n_save, k, k), obs0.dtype),
        jnp.zeros((), jnp.int32),
    )

    def chunk_sums(c):
        obs, bad, valid = chunk(c)
        return _block_sums(obs, valid, shift), (obs if cfg.keep_paths else None, bad)

    if n_dev == 1:
        sums = _accumulate(zeros, _block_sums(obs0, valid0, shift))

        def scan_body(sums, c):
            block_sums, out = chunk_sums(c)
            return _accumulate(sums, block_sums), out

        sums, (obs_rest, bad_rest) = jax.lax.scan(scan_body, sums, jnp.arange(1, cfg.n_chunks))
        obs_all = None if obs_rest is None else jnp.concatenate([obs0[None], obs_rest])
        bad_all = jnp.concatenate([bad0[None], bad_rest])
    else:
        mesh = jax.sharding.Mesh(np.asarray(cfg.devices), ("paths",))
        spec = jax.sharding.PartitionSpec("paths")
        sharded = jax.shard_map(
            lambda c: jax.tree_util.tree_map(lambda a: a[None], chunk_sums(c[0])),
            mesh=mesh,
            in_specs=spec,
            out_specs=spec,
            check_vma=False,
        )

        def round_body(sums, r):
            block_sums, out = sharded(r * n_dev + jnp.arange(n_dev))
            flat = jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), block_sums)
            return _accumulate(sums, flat), out

        sums, (obs_all, bad_all) = jax.lax.scan(round_body, zeros, jnp.arange(cfg.n_chunks // n_dev))
        obs_all = None if obs_all is None else obs_all.reshape(-1, *obs_all.shape[2:])
        bad_all = bad_all.reshape(-1, cfg.chunk)
    s1, s2, s3, s4, n = sums
    nf = n.astype(s1.dtype)
    mean = shift + s1 / nf
    cov = (s2 - jnp.einsum("ni,nj->nij", s1, s1) / nf) / jnp.maximum(nf - 1, 1)
    diag = jnp.diagonal(cov, axis1=1, axis2=2)
    mean_se = _safe_sqrt(diag / nf)
    cov_se = _safe_sqrt((_central_product_moment(s1 / nf, s2 / nf, s3 / nf, s4 / nf) - cov**2) / nf)
    failed = bad_all.reshape(-1)[: cfg.n_paths]
    paths = None
    if cfg.keep_paths:
        paths = obs_all.reshape(total, cfg.n_save, -1)[: cfg.n_paths]
    ts = jnp.linspace(cfg.t0, cfg.t1, cfg.n_save, dtype=y0.dtype)
    return ts, mean, cov, mean_se, cov_se, n, failed, paths


# ----------------------------------------------------------------------------- public


def _residuals_too_large(steps_per_save, chunk, state_dim, dtype) -> bool:
    return 10 * steps_per_save * chunk * state_dim * jnp.dtype(dtype).itemsize > 2**30


def simulate(
    system: StochasticSystem,
    y0,
    key,
    *,
    n_paths: int,
    t1: float,
    dt: float,
    t0: float = 0.0,
    solver: str = "euler",
    save: Save | None = None,
    chunk_size: int | None = None,
    brownian_dt: float | None = None,
    adaptive: bool = False,
    rtol: float = 1e-3,
    atol: float = 1e-3,
    max_steps: int = 100_000,
    on_failure: Literal["raise", "exclude"] = "raise",
    progress: bool = False,
    first_path: int = 0,
    devices=None,
    checkpoint: bool | None = None,
) -> Ensemble:
    """Integrate ``n_paths`` independent paths of ``system`` from ``y0``.

    - ``y0``: ``(d,)`` for a common initial state or ``(n_paths, d)``.
    - ``dt``: the step (fixed steps) or the first step (``adaptive=True``).
    - ``solver``: one of :data:`SOLVERS`; a system written in the other calculus
      is converted first (:meth:`StochasticSystem.converted`).
    - ``brownian_dt``: base step of the Brownian path (divides ``dt``); solves with
      different ``dt`` and the same ``brownian_dt`` and key share one path.
    - ``chunk_size``: paths per chunk (a multiple of 64); memory scales with it.
    - ``first_path``: index of the first path (a multiple of 64): paths
      ``first_path … first_path + n_paths − 1`` of the ensemble that ``key``
      defines, so a long run can be computed piecewise and resumed.
    - ``checkpoint``: in reverse mode, ``True`` recomputes each save interval
      instead of storing every step (memory ∝ steps per save interval, about one
      extra forward pass); ``False`` stores every step (faster, memory ∝ steps ×
      chunk); ``None`` stores while the estimated residuals (≈ 10 × steps per
      interval × chunk × state size × bytes) stay under 1 GiB.
    - ``devices``: the devices to shard chunks over (default: all of
      ``jax.devices()``); one chunk per device at a time, statistics bitwise the
      same as on one device.
    - ``on_failure``: ``'raise'`` raises :class:`SimulationError` (or, under a JAX
      transformation, a run-time error) if any path fails; ``'exclude'`` leaves
      failed paths out of the statistics and marks them in ``Ensemble.failed``.

    Same key ⇒ bitwise-identical results, whatever ``chunk_size``.
    """
    global _BAR
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if solver not in SOLVERS:
        raise ValueError(f"solver={solver!r}; allowed: {', '.join(SOLVERS)}.")
    if on_failure not in ("raise", "exclude"):
        raise ValueError(f"on_failure={on_failure!r}; allowed: 'raise', 'exclude'.")
    info = SOLVERS[solver]
    info.make(system)  # structural checks of the solver against the system
    if info.additive_only and not system.additive_noise:
        raise ValueError(
            f"solver={solver!r} needs additive noise, but this system's diffusion depends on the state; "
            "use 'euler', 'milstein', 'heun' or 'heun2'."
        )
    if not system.noise.continuous and solver != "euler":
        raise ValueError(f"solver={solver!r} does not apply to a system driven by jumps; use 'euler' (S0 §2, Remark).")
    if adaptive and not isinstance(system.noise, Wiener):
        raise ValueError("adaptive steps need a Wiener driver (VirtualBrownianTree); use fixed steps.")
    n_paths = _number("n_paths", n_paths, integer=True)
    if n_paths < 1:
        raise ValueError(f"n_paths={n_paths}; must be ≥ 1.")
    first_path = _number("first_path", first_path, integer=True)
    if first_path < 0 or first_path % BLOCK:
        raise ValueError(f"first_path={first_path}; must be a non-negative multiple of {BLOCK}.")
    t0 = _number("t0", t0)
    t1 = _number("t1", t1)
    if t1 <= t0:
        raise ValueError(f"t1={t1} must be > t0={t0}.")
    dt = _number("dt", dt, positive=True)
    if dt > t1 - t0:
        raise ValueError(f"dt={dt} is larger than t1 − t0 = {t1 - t0}.")
    n_steps = _steps("dt", t1 - t0, dt)
    substeps = 1
    if brownian_dt is not None:
        brownian_dt = _number("brownian_dt", brownian_dt, positive=True)
        substeps = _steps("brownian_dt", (t1 - t0) / n_steps, brownian_dt)
    d = system.state_dim
    y0 = jnp.asarray(y0)
    if not jnp.issubdtype(y0.dtype, jnp.floating):
        y0 = y0.astype(jnp.result_type(float))
    if y0.shape not in ((d,), (n_paths, d)):
        raise ValueError(
            f"y0 has shape {y0.shape}; expected ({d},) or ({n_paths}, {d}) for the state {system.layout.names}."
        )
    if not isinstance(y0, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(y0))):
        raise ValueError("y0 contains non-finite values.")
    key = _key(key)
    save = Save() if save is None else save
    if not isinstance(save, Save):
        raise TypeError(f"save={save!r}; expected nhsde.Save(...).")
    names = system.layout.names if save.names is None else tuple(save.names)
    system.observe(names)  # checks the names
    n_save = save.n
    if n_save is None:
        n_save = max(k for k in range(2, 12) if n_steps % (k - 1) == 0)
    n_save = _number("save.n", n_save, integer=True)
    if n_save < 2 or n_steps % (n_save - 1):
        raise ValueError(f"save.n={n_save}: n − 1 must be ≥ 1 and divide the {n_steps} steps.")
    if chunk_size is None:
        chunk_size = min(BLOCK * math.ceil(n_paths / BLOCK), 8192)
    chunk_size = _number("chunk_size", chunk_size, integer=True)
    if chunk_size < BLOCK or chunk_size % BLOCK:
        raise ValueError(f"chunk_size={chunk_size}; must be a positive multiple of {BLOCK}.")
    rtol = _number("rtol", rtol, positive=True)
    atol = _number("atol", atol, positive=True)
    max_steps = _number("max_steps", max_steps, integer=True, positive=True)
    if info.interpretation not in ("any", system.interpretation):
        system = system.converted(info.interpretation)
    devices = tuple(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices is empty; pass None for all devices or a list of jax devices.")
    n_chunks = math.ceil(n_paths / chunk_size)
    if len(devices) > 1:
        n_chunks = len(devices) * math.ceil(n_chunks / len(devices))
    cfg = _Config(
        n_paths=n_paths,
        first_path=first_path,
        n_chunks=n_chunks,
        chunk=chunk_size,
        n_steps=n_steps,
        n_save=n_save,
        t0=t0,
        t1=t1,
        substeps=substeps,
        names=names,
        solver=solver,
        adaptive=bool(adaptive),
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        keep_paths=bool(save.paths),
        per_path_y0=y0.ndim == 2,
        progress=bool(progress),
        devices=devices,
        checkpoint=_residuals_too_large(n_steps // (n_save - 1), chunk_size, system.state_dim, y0.dtype)
        if checkpoint is None
        else bool(checkpoint),
    )
    if progress:
        from tqdm.auto import tqdm

        _BAR = tqdm(total=cfg.n_chunks * n_steps, unit="step", desc=f"{n_paths} paths")
    try:
        ts, mean, cov, mean_se, cov_se, n_used, failed, paths = _run(system, y0, key, cfg)
    finally:
        if _BAR is not None:
            _BAR.close()
            _BAR = None
    n_failed = jnp.sum(failed)
    if on_failure == "raise":
        concrete = not isinstance(n_failed, jax.core.Tracer)
        if concrete and int(n_failed) > 0:
            first = int(np.argmax(np.asarray(failed)))
            raise SimulationError(
                f"{int(n_failed)} of {n_paths} paths failed (non-finite state or solver error), first path {first}; "
                f"try a smaller dt, a stiffer-stable solver, or on_failure='exclude' to inspect them."
            )
        if not concrete:
            mean = eqx.error_if(mean, n_failed > 0, "simulate: some paths failed (non-finite state or solver error).")
    roles = tuple(
        system.layout.roles[system.layout.index(n)] if n in system.layout.names else "observable" for n in names
    )
    return Ensemble(
        ts=ts,
        mean=mean,
        cov=cov,
        mean_se=mean_se,
        cov_se=cov_se,
        n_used=n_used,
        failed=failed,
        paths=paths,
        names=names,
        roles=roles,
        solver=solver,
        dt=(t1 - t0) / n_steps,
    )
