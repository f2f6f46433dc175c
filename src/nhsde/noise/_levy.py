"""Jump drivers: centred compound Poisson and Lévy processes, S0 (1.3)–(1.4).

Per noise channel, ``W(t) = W₀(t) + Σ_{jumps ≤ t} c_i − t λ E[c]``: a Wiener
part ``W₀`` (for :class:`Levy` only) plus jumps ``c_i`` of law ``c`` arriving at
rate ``λ``, centred by the compensator so that ``W`` has mean zero.  Its
intensity (variance per unit time, S0 (1.4)) is ``ν = ν₀ + λ E[c²]``.

Exact in law on the step grid.  On base step ``k`` of a block, one uniform per
lane and channel gives the jump count ``N ~ Poisson(λ dt)`` by inversion of its
survival function ``P(N > n)`` (summed from the top of the probability mass
function, so small probabilities keep their relative accuracy); counts above
``max_jumps`` are cut to ``max_jumps``, and that neglected
probability ``P(N > max_jumps)`` is checked to be below :data:`TRUNCATION` on
every step (a run-time error otherwise).  The sum of the ``N`` jumps is then
drawn exactly: in closed form where the law allows (normal jumps), else as the
masked sum of ``max_jumps`` draws.  Draws come from ``fold_in(fold_in(block_key,
JUMP_STREAM), k)``, so paths are deterministic, chunk-independent and
independent of the Wiener part; a step of ``substeps`` base steps sums them.

Counts are discrete: pathwise derivatives with respect to the intensity ``λ``
see only the compensator.  Differentiate with respect to ``λ`` through the
moment method (:func:`nhsde.statistics.normal_approximation`), not through paths.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array

from .._brownian import BLOCK, AbstractDriver, Wiener
from .._misc import over_substeps, substeps_span
from .._params import AbstractParameters, parameter, validated

__all__ = [
    "JUMP_STREAM",
    "TRUNCATION",
    "AbstractJumpLaw",
    "CompoundPoisson",
    "Levy",
    "NormalJumps",
    "ParetoJumps",
    "driver_intensity",
]

TRUNCATION = 1e-12
"""Largest allowed probability, per base step and channel, of more than ``max_jumps`` jumps."""

JUMP_STREAM = 2**32 - 1
"""``fold_in`` tag of a block's jump draws: never a (non-negative ``int32``) step counter of its Wiener draws."""


def _count_dtype():
    """Jump counts are resolved in the widest float available."""
    return jnp.result_type(float)


def _poisson_survival(mu, max_jumps: int):
    """``P(N > n)`` for ``n = 0 … max_jumps``, ``N ~ Poisson(μ)``: shape ``(*μ.shape, max_jumps + 1)``.

    The probabilities ``p_j`` (in log space) are summed from ``j = max_jumps + 24``
    down, and the rest is bounded by Chernoff's ``P(N ≥ m) ≤ e^{−μ}(eμ/m)^m``
    (``m > μ``; 1 otherwise), so the result is never below the truth.
    """
    m = max_jumps + 25
    j = jnp.arange(m, dtype=mu.dtype)
    mu = mu[..., None]
    positive = mu > 0
    log_mu = jnp.log(jnp.where(positive, mu, 1.0))
    p = jnp.where(positive, jnp.exp(-mu + j * log_mu - jax.lax.lgamma(j + 1)), (j == 0).astype(mu.dtype))
    bound = jnp.where(mu < m, jnp.exp(-mu + m * (1 + log_mu - jnp.log(jnp.asarray(m, mu.dtype)))), 1.0)
    tail = jnp.where(positive, bound, 0.0)
    above = jnp.cumsum(p[..., ::-1], axis=-1)[..., ::-1]  # above[i] = Σ_{j ≥ i} p_j
    return above[..., 1 : max_jumps + 2] + tail


class AbstractJumpLaw(AbstractParameters):
    """Law of the jump sizes ``c`` (one independent law per channel; leaves broadcast over channels)."""

    @abc.abstractmethod
    def moment(self, k: int) -> Array:
        """``E[c^k]`` (``inf`` where it does not exist)."""

    @abc.abstractmethod
    def sum_of_jumps(self, key, counts, max_jumps: int, dtype) -> Array:
        """The sum of ``counts`` independent jumps, elementwise (``counts ≤ max_jumps``)."""


