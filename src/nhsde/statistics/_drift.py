"""Statistics of an ensemble: the drift of the dependent coordinates q'' (S0 §6, (6.6)–(6.7)), stationary moments.

In a Chaplygin system the dependent coordinates have no restoring force:
``q''(t) = ∫ Λ dτ`` (6.6).  Their mean ``m_{q''}(t)`` is the *systematic drift*
and their covariance ``K_{q''}(t)`` the *fluctuation drift* (6.7); their
effective diffusion is the slope of ``K_{q''}`` or, by Green–Kubo, the integral
of the velocity autocorrelation of the paths (:func:`green_kubo`).  The
moments come from :func:`~nhsde.simulate` (with Monte-Carlo standard errors)
or from the moment equations (:func:`~nhsde.statistics.normal_approximation`,
without); all functions here are differentiable in the system's parameters
through either.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._ensemble import AbstractMoments, Ensemble
from .._misc import check_number, is_concrete
from .._system import StochasticSystem

__all__ = [
    "DriftStatistics",
    "GreenKubo",
    "StationaryMoments",
    "drift_statistics",
    "effective_diffusion",
    "effective_diffusion_se",
    "fluctuation_drift",
    "green_kubo",
    "stationary_moments",
    "systematic_drift",
]


class DriftStatistics(eqx.Module):
    """``m_{q''}(t)`` and ``K_{q''}(t)`` with their Monte-Carlo standard errors (``None`` for moments without)."""

    ts: Float[Array, " n"]
    systematic: Float[Array, "n k"]
    systematic_se: Float[Array, "n k"] | None
    fluctuation: Float[Array, "n k k"]
    fluctuation_se: Float[Array, "n k k"] | None
    names: tuple[str, ...] = eqx.field(static=True)


class StationaryMoments(eqx.Module):
    """Time-averaged mean and covariance over the save times ``t ≥ t_from``."""

    mean: Float[Array, " k"]
    cov: Float[Array, "k k"]
    names: tuple[str, ...] = eqx.field(static=True)


def _names_with_role(ens: AbstractMoments, role: str) -> tuple[str, ...]:
    return tuple(n for n, r in zip(ens.names, ens.roles) if r == role)


def drift_statistics(ens: AbstractMoments, coordinates: tuple[str, ...] | None = None) -> DriftStatistics:
    """Systematic and fluctuation drift (6.7) of the saved dependent coordinates, or of the coordinates named.

    ``m_{q''}(t) = E q''(t)`` and ``K_{q''}(t) = Cov q''(t)``, read by default from the saved components whose
    role is ``dependent_coordinate`` (a shipped scene built with ``drift=True``; a system from a
    :class:`~nhsde.mechanics.MechanicalSpec` formulated with ``dependent=(...)``).  ``coordinates`` names
    the components instead, whatever their roles: e.g. both ``("x", "y")`` of a knife edge, of which one
    constraint makes only one dependent.

    Arguments:
        ens: an :class:`~nhsde.Ensemble` from :func:`~nhsde.simulate` or the moments of
            :func:`normal_approximation`.
        coordinates: saved names to take the drift statistics of (default: those with role
            ``dependent_coordinate``).

    Returns:
        a :class:`DriftStatistics`: ``systematic`` ``(n, k)``, ``fluctuation`` ``(n, k, k)`` at ``ens.ts``, with
        standard errors for Monte Carlo (``None`` for moment equations).

    Examples:
        The ball of S0 (3.1) from rest has no systematic drift; its fluctuation drift grows like ``νδ²t/(4ε²)``:

        >>> import nhsde
        >>> from nhsde import statistics
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0)
        >>> moments = statistics.normal_approximation(scene.build(), scene.initial_state(), t1=8.0, dt=0.5, order=3)
        >>> drift = statistics.drift_statistics(moments)
        >>> drift.names, drift.systematic_se
        (('x', 'y'), None)
        >>> print(float(drift.systematic[-1, 0]), round(float(drift.fluctuation[-1, 0, 0]), 4))
        0.0 0.9247
        >>> statistics.drift_statistics(moments, coordinates=("y",)).names
        ('y',)
    """
    if coordinates is None:
        names = _names_with_role(ens, "dependent_coordinate")
        if not names:
            raise ValueError(_no_dependent_coordinates(ens))
    else:
        names = tuple(coordinates) if not isinstance(coordinates, str) else (coordinates,)
        unknown = [n for n in names if n not in ens.names]
        if unknown or not names or len(set(names)) != len(names):
            raise ValueError(
                f"coordinates={coordinates!r}: name distinct saved components, at least one; saved: {ens.names}."
            )
    mean, cov, mean_se, cov_se = ens.select(names)
    return DriftStatistics(ens.ts, mean, mean_se, cov, cov_se, names)


def _no_dependent_coordinates(ens: AbstractMoments) -> str:
    """What to do when no saved component is a dependent coordinate: name them, or give them the role."""
    positions = _names_with_role(ens, "independent_coordinate")
    name = (positions or ens.names)[:1]
    fix = f"name the coordinates: drift_statistics(ens, coordinates={name!r}), or "
    if positions:  # coordinates without the dependent role: a system formulated from a spec (or a rolling body)
        fix += (
            f"give them the role when formulating a MechanicalSpec: formulate(spec, route, dependent={name!r}) "
            "(a spec scene: its class variable dependent); a shipped scene: build it with drift=True."
        )
    else:
        fix += "build the scene with drift=True and save its position components."
    return f"no dependent coordinates among the saved {ens.names}; {fix}"


def systematic_drift(ens: AbstractMoments) -> Float[Array, "n k"]:
    """``m_{q''}(t)`` at the save times."""
    return drift_statistics(ens).systematic


def fluctuation_drift(ens: AbstractMoments) -> Float[Array, "n k k"]:
    """``K_{q''}(t)`` at the save times."""
    return drift_statistics(ens).fluctuation


def effective_diffusion(
    ens: AbstractMoments, t_from: float | None = None, coordinates: tuple[str, ...] | None = None
) -> Float[Array, "k k"]:
    """``D = ½ dK_{q''}/dt``, the least-squares slope over save times ``t ≥ t_from``.

    In a stationary regime ``K_{q''}(t) ≈ 2 D t + const`` (Green–Kubo); ``t_from``
    defaults to the second half of the run.

    Arguments:
        ens: moments with the dependent coordinates saved (as for :func:`drift_statistics`).
        t_from: first save time of the fit (default: the middle of the run); at least two save times.
        coordinates: saved names to take it of (default: those with role ``dependent_coordinate``), as for
            :func:`drift_statistics`.

    Returns:
        ``D``, ``(k, k)`` over the dependent (or named) coordinates, differentiable in the system's parameters.

    Examples:
        The ball's ``D = νδ²/(8ε²)`` (S0 §3; ``δ = 5/7``):

        >>> import nhsde
        >>> from nhsde import statistics
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0)
        >>> moments = statistics.normal_approximation(scene.build(), scene.initial_state(), t1=8.0, dt=0.5, order=3)
        >>> print(statistics.effective_diffusion(moments).round(4))
        [[0.0638 0.    ]
         [0.     0.0638]]
        >>> print(round((5 / 7) ** 2 / 8, 4))
        0.0638
    """
    stats = drift_statistics(ens, coordinates)
    start = _fit_start(ens.ts, t_from)
    return _effective_diffusion(ens.ts, stats.fluctuation, start, not is_concrete(ens.ts, start))


def _fit_start(ts, t_from: float | None):
    """The first save time of the slope's fit (default the middle of the run); fewer than two save times at or
    after it are refused now where the times are concrete, else inside the fit (the same message)."""
    ts = np.asarray(ts) if is_concrete(ts) else ts  # concrete times: the start is found on the host
    start = ts[-1] / 2 + ts[0] / 2 if t_from is None else t_from
    if is_concrete(ts, start):
        if np.sum(ts >= np.asarray(start)) < 2:
            raise ValueError(_few_times(start))
    return start


def _few_times(start) -> str:
    return f"t_from={start}: fewer than two save times at or after it; save more points."


def _slope_weights(ts, start, traced: bool):
    """``c`` with ``Σ c_n K(t_n)`` the least-squares slope of ``K`` over the save times ``t ≥ start`` (checked here
    where ``traced``; concrete times were checked on the host, and a program without the check can be cached)."""
    w = (ts >= start).astype(ts.dtype)
    if traced:
        w = eqx.error_if(w, jnp.sum(w) < 2, _few_times("the fit's start"))
    tbar = jnp.sum(w * ts) / jnp.sum(w)
    dt = w * (ts - tbar)
    return dt / jnp.sum(dt * (ts - tbar))


@functools.partial(jax.jit, static_argnums=3)
def _effective_diffusion(ts, fluctuation, start, traced: bool):
    """``½ Σ_n c_n K(t_n)`` (one program)."""
    return jnp.einsum("n,nij->ij", _slope_weights(ts, start, traced).astype(fluctuation.dtype), fluctuation) / 2


def effective_diffusion_se(
    ens: Ensemble, t_from: float | None = None, coordinates: tuple[str, ...] | None = None
) -> Float[Array, "k k"]:
    """The Monte-Carlo standard error of :func:`effective_diffusion`, from the paths (``Save(paths=True)``).

    ``D̂ = ½ Σ_n c_n K̂(t_n)`` is a linear combination of sample covariances at several times of the same
    paths, so their errors are correlated.  With ``F_p(t) = z_p(t) − m(t)`` over the ``N`` paths used, the
    influence of path ``p`` is ``ψ_p = ½ Σ_n c_n F_p(t_n) F_p(t_n)ᵀ`` and (delta method, as for
    :func:`moment_sensitivities`) ``se(D̂) = N/(N−1) · std(ψ_p)/√N``.

    Arguments:
        ens: an :class:`~nhsde.Ensemble` with per-path values (``Save(paths=True)``).
        t_from, coordinates: as for :func:`effective_diffusion`.

    Returns:
        ``(k, k)``, the standard error of each entry of ``D``.
    """
    if ens.paths is None or ens.failed is None:
        raise ValueError("effective_diffusion_se needs the paths: simulate with Save(paths=True).")
    names = drift_statistics(ens, coordinates).names
    idx = tuple(ens.names.index(n) for n in names)
    start = _fit_start(ens.ts, t_from)
    return _effective_diffusion_se(ens.paths, ens.failed, ens.ts, start, idx, not is_concrete(ens.ts, start))


@functools.partial(jax.jit, static_argnums=(4, 5))
def _effective_diffusion_se(paths, failed, ts, start, idx: tuple[int, ...], traced: bool):
    """``N/(N−1) · std(ψ_p)/√N`` over the paths used (one program)."""
    used = (~failed)[:, None, None]
    n = (failed.size - jnp.sum(failed)).astype(paths.dtype)
    z = jnp.where(used, paths[..., jnp.asarray(idx)], 0)  # (P, n, k), failed paths (maybe nan) zero
    f = jnp.where(used, z - jnp.sum(z, axis=0) / n, 0)
    psi = jnp.einsum("n,pni,pnj->pij", _slope_weights(ts, start, traced).astype(f.dtype), f, f) / 2
    mean = jnp.sum(psi, axis=0) / n
    var = jnp.sum(jnp.where(used, psi - mean, 0) ** 2, axis=0) / (n - 1)
    return n / (n - 1) * jnp.sqrt(var / n)


def stationary_moments(ens: AbstractMoments, t_from: float) -> StationaryMoments:
    """Mean and covariance of the non-drifting saved components, averaged over ``t ≥ t_from``.

    Arguments:
        ens: moments from :func:`~nhsde.simulate` or :func:`normal_approximation`.
        t_from: start of the stationary regime; the save times ``t ≥ t_from`` are averaged with equal weights.

    Returns:
        a :class:`StationaryMoments` of the saved components that are not dependent coordinates.

    Examples:
        The ball's velocity variance ``νδ²/(4ε)`` (S0 (3.1)):

        >>> import nhsde
        >>> from nhsde import statistics
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0)
        >>> moments = statistics.normal_approximation(scene.build(), scene.initial_state(), t1=8.0, dt=0.5, order=3)
        >>> stationary = statistics.stationary_moments(moments, t_from=4.0)
        >>> stationary.names
        ('u_x', 'u_y')
        >>> print(stationary.cov.round(4))
        [[0.1276 0.    ]
         [0.     0.1276]]
    """
    names = tuple(n for n, r in zip(ens.names, ens.roles) if r != "dependent_coordinate")
    if not names:
        raise ValueError(f"only dependent coordinates were saved ({ens.names}); nothing is stationary.")
    w = (ens.ts >= t_from).astype(ens.ts.dtype)
    if int(jnp.sum(w)) < 1:
        raise ValueError(f"t_from={t_from} is after the last save time {float(ens.ts[-1])}.")
    mean, cov, _, _ = ens.select(names)
    w = w / jnp.sum(w)
    return StationaryMoments(jnp.einsum("n,ni->i", w, mean), jnp.einsum("n,nij->ij", w, cov), names)


class GreenKubo(eqx.Module):
    """Green–Kubo diffusion ``D = ∫₀^{τ_max} sym C(τ) dτ`` of the dependent coordinates from paths.

    ``autocorrelation[j] = C(τ_j) = E[Λ°(t+τ_j) Λ°(t)ᵀ]`` averaged over paths and
    time origins; ``diffusion_se`` is the Monte-Carlo standard error over paths.
    """

    lags: Float[Array, " n"]
    autocorrelation: Float[Array, "n k k"]
    diffusion: Float[Array, "k k"]
    diffusion_se: Float[Array, "k k"]
    names: tuple[str, ...] = eqx.field(static=True)


def green_kubo(system: StochasticSystem, ens: Ensemble, *, t_from: float, max_lag: float) -> GreenKubo:
    """Green–Kubo diffusion from the velocity autocorrelation of Monte-Carlo paths.

    ``ens`` must hold the whole state per path (``Save(paths=True)``); the
    velocities ``Λ = q̇''`` (the drift's ``q''`` rows) at the save times
    ``t ≥ t_from`` give ``C(τ)`` for lags up to ``max_lag`` (trapezoid rule).

    Arguments:
        system: the system ``ens`` was simulated from.
        ens: an :class:`~nhsde.Ensemble` with the whole state per path.
        t_from: start of the stationary window.
        max_lag: the largest lag ``τ_max`` (at least one save spacing, shorter than the window).

    Returns:
        a :class:`GreenKubo` with the autocorrelation, ``diffusion`` and its Monte-Carlo standard error.
    """
    if ens.paths is None or ens.failed is None or ens.names != system.layout.names:
        raise ValueError(
            f"green_kubo needs the whole state {system.layout.names} per path: simulate with Save(paths=True)."
        )
    dep = np.asarray(system.layout.indices("dependent_coordinate"), dtype=int)
    if dep.size == 0:
        raise ValueError(f"the state {system.layout.names} has no dependent coordinates.")
    ts = np.asarray(ens.ts)
    spacing = float(ts[1] - ts[0])
    window = np.flatnonzero(ts >= t_from - 1e-9 * spacing)
    n_lag = round(check_number("max_lag", max_lag, positive=True) / spacing)
    if n_lag < 1 or len(window) <= n_lag:
        raise ValueError(
            f"max_lag={max_lag}: need at least one save spacing ({spacing:g}) and a window t ≥ t_from={t_from} "
            f"longer than max_lag ({len(window)} save times); save more points or run longer."
        )
    ok = ~np.asarray(ens.failed)
    y = jnp.asarray(ens.paths)[ok][:, window]  # (p, n, d)
    params = system.params
    vel = jax.vmap(jax.vmap(lambda t, z: system.drift(t, z, params)[dep], in_axes=(0, 0)), in_axes=(None, 0))(
        jnp.asarray(ts[window], y.dtype), y
    )
    vel = vel - jnp.mean(vel, axis=0)
    n_origin = len(window) - n_lag

    def one_path(v):  # (lags, k, k): C_p(τ_j) averaged over time origins
        return (
            jax.vmap(lambda j: jnp.einsum("nk,nl->kl", jax.lax.dynamic_slice_in_dim(v, j, n_origin), v[:n_origin]))(
                jnp.arange(n_lag + 1)
            )
            / n_origin
        )

    per_path = jax.jit(jax.vmap(one_path))(vel)  # (p, lags, k, k)
    w = np.full(n_lag + 1, spacing)
    w[0] = w[-1] = spacing / 2
    d_path = jnp.einsum("j,pjkl->pkl", jnp.asarray(w, y.dtype), per_path)
    d_path = 0.5 * (d_path + jnp.swapaxes(d_path, 1, 2))
    n = d_path.shape[0]
    return GreenKubo(
        lags=jnp.asarray(spacing * np.arange(n_lag + 1), y.dtype),
        autocorrelation=jnp.mean(per_path, axis=0),
        diffusion=jnp.mean(d_path, axis=0),
        diffusion_se=jnp.std(d_path, axis=0, ddof=1) / math.sqrt(n),
        names=tuple(system.layout.names[i] for i in dep),
    )
