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
and runs are independent of the chunking.  All ``R`` scramblings run as one solve: block ``b``
of a run is point block ``b // R`` of scrambling ``b mod R`` (:class:`ScrambledSobol`), so
the points ``N … 2N − 1`` of every scrambling are the contiguous paths ``NR … 2NR − 1``.

Scrambling (Owen 1998; Matoušek 1998): a random linear matrix scramble, per dimension a
lower-triangular binary matrix with unit diagonal acting on the bits (most significant
first) of the direction numbers ``V`` (the scramble is linear, so ``V' = M V``), and a
random digital shift ``s``.  Each point is then uniform on the unit cube and the first
``2^k`` points keep the net property of the sequence.  Direction numbers: Joe & Kuo
(2008), the table SciPy ships for ``scipy.stats.qmc.Sobol``, read from its file (at most 21201 dimensions).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.util
import math
import pathlib
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray, UInt

from .._brownian import BLOCK, AbstractDriver
from .._misc import fold_key, is_concrete, under_trace
from .._solvers import SOLVERS, solver_needs
from .._system import StochasticSystem
from .._weak import GaussianWeakIncrement
from ._estimate import AbstractEstimate, AbstractStatistic, Cost, Derivatives, Values
from ._paths import array_module

__all__ = ["QuasiMonteCarloEstimate", "scrambled_sobol", "sobol_points"]

MAX_DIMENSION = 21201
"""Dimensions of the direction numbers (Joe & Kuo's table in SciPy)."""
BITS = 32
LANE_BITS = BLOCK.bit_length() - 1
"""Bits of a path index that number its lane in a block (``BLOCK`` is a power of two)."""


@functools.lru_cache(maxsize=8)
def _direction_numbers(d: int) -> np.ndarray:
    """Unscrambled direction numbers ``(d, 32)`` ``uint32``, column ``b`` for bit ``b`` of the point index (Joe & Kuo
    2008, §2): dimension ``j`` of primitive polynomial ``x^s + a_1 x^{s−1} + … + a_{s−1} x + 1`` (``poly``, its
    leading and trailing ones included) and initial numbers ``m_1 … m_s`` (``vinit``) has ``V_b = m_{b+1} 2^{31−b}``
    for ``b < s``, then ``V_b = V_{b−s} ⊕ (V_{b−s} ≫ s) ⊕ a_1 V_{b−1} ⊕ … ⊕ a_{s−1} V_{b−s+1}``; dimension 0 is
    ``V_b = 2^{31−b}``.  The table is read from SciPy's file without importing ``scipy.stats`` (0.5–0.6 s)."""
    spec = importlib.util.find_spec("scipy")
    assert spec is not None and spec.submodule_search_locations
    with np.load(pathlib.Path(spec.submodule_search_locations[0], "stats", "_sobol_direction_numbers.npz")) as table:
        poly, vinit = table["poly"][:d].astype(np.uint64), table["vinit"][:d].astype(np.uint64)
    shifts = np.uint64(BITS - 1) - np.arange(BITS, dtype=np.uint64)
    v = np.zeros((d, BITS), np.uint64)
    v[0] = np.uint64(1) << shifts
    degree = np.array([int(x).bit_length() - 1 for x in poly])
    for s in range(1, int(degree.max(initial=0)) + 1):
        rows = np.flatnonzero(degree == s)
        rows = rows[rows > 0]
        if not rows.size:
            continue
        p = poly[rows]
        w = v[rows]
        w[:, :s] = vinit[rows, :s] << shifts[:s]
        for b in range(s, BITS):
            new = w[:, b - s] ^ (w[:, b - s] >> np.uint64(s))
            for k in range(1, s):
                a_k = (p >> np.uint64(s - k)) & np.uint64(1)
                new ^= a_k * w[:, b - k]
            w[:, b] = new
        v[rows] = w
    v = v.astype(np.uint32)
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


class ScrambledSobol(AbstractDriver):
    """The Wiener driver of quasi-Monte Carlo and of each level of the multilevel estimator (module): ``R``
    scramblings of Sobol' points in ``d`` dimensions through a Brownian bridge, stacked, ``v`` ``(R, d, 32)`` and
    ``shift`` ``(R, d)``; lane ``l`` of block ``b`` is point ``(b // R)·BLOCK + l`` of scrambling ``b mod R``;
    ``2^log_base`` base steps, as data (one compiled solve for every level and step).  Besides Brownian
    increments it gives :class:`~nhsde.PlatenWeak2`'s Gaussian ones: ``ΔW`` from the points, the two-point ``V``
    pseudo-random from the block key, as the Wiener driver draws it."""

    v: UInt[Array, "r d 32"]
    shift: UInt[Array, "r d"]
    log_base: Int[Array, ""]
    channels: int = eqx.field(static=True)
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

    def _increment(self, block, k0, dt, substeps):
        """``W((k0 + 1)·s) − W(k0·s)`` of the block's lanes, ``(BLOCK, m)``: step ``k0`` of ``s`` base steps (a
        power of two) is the dyadic interval ``[k0·s, (k0 + 1)·s]`` of the bridge: one walk from the root down
        through its ``log_base − log₂ s`` ancestors (a loop whose trip count is data) gives both of its ends."""
        r = self.shift.shape[0]
        replicate, points = block % r, (block // r).astype(jnp.uint32)
        lanes = jnp.arange(BLOCK, dtype=jnp.uint32)
        levels = self.log_base
        n_base = jnp.left_shift(jnp.int32(1), levels)
        substeps = jnp.asarray(substeps, jnp.int32)
        g, depth = k0 * substeps, levels - (jnp.int32(31) - jax.lax.clz(substeps))

        def normals(q):
            return self._normals(replicate, points, lanes, q, dt.dtype)

        w_lo = jnp.zeros((BLOCK, self.channels), dt.dtype)
        w_hi = jnp.sqrt(n_base.astype(dt.dtype) * dt) * normals(jnp.zeros((), jnp.int32))

        def ancestor(level, carry):  # the ancestors of g, coarse to fine
            lo, w_lo, w_hi = carry
            half = jnp.right_shift(n_base, level)
            mid = lo + half
            q = jnp.left_shift(jnp.int32(1), level - 1) + jnp.right_shift(lo, levels - level + 1)
            w_mid = 0.5 * (w_lo + w_hi) + jnp.sqrt(0.5 * half.astype(dt.dtype) * dt) * normals(q)
            left = g < mid
            return jnp.where(left, lo, mid), jnp.where(left, w_lo, w_mid), jnp.where(left, w_mid, w_hi)

        _, w_lo, w_hi = jax.lax.fori_loop(1, depth + 1, ancestor, (jnp.zeros((), jnp.int32), w_lo, w_hi))
        return w_hi - w_lo

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
    ``(R, d, 32)`` and ``shift`` ``(R, d)``, stacked on the host (no program per count); a concrete key's under a
    JAX transformation too (computed now), a traced key's (``vmap`` over keys) in the trace."""
    if not is_concrete(key):
        scrambled = [scrambled_sobol(fold_key(key, r), d) for r in range(replicates)]
        return jnp.stack([s[0] for s in scrambled]), jnp.stack([s[1] for s in scrambled])
    with jax.ensure_compile_time_eval() if under_trace() else contextlib.nullcontext():
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