class NormalJumps(AbstractJumpLaw):
    """Jumps ``c ~ N(mean, std²)``; the sum of ``N`` of them is ``N·mean + √N·std·Z`` exactly.

    Arguments:
        mean: the mean jump size (scalar or per channel).
        std: the standard deviation of the jump size.

    Examples:
        >>> from nhsde import noise
        >>> [float(noise.NormalJumps(mean=1.0, std=2.0).moment(k)) for k in (1, 2, 4)]
        [1.0, 5.0, 73.0]
    """

    mean: Array = parameter(default=0.0, per_channel=True, doc="mean jump size")
    std: Array = parameter(default=1.0, lower=0.0, per_channel=True, doc="standard deviation of the jump size")

    def moment(self, k):
        m, s = self.mean, self.std
        moments = {1: m, 2: m**2 + s**2, 3: m**3 + 3 * m * s**2, 4: m**4 + 6 * m**2 * s**2 + 3 * s**4}
        if k not in moments:
            raise ValueError(f"NormalJumps.moment: k={k}; moments 1–4 are offered.")
        return moments[k]

    def sum_of_jumps(self, key, counts, max_jumps, dtype):
        n = counts.astype(dtype)
        z = jr.normal(key, counts.shape, dtype)
        return n * self.mean.astype(dtype) + jnp.sqrt(n) * self.std.astype(dtype) * z


class ParetoJumps(AbstractJumpLaw):
    """Symmetric heavy-tailed jumps ``c = ±scale·U^{−1/tail}``: ``P(|c| > x) = (scale/x)^tail``, ``x ≥ scale``.

    ``E|c|^k = scale^k tail/(tail − k)`` for ``k < tail``; finite variance needs ``tail > 2``.

    Arguments:
        scale: the smallest jump size.
        tail: the tail index, ``> 2``.
    """

    scale: Array = parameter(default=1.0, lower=0.0, per_channel=True, doc="smallest jump size")
    tail: Array = parameter(
        default=3.0, lower=2.0, strict=True, per_channel=True, doc="tail index; > 2 for finite variance"
    )

    def __check_init__(self):
        try:
            tail = float(jnp.min(self.tail))
        except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
            return  # traced: `validated` checks it at run time
        if not tail > 2:
            raise ValueError(
                f"ParetoJumps: tail={tail!r} gives a jump law without finite variance "
                "(E c² = ∞ unless tail > 2); S0 (1.3) needs W with finite covariance."
            )

    def moment(self, k):
        """``E[c^k]``: ``scale^k tail/(tail − k)`` for even ``k < tail``, 0 for odd ``k < tail``, else
        ``inf``/``nan``."""
        exists = self.tail > k
        if k % 2:
            return jnp.where(exists, 0.0, jnp.nan) * self.scale
        return self.scale**k * jnp.where(exists, self.tail / (self.tail - k), jnp.inf)

    def sum_of_jumps(self, key, counts, max_jumps, dtype):
        k_size, k_sign = jr.split(key)
        shape = (max_jumps,) + counts.shape
        u = 1.0 - jr.uniform(k_size, shape, dtype)  # in (0, 1]
        size = self.scale.astype(dtype) * u ** (-1.0 / self.tail.astype(dtype))
        sign = jnp.where(jr.bernoulli(k_sign, 0.5, shape), 1.0, -1.0).astype(dtype)
        used = jnp.arange(max_jumps)[(slice(None),) + (None,) * counts.ndim] < counts
        return jnp.sum(jnp.where(used, sign * size, 0.0), axis=0)


