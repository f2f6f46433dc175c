"""What every estimator returns, and what it is asked for: one abstract estimate type with final subclasses
(as diffrax returns one ``Solution`` whatever the solver), the statistic, derivatives and cost.

- A statistic (:class:`Mean`, :class:`Covariance`) names saved quantities once and picks itself out of means and
  covariances (or of their standard errors or derivatives) at the last save time.
- :class:`AbstractEstimate`: means and covariances at ``ts`` with standard errors, ``derivatives`` (with standard
  errors, :class:`Derivatives`) where asked for, and ``cost`` (:class:`Cost`: path-steps, seconds and the seconds
  spent compiling, measured).  ``value(statistic)`` and ``derivative(statistic)`` read one statistic with its
  standard error.
"""

from __future__ import annotations

import abc
import dataclasses
import time
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float, Int

from .._ensemble import AbstractMoments
from ._cost import compile_clock

Values = Array | np.ndarray
"""Arrays of statistics: NumPy while a concrete estimate is reduced on the host, JAX arrays once it is complete
(``on_device``) and under JAX transformations."""

__all__ = [
    "AbstractEstimate",
    "AbstractStatistic",
    "Cost",
    "Covariance",
    "Derivatives",
    "Mean",
    "MonteCarloEstimate",
    "as_statistic",
]


class AbstractStatistic(eqx.Module):
    """One statistic of the saved quantities at the last save time: what an estimator is asked to control."""

    @property
    @abc.abstractmethod
    def names(self) -> tuple[str, ...]:
        """The saved quantities it reads."""

    @abc.abstractmethod
    def pick(self, names: tuple[str, ...], mean, cov) -> Any:
        """Its entry at the last save time of ``mean (…, n, k)`` and ``cov (…, n, k, k)`` (or of their standard
        errors, variances or derivatives: leading axes are kept) of the saved quantities ``names``."""

    def check(self, names: tuple[str, ...], argument: str = "statistic") -> None:
        """Raise naming ``argument`` if a quantity it reads is not among the saved ``names``."""
        missing = [n for n in self.names if n not in names]
        if missing:
            raise ValueError(f"{argument}={self} names {missing}, which are not saved; available: {names}.")


class Mean(AbstractStatistic):
    """``E[name]`` at the last save time."""

    name: str = eqx.field(static=True)

    @property
    def names(self) -> tuple[str, ...]:
        return (self.name,)

    def pick(self, names, mean, cov) -> Any:
        return mean[..., -1, names.index(self.name)]

    def __str__(self) -> str:
        return f"mean {self.name}"


class Covariance(AbstractStatistic):
    """``Cov[a, b]`` at the last save time."""

    a: str = eqx.field(static=True)
    b: str = eqx.field(static=True)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys((self.a, self.b)))

    def pick(self, names, mean, cov) -> Any:
        return cov[..., -1, names.index(self.a), names.index(self.b)]

    def __str__(self) -> str:
        return f"cov {self.a} {self.b}"


def as_statistic(value, argument: str = "statistic") -> AbstractStatistic:
    """``value`` as a statistic: a :class:`Mean` or :class:`Covariance`, or the shorthand ``('mean', name)`` or
    ``('cov', a, b)``; otherwise a ``ValueError`` naming ``argument``."""
    if isinstance(value, AbstractStatistic):
        return value
    if isinstance(value, tuple) and all(isinstance(n, str) for n in value):
        if len(value) == 2 and value[0] == "mean":
            return Mean(value[1])
        if len(value) == 3 and value[0] == "cov":
            return Covariance(value[1], value[2])
    raise ValueError(
        f"{argument}={value!r}; expected nhsde.statistics.Mean(name) or Covariance(a, b), or ('mean', name) or "
        "('cov', a, b)."
    )


