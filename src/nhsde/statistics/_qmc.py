"""Randomised quasi-Monte Carlo: scrambled Sobol' points through a Brownian bridge, counter-based on the device.

Path ``i`` of a run of ``n = 2^L`` base steps of length ``δ`` and ``m`` channels takes
point ``i`` of a scrambled Sobol' sequence in ``d = n·m`` dimensions (direct order:
``x_j(i) = ⊕_b i_b V'_{j,b} ⊕ s_j``, ``i_b`` the bits of ``i``), ``u = (x + ½)/2^32``,
``z = Φ⁻¹(u)``, and builds each channel's Wiener path on the grid by a Brownian bridge:
``W(n) = √(nδ) z_0``, then, level by level, ``W(mid) = ½(W(lo) + W(hi)) + √((hi − lo)δ/4) z_q``.
Grid index ``g = odd·2^j`` is node ``q(g) = 2^(L−j−1) + (g >> (j+1))`` of the bridge in
breadth-first order, and node ``q`` of channel ``c`` takes Sobol' dimension ``q·m + c``:
the coarse levels, which carry most of the variance, get the best-distributed
dimensions.  A step of ``s = 2^j`` base steps, ``[k s, (k + 1) s]``, is an interval of
the bridge: one walk from the root down through its ``L − j`` ancestors gives both of
its ends (``L − j + 1`` normals per channel), so the increment over any step is a
function of ``(scrambling, path, step)`` alone, as the counter-based Wiener driver's,
and runs are independent of the chunking.  All ``R`` scramblings run as one solve of
``R·N`` paths, path ``i`` point ``i mod N`` of scrambling ``i // N``.

Scrambling (Owen 1998; Matoušek 1998): a random linear matrix scramble, per dimension a
lower-triangular binary matrix with unit diagonal acting on the bits (most significant
first) of the direction numbers ``V`` (the scramble is linear, so ``V' = M V``), and a
random digital shift ``s``.  Each point is then uniform on the unit cube and the first
``2^k`` points keep the net property of the sequence.  Direction numbers: Joe & Kuo
(2008) as shipped by ``scipy.stats.qmc.Sobol`` (at most 21201 dimensions).
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray, UInt

from .._brownian import BLOCK, AbstractDriver
from .._ensemble import Save
from .._misc import check_key, check_number, fold_key
from .._options import Batching, FixedSteps, run_options
from .._simulate import MAX_PATH_INDEX, simulate_run
from .._solvers import SOLVERS, solver_needs
from .._system import StochasticSystem
from .._weak import GaussianWeakIncrement
from ._estimate import AbstractEstimate, AbstractStatistic, Cost, Derivatives, Stopwatch, Values
from ._paths import array_module, on_device, roles_of, with_tangents
from ._sensitivities import check_wrt
from ._variance_reduction import antithetic as reflected

__all__ = ["QuasiMonteCarloEstimate", "quasi_monte_carlo", "scrambled_sobol", "sobol_points"]

MAX_DIMENSION = 21201
"""Dimensions of the direction numbers (Joe & Kuo's table in SciPy)."""
BITS = 32
LANE_BITS = BLOCK.bit_length() - 1
"""Bits of a path index that number its lane in a block (``BLOCK`` is a power of two)."""


@functools.lru_cache(maxsize=8)
def _direction_numbers(d: int) -> np.ndarray:
    """Unscrambled direction numbers ``(d, 32)`` ``uint32``, column ``b`` for bit ``b`` of the point index."""
    from scipy.stats import qmc

    v = np.array(qmc.Sobol(d, scramble=False, bits=BITS)._sv, dtype=np.uint32)
    v.flags.writeable = False
    return v


def _xor_reduce(x: Array, axis: int) -> Array:
    return jax.lax.reduce(x, np.uint32(0), jax.lax.bitwise_xor, (axis,))


def _xor_at_bits(v: Array, index: Array) -> Array:
    """``⊕_b index_b v[..., b]`` for each of ``index`` ``(N,)``: ``(N, *v.shape[:-1])``."""
    bits = (index[:, None].astype(jnp.uint32) >> jnp.arange(v.shape[-1], dtype=jnp.uint32)) & jnp.uint32(1)
    bits = bits.reshape(bits.shape[:1] + (1,) * (v.ndim - 1) + bits.shape[1:])
    return _xor_reduce(jnp.where(bits == 1, v[None], jnp.uint32(0)), v.ndim)


def sobol_points(v: Array, shift: Array, index: Array, dims: Array) -> Array:
    """Sobol' points ``(len(index), len(dims))`` as ``uint32`` (the binary fraction ``x/2^32``), direct order:
    the XOR of the direction numbers ``v[dims]`` at the set bits of ``index``, and the shift."""
    return _xor_at_bits(v[dims], index) ^ shift[dims]


class SobolDriver(AbstractDriver):
    """A Wiener driver from ``R`` scramblings of Sobol' points through a Brownian bridge (module): the scramblings
    stacked, ``v`` ``(R, d, 32)`` and ``shift`` ``(R, d)``; subclasses place the paths (``_increment``).  Besides
    Brownian increments it gives :class:`~nhsde.PlatenWeak2`'s Gaussian ones: ``ΔW`` from the points, the
    two-point ``V`` pseudo-random from the block key, as the Wiener driver draws it."""

    v: eqx.AbstractVar[UInt[Array, "r d 32"]]
    shift: eqx.AbstractVar[UInt[Array, "r d"]]
    channels: eqx.AbstractVar[int]
    continuous: ClassVar[bool] = True

    def variance_rate(self):
        return jnp.ones(())

    def _normals(self, replicate: Array, block: Array, lanes: Array, q: Array, dtype) -> Array:
        """``Φ⁻¹(u)`` of bridge node ``q`` of every channel for paths ``block·BLOCK + lanes`` of scrambling
        ``replicate``: ``(len(lanes), m)``."""
        # point block·BLOCK + lane: the block's high bits once per block, the lane's low bits per lane
        dims = q * self.channels + jnp.arange(self.channels, dtype=jnp.int32)
        v = self.v[replicate, dims]
        x = _xor_at_bits(v[:, :LANE_BITS], lanes) ^ (
            _xor_at_bits(v[:, LANE_BITS:], block[None]) ^ self.shift[replicate, dims]
        )
        if jnp.finfo(dtype).bits > 32:
            u = (x.astype(dtype) + 0.5) / 2.0**32
        else:  # the top 23 bits: k + 0.5 is exact in float32 for k < 2^23 (for 2^24 − 1 it rounds to 2^24: u = 1)
            u = ((x >> jnp.uint32(9)).astype(dtype) + 0.5) / 2.0**23
        # Φ⁻¹(u) = √2 erf⁻¹(2u − 1) (2u − 1 is exact), as jax.random.normal.  The barriers give the inverse a
        # kernel of its own: fused with its neighbours, its rounding followed the compiler's fusion, which
        # differs between the first chunk and the others, and the results depended on the chunking.
        u = jax.lax.optimization_barrier(2.0 * u - 1.0)
        return jax.lax.optimization_barrier(math.sqrt(2.0) * jax.scipy.special.erfinv(u))

    @abc.abstractmethod
    def _increment(self, block: Array, k0: Array, dt: Array, substeps) -> Array:
        """``W((k0 + 1)·substeps) − W(k0·substeps)`` of the block's lanes: ``(BLOCK, m)``."""

    def block_increment(self, key, block, k0, dt, shape, substeps, levy_area):
        if levy_area not in (dfx.BrownianIncrement, GaussianWeakIncrement):
            raise ValueError(
                f"quasi-Monte Carlo draws Brownian increments and PlatenWeak2's Gaussian ones only; this solver asks "
                f"for {levy_area.__name__}."
            )
        if shape != (self.channels,):
            raise ValueError(f"the driver was built for {self.channels} channels; the system has shape {shape}.")
        w = self._increment(jnp.asarray(block).astype(jnp.int32), jnp.asarray(k0, jnp.int32), dt, substeps)
        if levy_area is dfx.BrownianIncrement:
            return w
        # V from the block key; the pseudo-random ΔW it comes with is unused, and compiled away
        return dataclasses.replace(GaussianWeakIncrement.block_draw(key, k0, dt, (BLOCK,) + shape, substeps), W=w)


class ScrambledSobol(SobolDriver):
    """The driver of quasi-Monte Carlo (module): ``R`` scramblings of ``N = blocks·BLOCK`` points each, path ``i``
    point ``i mod N`` of scrambling ``i // N`` (block ``b`` of scrambling ``b // blocks``); ``n_base`` base steps
    (a power of two) and ``channels`` fix the dimension."""

    v: UInt[Array, "r d 32"]
    shift: UInt[Array, "r d"]
    blocks: Int[Array, ""]
    n_base: int = eqx.field(static=True)
    channels: int = eqx.field(static=True)

    def _interval(self, replicate: Array, block: Array, lanes: Array, g: Array, depth: int, dt: Array):
        """``(lo, W(lo), W(hi))`` of the dyadic interval ``[lo, hi]`` of ``n_base/2^depth`` base steps that holds
        grid index ``g``, for paths ``block·BLOCK + lanes``: the bridge from its root down through ``depth``
        ancestors of ``g``, ``depth + 1`` nodes."""
        levels = self.n_base.bit_length() - 1
        lo = jnp.zeros((), jnp.int32)
        w_lo = jnp.zeros((lanes.shape[0], self.channels), dt.dtype)
        w_hi = math.sqrt(self.n_base) * jnp.sqrt(dt) * self._normals(replicate, block, lanes, lo, dt.dtype)
        for level in range(1, depth + 1):  # the ancestors of g, coarse to fine
            half = self.n_base >> level
            mid = lo + half
            q = (1 << (level - 1)) + (lo >> (levels - level + 1))
            z = self._normals(replicate, block, lanes, q, dt.dtype)
            w_mid = 0.5 * (w_lo + w_hi) + jnp.sqrt(0.5 * half * dt) * z
            left = g < mid
            w_lo, w_hi = jnp.where(left, w_lo, w_mid), jnp.where(left, w_mid, w_hi)
            lo = jnp.where(left, lo, mid)
        return lo, w_lo, w_hi

    def _increment(self, block, k0, dt, substeps):
        if not isinstance(substeps, int) or substeps & (substeps - 1) or substeps > self.n_base:
            raise ValueError(
                f"substeps={substeps!r}; the bridge's steps are its dyadic intervals: a power of two up to "
                f"{self.n_base}, as a number."
            )
        replicate, points = block // self.blocks, (block % self.blocks).astype(jnp.uint32)
        depth = (self.n_base // substeps).bit_length() - 1
        # step k0 is the dyadic interval [k0·s, (k0 + 1)·s]: the walk down to it gives both of its ends
        _, w_lo, w_hi = self._interval(replicate, points, jnp.arange(BLOCK, dtype=jnp.uint32), k0 * substeps, depth, dt)
        return w_hi - w_lo


@functools.partial(jax.jit, static_argnums=1)
def scrambled_sobol(key: PRNGKeyArray, d: int) -> tuple[Array, Array]:
    """Linearly scrambled direction numbers ``(d, 32)`` and a digital shift ``(d,)``, ``uint32``, from ``key``.

    Column ``l`` (bit ``31 − l``, most significant first) of the lower-triangular matrix ``M`` is ``1`` on the
    diagonal and random below it; ``M V`` over GF(2) is the XOR of the columns at the set bits of ``V``.
    """
    k_matrix, k_shift = jr.split(key)
    top = jnp.left_shift(jnp.uint32(1), jnp.arange(BITS - 1, -1, -1, dtype=jnp.uint32))  # bit 31 − l
    columns = (jr.bits(k_matrix, (d, BITS), jnp.uint32) & (top - jnp.uint32(1))) | top
    v = jnp.asarray(_direction_numbers(d))
    scrambled = jnp.zeros_like(v)
    for col in range(BITS):
        hit = (v & top[col]) != 0
        scrambled = scrambled ^ jnp.where(hit, columns[:, col, None], jnp.uint32(0))
    return scrambled, jr.bits(k_shift, (d,), jnp.uint32)


class QuasiMonteCarloEstimate(AbstractEstimate):
    """Means and covariances by randomised quasi-Monte Carlo, with standard errors from the spread of ``replicates``
    independent scramblings; ``derivatives`` in the parameters ``wrt`` when asked for; ``cost`` the path-steps of
    all replicates."""

    ts: Float[Values, " n"]
    mean: Float[Values, "n k"]
    cov: Float[Values, "n k k"]
    mean_se: Float[Values, "n k"]
    cov_se: Float[Values, "n k k"]
    n_paths: Int[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    replicates: int = eqx.field(static=True)
    derivatives: Derivatives | None
    cost: Cost = eqx.field(static=True)
    statistic: AbstractStatistic | None = eqx.field(static=True)


def allowed_solvers() -> list[str]:
    """The solvers quasi-Monte Carlo drives: the aliases that need Brownian increments only, and Platen's weak
    order-2 scheme with Gaussian increments."""
    brownian = [
        name
        for name, make in SOLVERS.items()
        if issubclass(dfx.BrownianIncrement, getattr(make(), "minimal_levy_area", dfx.AbstractBrownianIncrement))
    ]
    return brownian + ["nhsde.PlatenWeak2(increments='gaussian')"]


def check_solver(solver, system: StochasticSystem):
    """``solver``'s needs if the Sobol' drivers give its increments (:func:`allowed_solvers`); else raises."""
    needs = solver_needs(solver, system)
    if needs.levy_area not in (dfx.BrownianIncrement, GaussianWeakIncrement):
        raise ValueError(
            f"solver={solver!r} needs {needs.levy_area.__name__}, which quasi-Monte Carlo does not draw; "
            f"allowed: {', '.join(allowed_solvers())}, or a diffrax solver that needs Brownian increments only."
        )
    return needs


def stacked_scramblings(key, replicates: int, d: int) -> tuple[Array, Array]:
    """Scramblings ``r = 0 … replicates − 1`` (:func:`scrambled_sobol` of ``fold_in(key, r)``), stacked: ``v``
    ``(R, d, 32)`` and ``shift`` ``(R, d)``, stacked on the host (no program per count)."""
    scrambled = [scrambled_sobol(fold_key(key, r), d) for r in range(replicates)]
    return tuple(jax.device_put(np.stack([np.asarray(s[i]) for s in scrambled])) for i in (0, 1))


def combine_replicates(means: Values, seconds: Values):
    """Mean and covariance from per-replicate means ``(R, n, k)`` and second moments ``(R, n, k, k)``.

    ``E[m mᵀ] = μμᵀ + Cov(m)``, and ``Cov(m)`` is estimated without bias by the replicate spread over ``R``:
    ``cov = avg(S_r) − m mᵀ − Σ_r (m_r − m)(m_r − m)ᵀ / (R(R − 1))``.
    """
    xp = array_module(means, seconds)
    r = means.shape[0]
    mean = xp.mean(means, axis=0)
    dev = means - mean
    spread = xp.einsum("rni,rnj->nij", dev, dev) / (r * (r - 1))
    return mean, xp.mean(seconds, axis=0) - xp.einsum("ni,nj->nij", mean, mean) - spread


def _se(per_replicate: Values, axis: int = 0) -> Values:
    return array_module(per_replicate).std(per_replicate, axis=axis, ddof=1) / math.sqrt(per_replicate.shape[axis])


def quasi_monte_carlo(
    system: StochasticSystem,
    y0,
    key,
    *,
    n_paths: int,
    t1: float,
    dt: float | None = None,
    steps: FixedSteps | None = None,
    replicates: int = 16,
    t0: float = 0.0,
    solver: str | dfx.AbstractSolver = "euler",
    save: Save | None = None,
    antithetic: bool = False,
    batching: Batching | None = None,
    wrt: Sequence[str] | None = None,
) -> QuasiMonteCarloEstimate:
    """Means and covariances of the saved quantities by randomised quasi-Monte Carlo (module).

    One :func:`~nhsde.simulate` of ``replicates × n_paths`` paths, the system's Wiener driver replaced by
    ``replicates`` independently scrambled Sobol' point sets (keys ``fold_in(key, r)``) through a Brownian
    bridge, ``n_paths`` paths each; the per-replicate moments are reduced from the kept paths (on the host in
    float64 for concrete values).  The same key gives bitwise the same result, whatever the batching.  Every
    path has the law of a Monte-Carlo path, so the estimate is unbiased for the scheme's expectation at ``dt``:
    ``mean = avg_r m_r``, ``cov = avg_r S_r − mean meanᵀ − Ĉov(mean)`` with ``S_r`` replicate ``r``'s second
    moment and ``Ĉov(mean)`` the replicate spread over ``R``.  Paths within a replicate are dependent, so
    per-path standard errors would be wrong: the errors are the standard deviations over the independent
    replicates divided by ``√R`` (``R ≥ 8`` gives usable errors).

    The gain needs a statistic smooth in the path ``W`` (moments of a smooth flow are; indicators and
    maxima gain little), and falls with the dimension ``(t1 − t0)/dt × noise channels``.  Measured against
    Monte Carlo at the same paths, scheme and step: on the ball (Euler, 16 steps, 4096 paths × 16
    replicates) the covariances' standard errors 24–49× smaller (variance ÷700–2400) at ~7× the time per
    path; the host prototype (``benchmarks/qmc.py``, 16384 paths) variance ÷120–3400 on the ball, the sleigh
    and the body on the vibrating plane, ÷4–7 on Chaplygin's ball.

    Arguments as :func:`~nhsde.simulate` (the step ``dt=h`` or ``steps=FixedSteps(h)``); ``n_paths`` per replicate,
    a power of two ≥ 64 (the Sobol' points ``0 … n_paths − 1`` form a net); ``(t1 − t0)/dt`` a power of two with
    ``(t1 − t0)/dt × channels ≤ 21201``; ``solver`` one of :func:`allowed_solvers`: one that needs Brownian
    increments only (not Lévy area), or ``nhsde.PlatenWeak2(increments='gaussian')`` (weak order 2), whose ``ΔW``
    come from the points and two-point ``V`` pseudo-random from ``fold_in(key, replicates)``; ``antithetic``: every
    point also solved with its increments reflected (``W → −W``, the point set ``1 − u``), its value the pair's
    average and its second moment the average of the two paths' (twice the path-steps; it gains where the statistic
    has a part odd in ``W``, :mod:`._variance_reduction`); ``wrt``: names of scalar parameters: ``derivatives`` of
    the moments in them (forward mode), with errors from the replicate spread.
    """
    watch = Stopwatch()
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    wrt = () if wrt is None else check_wrt(system, wrt)
    if not system.noise.continuous:
        raise ValueError(
            f"system.noise={type(system.noise).__name__} has jumps; quasi-Monte Carlo needs a Wiener driver."
        )
    check_solver(solver, system)
    n_paths = check_number("n_paths", n_paths, integer=True)
    if n_paths < BLOCK or n_paths & (n_paths - 1) or n_paths > MAX_PATH_INDEX:
        raise ValueError(
            f"n_paths={n_paths}; quasi-Monte Carlo needs a power of two ≥ {BLOCK} (the Sobol' points of a "
            f"replicate form a net), at most {MAX_PATH_INDEX + 1 >> 1}."
        )
    replicates = check_number("replicates", replicates, integer=True)
    if replicates < 2:
        raise ValueError(f"replicates={replicates}; the standard errors need ≥ 2 independent scramblings.")
    if not isinstance(antithetic, bool):
        raise TypeError(f"antithetic={antithetic!r}; expected True or False.")
    if replicates * n_paths > MAX_PATH_INDEX + 1:
        raise ValueError(
            f"replicates={replicates}, n_paths={n_paths}: {replicates * n_paths} paths in one run, beyond the "
            f"{MAX_PATH_INDEX + 1} it indexes; take fewer."
        )
    # a point set fixed in advance: no adaptive steps
    run = run_options(
        "quasi_monte_carlo", t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, batching=batching
    )
    dt, n_base = run.dt, run.n_steps
    if n_base & (n_base - 1):
        raise ValueError(
            f"dt={dt}: (t1 − t0)/dt = {n_base} base steps; quasi-Monte Carlo needs a power of two such as "
            f"{1 << (n_base.bit_length() - 1)} or {1 << n_base.bit_length()}."
        )
    m = system.noise_dim
    if n_base * m > MAX_DIMENSION:
        raise ValueError(
            f"dt={dt}, t1={t1}: {n_base} steps × {m} channels = {n_base * m} Sobol' dimensions, beyond the "
            f"{MAX_DIMENSION} of the direction numbers; take a larger dt or a shorter t1 − t0."
        )
    key = check_key(key)
    save = Save() if run.save is None else run.save
    names = system.layout.names if save.names is None else save.names

    v, shift = stacked_scramblings(key, replicates, n_base * m)  # independent scramblings
    blocks = jax.device_put(np.asarray(n_paths // BLOCK, np.int32))
    driven = eqx.tree_at(
        lambda s: s.noise, system, ScrambledSobol(v=v, shift=shift, blocks=blocks, n_base=n_base, channels=m)
    )
    run = dataclasses.replace(run, save=dataclasses.replace(save, paths=True))
    paths_key = fold_key(key, replicates)  # the pseudo-random parts (PlatenWeak2's V): no scrambling's key

    def moments(s):
        """Per-replicate means ``(R, n, k)`` and second moments ``(R, n, k, k)`` of one run of all the paths (and
        of their reflections: the averages over both)."""
        zs = []
        for solved in (s, reflected(s)) if antithetic else (s,):
            ens = simulate_run(solved, y0, paths_key, run, n_paths=replicates * n_paths)
            assert ens.paths is not None
            xp = array_module(ens.paths)  # concrete: on the host in float64, no program per shape
            z = np.asarray(ens.paths, np.float64) if xp is np else ens.paths
            zs.append(z.reshape(replicates, n_paths, -1, len(names)))
        z = xp.stack(zs)  # (1 or 2, R, n_paths, n, k)
        mean = xp.mean(z, axis=(0, 2))
        f = z - mean[None, :, None]
        second = xp.einsum("arpni,arpnj->rnij", f, f) / (len(zs) * n_paths)
        return ens.ts, mean, second + xp.einsum("rni,rnj->rnij", mean, mean)

    (ts, means, seconds), tangents = with_tangents(moments, driven, wrt)
    xp = array_module(means, seconds)
    mean, cov = combine_replicates(means, seconds)
    per_cov = seconds - xp.einsum("rni,rnj->rnij", means, means)
    derivatives = None
    if tangents is not None:
        d_means, d_seconds = tangents[1], tangents[2]  # (p, R, n, k), (p, R, n, k, k)
        d_mean, d_cov = jax.vmap(lambda dm, ds: jax.jvp(combine_replicates, (means, seconds), (dm, ds))[1])(
            d_means, d_seconds
        )
        d_outer = jnp.einsum("prni,rnj->prnij", d_means, means)
        d_per_cov = d_seconds - d_outer - jnp.swapaxes(d_outer, -1, -2)
        derivatives = Derivatives(d_mean, d_cov, _se(d_means, 1), _se(d_per_cov, 1), wrt)
    estimate = QuasiMonteCarloEstimate(
        ts=ts,
        mean=mean,
        cov=cov,
        mean_se=_se(means),
        cov_se=_se(per_cov),
        n_paths=jax.device_put(np.asarray(replicates * n_paths)),
        names=names,
        roles=roles_of(system, names),
        replicates=replicates,
        derivatives=derivatives,
        cost=watch.cost((2 if antithetic else 1) * replicates * n_paths * n_base),
        statistic=None,
    )
    return on_device(estimate, ts.dtype)
