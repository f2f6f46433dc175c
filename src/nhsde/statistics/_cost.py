"""The estimators' model of bias, work and memory: one copy, used to plan (``to_accuracy``) and to run (MLMC).

Bias of a scheme of weak order ``p`` at the step ``h = h₀ 2^{−k}``, bounded by the pilot's ``|C|``:

    |E S(h) − S| ≤ bias_bound · h^p,

with ``h`` in time units, so ``h₀^p`` is part of it (Talay & Tubaro 1990).  A single-step estimator with
per-sample variance ``V`` reaches a root-mean-square error ``ε`` with ``N = V/(ε² − (bias_bound h^p)²)`` samples
(Glasserman 2004, §1.1.3), at ``N (t1 − t0)/h`` path-steps times its cost factor.  A multilevel level ``ℓ``
costs ``C_ℓ = s₀ 2^ℓ + s₀ 2^{ℓ−1}`` path-steps per sample (the fine and the coarse solve, ``s₀`` the coarsest
step count; twice that with antithetic pairs) and takes ``N_ℓ = σ²⁻¹ √(V_ℓ/C_ℓ) Σ_k √(V_k C_k)`` samples for a
variance ``Σ V_ℓ/N_ℓ = σ²`` (Giles 2008, §2), run in pieces of ``piece_paths 2^{−ℓ}`` paths (at least one
block).  A plan splits ``ε²`` between the squared bias bound and the variance: ``σ² = ε² − (bias_bound h^p)²``,
the number of levels (or the step) chosen where that costs least (Giles 2015, §2.3; Haji-Ali et al. 2016).

Memory.  The paired estimators keep per-path values: ``n_save × k`` numbers per path and solve (and per
parameter of ``wrt``); a plan whose values, with the copies its statistics make, would not fit in the device's
memory is refused before it runs (:func:`check_memory`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence

import jax
import jax.monitoring
import jax.numpy as jnp

from .._brownian import BLOCK

__all__ = [
    "MAX_LEVELS",
    "MAX_REFINEMENTS",
    "allocate",
    "best_single",
    "check_memory",
    "compile_clock",
    "memory_limit",
    "path_bytes",
    "peak_bytes",
    "level_cost",
    "level_piece",
    "multilevel_plan",
    "whole_pieces",
]

MAX_REFINEMENTS = 24
"""Finest step considered: ``h₀ 2^{−24}``."""
MAX_LEVELS = 12
"""Most multilevel levels, ``h₀ … h₀ 2^{−11}``."""
PEAK_COPIES = 3
"""Per-path values held at the peak of a paired estimate: the values, their concatenation and the centred copies."""


def bias(bound: float, h: float, order: float) -> float:
    """``bias_bound · h^p`` (module), ``inf`` where it overflows."""
    try:
        return bound * h**order
    except OverflowError:
        return math.inf


def best_single(
    variance: float,
    bound: float,
    order: float,
    eps: float,
    h0: float,
    steps0: int,
    cost_factor: float,
    max_refinements: int = MAX_REFINEMENTS,
    round_paths: Callable[[float], int] | None = None,
) -> tuple[float, int, int, float]:
    """``(cost, k, N, bias bound)`` of the cheapest ``h = h₀ 2^{−k}``, ``k ≤ max_refinements``, with
    ``N = V/(ε² − (bound h^order)²)`` (module) rounded up by ``round_paths`` (default: to whole pieces)."""
    best = (math.inf, -1, 0, math.nan)
    if not math.isfinite(variance) or not math.isfinite(bound):
        return best
    for k in range(max_refinements + 1):
        b = bias(bound, h0 / 2**k, order)
        if not b < eps:
            continue
        budget = (eps - b) * (eps + b)  # ε² − b², without overflow at huge ε
        n = variance / budget if budget < math.inf else 0.0
        if not n < 2.0**62:  # a tiny ε: no count reaches it
            continue
        n = round_paths(n) if round_paths else whole_pieces(n)[0]
        cost = n * steps0 * 2**k * cost_factor
        if cost < best[0]:
            best = (cost, k, n, b)
    return best


def piece_paths(n: float, cap: int = 4096) -> int:
    """A piece size for about ``n`` samples: ``64·2^k ≥ n/4`` (at most ``cap``), so that nearby ``n`` share one
    compiled program and whole pieces overshoot ``n`` by less than a quarter."""
    k = max(0, math.ceil(math.log2(max(n, 1) / (4 * BLOCK))))
    return min(cap, BLOCK * 2**k)


def whole_pieces(n: float, cap: int = 2**16) -> tuple[int, int]:
    """``(total, piece)``: ``n`` rounded up to whole pieces of :func:`piece_paths`."""
    piece = piece_paths(n, cap)
    return piece * max(1, math.ceil(n / piece)), piece


def level_cost(steps0: int, level: int, antithetic: bool, control: bool = False) -> float:
    """``C_ℓ``: path-steps per sample of multilevel level ``level`` (module); the reflected paths and a control
    (the linearised system on the same paths) each double it."""
    fine = steps0 * 2**level
    return (2.0 if antithetic else 1.0) * (2.0 if control else 1.0) * (fine + (fine // 2 if level else 0))


def level_piece(piece: int, level: int) -> int:
    """The smallest run of multilevel level ``level``: ``piece 2^{−ℓ}`` in whole blocks, at least one block."""
    return max(BLOCK, (piece >> level) // BLOCK * BLOCK)


def allocate(variances: Sequence[float], costs: Sequence[float], budget: float) -> list[float]:
    """``N_ℓ = σ²⁻¹ √(V_ℓ/C_ℓ) Σ_k √(V_k C_k)``: the least work with ``Σ V_ℓ/N_ℓ = σ²``, ``budget = σ²`` (module)."""
    total = sum(math.sqrt(v * c) for v, c in zip(variances, costs, strict=True))
    return [math.sqrt(v / c) * total / budget for v, c in zip(variances, costs, strict=True)]


def multilevel_plan(
    levels_v: Sequence[float],
    bound: float,
    order: int,
    eps: float,
    steps0: int,
    h0: float,
    anti: bool,
    base: int,
    max_levels: int = MAX_LEVELS,
    control: bool = False,
) -> tuple[float, tuple[int, ...], int, int]:
    """``(cost, N_ℓ, piece_paths, L + 1)`` predicted for ``multilevel_monte_carlo``, pieces included.

    The cheapest number of levels ``L + 1 ≥ 3`` whose bias bound ``b_L = bias_bound h_L^p`` is below ``ε``, with the
    variance ``ε² − b_L²`` left to the samples (module): a bias well under ``ε`` leaves nearly all of ``ε²`` to the
    variance, where a fixed ``b_L ≤ ε/√2`` would halve it.  ``V_ℓ`` beyond the pilot's decay at its finest rate
    ``2^{−β}``, ``1 ≤ β ≤ 2``.  Pieces of ``base·4^k`` paths on level 0 (``base`` the pilot's paths), at least
    ``N_0/16``: targets close to one another share the compiled programs of each level; ``control``: each sample
    also solves the linearised system (``level_cost``)."""
    v = [max(x, 1e-300) for x in levels_v]
    if not all(math.isfinite(x) for x in v) or not math.isfinite(bound):
        return math.inf, (), 0, 0
    beta = min(max(math.log2(v[-2] / v[-1]), 1.0), 2.0) if len(v) >= 3 else 1.0
    while len(v) < max_levels:
        v.append(v[-1] * 2**-beta)
    best: tuple[float, tuple[int, ...], int, int] = (math.inf, (), 0, 0)
    for n_levels in range(3, max_levels + 1):
        b = bias(bound, h0 / 2 ** (n_levels - 1), order)
        if not b < eps:
            continue
        costs = [level_cost(steps0, ell, anti, control) for ell in range(n_levels)]
        optimal = allocate(v[:n_levels], costs, (eps - b) * (eps + b))
        if not all(o < 2.0**62 for o in optimal):
            continue
        piece = min(2**16, base * 4 ** max(0, math.floor(math.log(max(optimal[0], 1) / (16 * base), 4)) + 1))
        piece = base if optimal[0] < 16 * base else piece
        counts = tuple(
            level_piece(piece, ell) * max(1, math.ceil(o / level_piece(piece, ell))) for ell, o in enumerate(optimal)
        )
        cost = float(sum(n * c for n, c in zip(counts, costs)))
        if cost < best[0]:
            best = (cost, counts, piece, n_levels)
    return best


def memory_limit() -> int:
    """Bytes of memory for per-path values: the default device's allocator limit where it reports one (GPU),
    else the host's physical memory (or its control group's limit, where lower)."""
    stats = jax.devices()[0].memory_stats() or {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            group = f.read().strip()
    except OSError:
        group = ""
    return min(limit, int(group)) if group.isdigit() else limit


def path_bytes(n_save: int, n_names: int, n_wrt: int) -> int:
    """Bytes of one solve's per-path values: ``n_save × k`` numbers, and as many per parameter of ``wrt``, in the
    default float precision."""
    return n_save * n_names * (1 + n_wrt) * jnp.dtype(jnp.result_type(float)).itemsize


def peak_bytes(kept: float) -> float:
    """Bytes at the peak of a paired estimate that keeps ``kept`` bytes of per-path values: ``PEAK_COPIES`` times."""
    return PEAK_COPIES * kept


def check_memory(name: str, need: float, fix: str) -> None:
    """Refuse, naming ``name``, a plan whose per-path values take ``need`` bytes at their peak, beyond
    :func:`memory_limit`; ``fix`` says what to change."""
    limit = memory_limit()
    if need > limit:
        raise ValueError(
            f"{name} keeps per-path values of {need / 2**30:.3g} GiB at their peak, more than the "
            f"{limit / 2**30:.3g} GiB of memory here; {fix}"
        )


_compiled = {"seconds": 0.0, "listening": False}


def _listen(event: str, duration_secs: float, **kwargs: str | int) -> None:
    # lowering to MLIR and the backend's compilation (tracing is left out: its events nest, an outer trace's
    # duration including the inner ones)
    if event in ("/jax/core/compile/jaxpr_to_mlir_module_duration", "/jax/core/compile/backend_compile_duration"):
        _compiled["seconds"] += duration_secs


def compile_clock() -> float:
    """Seconds JAX has spent lowering and compiling programs since the first call (its compilation events): the
    difference of two readings is the compile time between them."""
    if not _compiled["listening"]:
        jax.monitoring.register_event_duration_secs_listener(_listen)
        _compiled["listening"] = True
    return _compiled["seconds"]