@dataclasses.dataclass(frozen=True)
class Cost:
    """Work done: ``path_steps`` (solver steps summed over paths), wall ``seconds`` of the call, and
    ``compile_seconds`` of them spent tracing and compiling (JAX's compilation events)."""

    path_steps: float
    seconds: float = float("nan")
    compile_seconds: float = float("nan")

    def __add__(self, other: Cost) -> Cost:
        return Cost(
            self.path_steps + other.path_steps,
            self.seconds + other.seconds,
            self.compile_seconds + other.compile_seconds,
        )


class Stopwatch:
    """Seconds and compile seconds since it was started: ``cost(path_steps)`` is the :class:`Cost` so far."""

    def __init__(self):
        self.start, self.compile_start = time.perf_counter(), compile_clock()

    def cost(self, path_steps: float) -> Cost:
        return Cost(float(path_steps), time.perf_counter() - self.start, compile_clock() - self.compile_start)


class Derivatives(eqx.Module):
    """Derivatives of an estimate's means and covariances in the parameters ``wrt`` (leading axis), with their
    Monte-Carlo standard errors (per-path tangents)."""

    d_mean: Float[Values, "p n k"]
    d_cov: Float[Values, "p n k k"]
    d_mean_se: Float[Values, "p n k"]
    d_cov_se: Float[Values, "p n k k"]
    wrt: tuple[str, ...] = eqx.field(static=True)


class AbstractEstimate(AbstractMoments):
    """Means and covariances of saved quantities at ``ts`` with their Monte-Carlo standard errors: what every
    estimator returns.

    ``n_paths`` counts the sampled paths (pairs count once); ``derivatives`` in the parameters ``wrt`` where asked
    for, else ``None``; ``cost`` the work done.  ``statistic`` is the one the estimator controlled, where it chose
    its effort for one (``None`` where every entry was computed alike).
    """

    ts: eqx.AbstractVar[Float[Values, " n"]]
    mean: eqx.AbstractVar[Float[Values, "n k"]]
    cov: eqx.AbstractVar[Float[Values, "n k k"]]
    mean_se: eqx.AbstractVar[Float[Values, "n k"]]
    cov_se: eqx.AbstractVar[Float[Values, "n k k"]]
    n_paths: eqx.AbstractVar[Int[Array, ""]]
    derivatives: eqx.AbstractVar[Derivatives | None]
    cost: eqx.AbstractVar[Cost]
    statistic: eqx.AbstractVar[AbstractStatistic | None]

    def standard_errors(self):
        return self.mean_se, self.cov_se

    def _statistic(self, statistic) -> AbstractStatistic:
        if statistic is None:
            if self.statistic is None:
                raise TypeError("value(statistic): name the statistic, e.g. Mean('x') or ('cov', 'x', 'x').")
            return self.statistic
        statistic = as_statistic(statistic)
        statistic.check(self.names)
        return statistic

    def value(self, statistic=None):
        """``(value, standard error)`` of ``statistic`` (default: the one the estimator controlled) at ``ts[-1]``."""
        s = self._statistic(statistic)
        return s.pick(self.names, self.mean, self.cov), s.pick(self.names, self.mean_se, self.cov_se)

    def derivative(self, statistic=None):
        """``(derivatives, standard errors)`` ``(len(wrt),)`` of ``statistic`` in the parameters ``wrt``."""
        if self.derivatives is None:
            raise ValueError("derivative(): this estimate was computed without wrt=…; pass wrt=('eps', …).")
        s, d = self._statistic(statistic), self.derivatives
        return s.pick(self.names, d.d_mean, d.d_cov), s.pick(self.names, d.d_mean_se, d.d_cov_se)


class MonteCarloEstimate(AbstractEstimate):
    """Means and covariances of paths with their standard errors (e.g. the two solves of an extrapolation)."""

    ts: Float[Values, " n"]
    mean: Float[Values, "n k"]
    cov: Float[Values, "n k k"]
    mean_se: Float[Values, "n k"]
    cov_se: Float[Values, "n k k"]
    n_paths: Int[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    derivatives: Derivatives | None
    cost: Cost = eqx.field(static=True)
    statistic: AbstractStatistic | None = eqx.field(static=True)
