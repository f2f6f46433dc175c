"""Drift statistics of the dependent coordinates q'' (S0 §6, (6.6)–(6.7)).

In a Chaplygin system the dependent coordinates have no restoring force:
``q''(t) = ∫ Λ dτ`` (6.6).  Their mean ``m_{q''}(t)`` is the *systematic drift*
and their covariance ``K_{q''}(t)`` the *fluctuation drift* (6.7).  All
functions here are differentiable in the system's parameters through
:func:`~nhsde.simulate`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._simulate import Ensemble

__all__ = [
    "DriftStatistics",
    "StationaryMoments",
    "drift_statistics",
    "effective_diffusion",
    "fluctuation_drift",
    "stationary_moments",
    "systematic_drift",
]


class DriftStatistics(eqx.Module):
    """``m_{q''}(t)`` and ``K_{q''}(t)`` with their Monte-Carlo standard errors."""

    ts: Float[Array, " n"]
    systematic: Float[Array, "n k"]
    systematic_se: Float[Array, "n k"]
    fluctuation: Float[Array, "n k k"]
    fluctuation_se: Float[Array, "n k k"]
    names: tuple[str, ...] = eqx.field(static=True)


class StationaryMoments(eqx.Module):
    """Time-averaged mean and covariance over the save times ``t ≥ t_from``."""

    mean: Float[Array, " k"]
    cov: Float[Array, "k k"]
    names: tuple[str, ...] = eqx.field(static=True)


def _names_with_role(ens: Ensemble, role: str) -> tuple[str, ...]:
    return tuple(n for n, r in zip(ens.names, ens.roles) if r == role)


def drift_statistics(ens: Ensemble) -> DriftStatistics:
    """Systematic and fluctuation drift (6.7) of the saved dependent coordinates."""
    names = _names_with_role(ens, "dependent_coordinate")
    if not names:
        raise ValueError(
            f"no dependent coordinates among the saved {ens.names}; build the scene with drift=True "
            "and save its position components."
        )
    mean, cov, mean_se, cov_se = ens.select(names)
    return DriftStatistics(ens.ts, mean, mean_se, cov, cov_se, names)


def systematic_drift(ens: Ensemble) -> Float[Array, "n k"]:
    """``m_{q''}(t)`` at the save times."""
    return drift_statistics(ens).systematic


def fluctuation_drift(ens: Ensemble) -> Float[Array, "n k k"]:
    """``K_{q''}(t)`` at the save times."""
    return drift_statistics(ens).fluctuation


def effective_diffusion(ens: Ensemble, t_from: float | None = None) -> Float[Array, "k k"]:
    """``D = ½ dK_{q''}/dt``, the least-squares slope over save times ``t ≥ t_from``.

    In a stationary regime ``K_{q''}(t) ≈ 2 D t + const`` (Green–Kubo); ``t_from``
    defaults to the second half of the run.
    """
    stats = drift_statistics(ens)
    ts = ens.ts
    t_from = ts[-1] / 2 + ts[0] / 2 if t_from is None else t_from
    w = (ts >= t_from).astype(ts.dtype)
    if int(jnp.sum(w)) < 2:
        raise ValueError(f"t_from={t_from}: fewer than two save times at or after it; save more points.")
    tbar = jnp.sum(w * ts) / jnp.sum(w)
    dt = w * (ts - tbar)
    slope = jnp.einsum("n,nij->ij", dt, stats.fluctuation) / jnp.sum(dt * (ts - tbar))
    return slope / 2


def stationary_moments(ens: Ensemble, t_from: float) -> StationaryMoments:
    """Mean and covariance of the non-drifting saved components, averaged over ``t ≥ t_from``."""
    names = tuple(n for n, r in zip(ens.names, ens.roles) if r != "dependent_coordinate")
    if not names:
        raise ValueError(f"only dependent coordinates were saved ({ens.names}); nothing is stationary.")
    w = (ens.ts >= t_from).astype(ens.ts.dtype)
    if int(jnp.sum(w)) < 1:
        raise ValueError(f"t_from={t_from} is after the last save time {float(ens.ts[-1])}.")
    mean, cov, _, _ = ens.select(names)
    w = w / jnp.sum(w)
    return StationaryMoments(jnp.einsum("n,ni->i", w, mean), jnp.einsum("n,nij->ij", w, cov), names)