class CompoundPoisson(AbstractDriver, AbstractParameters):
    """Centred compound Poisson process: jumps of law ``law`` at rate ``intensity`` per channel.

    S0's Poisson stochastic systems.  ``intensity`` (``λ``) and the law's leaves
    are scalars or per-channel arrays.  Intensity of ``W``: ``λ E[c²]`` (1.4).

    Arguments:
        law: the jump law (:class:`NormalJumps`, :class:`ParetoJumps`).
        intensity: the jump rate ``λ`` per unit time and channel.
        max_jumps: most jumps counted per step and channel (a step with a larger probability of more
            than this raises at run time).

    Examples:
        Pass it as a system's ``noise``; its intensity (1.4) is ``λ E[c²]``:

        >>> import nhsde
        >>> jumps = nhsde.noise.CompoundPoisson(law=nhsde.noise.NormalJumps(std=0.5), intensity=2.0)
        >>> float(jumps.variance_rate())
        0.5
        >>> float(nhsde.noise.Levy(jumps=jumps).variance_rate())  # plus the unit Wiener part
        1.5
    """

    law: AbstractJumpLaw
    intensity: Array = parameter(default=1.0, lower=0.0, per_channel=True, doc="jump rate λ per unit time and channel")
    max_jumps: int = eqx.field(static=True, default=12)

    continuous: ClassVar[bool] = False

    def __check_init__(self):
        if not isinstance(self.law, AbstractJumpLaw):
            raise TypeError(f"law={self.law!r}; expected a jump law such as nhsde.noise.NormalJumps(std=…).")
        if isinstance(self.max_jumps, bool) or not isinstance(self.max_jumps, int) or self.max_jumps < 1:
            raise ValueError(f"max_jumps={self.max_jumps!r}; must be a whole number ≥ 1.")

    def variance_rate(self) -> Array:
        """``λ E[c²]``: the intensity of S0 (1.4) per channel."""
        return self.intensity * self.law.moment(2)

    def neglected_probability(self, dt) -> Array:
        """``P(N > max_jumps)`` for one step ``dt``, per channel: the truncation of the count (never underestimated)."""
        mu = jnp.asarray(self.intensity, _count_dtype()) * jnp.asarray(dt, _count_dtype())
        return _poisson_survival(mu, self.max_jumps)[..., -1]

    def block_increment(self, key, block, k0, dt, shape, substeps, levy_area):
        del block  # the block key alone defines the draws
        driver = validated(self)
        law = driver.law
        dtype = dt.dtype
        rate = jax.lax.stop_gradient(driver.intensity).astype(_count_dtype())
        mu = jnp.broadcast_to(rate * dt.astype(_count_dtype()), shape)
        survival = _poisson_survival(mu, self.max_jumps)  # P(N > n), n = 0 … max_jumps
        intensity = eqx.error_if(
            driver.intensity,
            jnp.any(survival[..., -1] > TRUNCATION),
            f"CompoundPoisson: more than max_jumps={self.max_jumps} jumps in one step has probability "
            f"> {TRUNCATION:g} (intensity·dt too large); increase max_jumps or reduce dt.",
        )
        stream = jr.fold_in(key, JUMP_STREAM)

        def base_step(k, total):
            k_count, k_size = jr.split(jr.fold_in(stream, k))
            u = jr.uniform(k_count, (BLOCK,) + shape, _count_dtype())
            counts = jnp.sum(u[..., None] < survival[..., :-1], axis=-1)
            return total + law.sum_of_jumps(k_size, counts, self.max_jumps, dtype)

        jumps = over_substeps(base_step, k0, substeps, jnp.zeros((BLOCK,) + shape, dtype))
        compensator = substeps_span(substeps, dt) * intensity.astype(dtype) * law.moment(1).astype(dtype)
        return jumps - compensator


class Levy(AbstractDriver):
    """Wiener process plus independent centred compound-Poisson jumps: S0's general systems (1.3).

    Intensity of ``W``: ``1 + λ E[c²]`` per channel (1.4).  The Wiener part is
    the :class:`~nhsde.noise.Wiener` path of the same key, so ``Levy`` with no
    jumps reproduces it.

    Arguments:
        jumps: the :class:`CompoundPoisson` part.
    """

    jumps: CompoundPoisson

    continuous: ClassVar[bool] = False

    def __check_init__(self):
        if not isinstance(self.jumps, CompoundPoisson):
            raise TypeError(f"jumps={self.jumps!r}; expected nhsde.noise.CompoundPoisson(intensity=…, law=…).")

    def variance_rate(self) -> Array:
        """``1 + λ E[c²]`` per channel (1.4)."""
        return 1.0 + self.jumps.variance_rate()

    def block_increment(self, key, block, k0, dt, shape, substeps, levy_area):
        wiener = Wiener().block_increment(key, block, k0, dt, shape, substeps, levy_area)
        return wiener + self.jumps.block_increment(key, block, k0, dt, shape, substeps, levy_area)


def driver_intensity(driver: AbstractDriver, noise_dim: int, dtype=None) -> Array:
    """Intensity ``ν`` of the driving process per channel, S0 (1.4): ``(noise_dim,)`` (the driver's own)."""
    return driver.noise_intensity(noise_dim, jnp.result_type(float) if dtype is None else dtype)
