"""Derivatives of Monte-Carlo moments in physical parameters, with their Monte-Carlo standard errors.

Pathwise (forward-mode) estimator.  With ``x_i`` the saved values of path ``i``
and ``t_i = ∂x_i/∂θ`` their tangent (``jax.jacfwd`` of the per-path values, the
noise held fixed: paths are drawn by the counter-based driver), over the ``N``
paths that did not fail,

    m = (1/N) Σ x_i,            ∂m = (1/N) Σ t_i,
    K = 1/(N−1) Σ F_i F_iᵀ,     ∂K = 1/(N−1) Σ (t_i F_iᵀ + F_i t_iᵀ),      F_i = x_i − m,

where the tangent of the centring mean drops out because ``Σ F_i = 0``.  These
are exactly ``jax.jacfwd`` of ``simulate(...).mean`` and ``.cov`` for the same key
(the pathwise derivative estimator, Glasserman, *Monte Carlo Methods in Financial
Engineering*, 2004, §7.2).

Standard errors (delta method, van der Vaart, *Asymptotic Statistics*, 1998, §3).  ``∂m`` is a mean of i.i.d. terms:
``se(∂m) = std(t_i)/√N``.  ``∂K`` is a smooth function of the means of ``t xᵀ``,
``t`` and ``x``; linearising about their expectations gives the influence terms

    ψ_i = (t_i − ∂m) F_iᵀ + F_i (t_i − ∂m)ᵀ,        ∂K = 1/(N−1) Σ ψ_i,
    se(∂K) = N/(N−1) · std(ψ_i)/√N.

The tangent is centred in ``ψ``: the error of the centring mean ``m`` enters
``∂K`` at first order through ``E t`` (``−E[t](m − E x)ᵀ`` and its transpose),
unlike in ``K`` itself, where ``E F = 0`` makes it second order.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Sequence
from typing import Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._ensemble import (
    AbstractMoments,
    Ensemble,
    Save,
    check_result,
    covariance_variance,
    failure_result,
    scale_cause,
)
from .._interrupt import watching
from .._misc import is_concrete, under_trace
from .._options import AbstractSteps, Batching, RunOptions, run_options
from .._params import AbstractParameters, checked_on_host
from .._simulate import check_on_host, simulate_run
from .._system import StochasticSystem

__all__ = ["Sensitivities", "moment_sensitivities"]


class Sensitivities(AbstractMoments):
    """Moments of saved quantities at ``ts`` and their derivatives in the parameters ``wrt``, with standard errors.

    ``mean (n, k)``, ``cov (n, k, k)`` and their errors are those of :func:`~nhsde.simulate` over the paths
    used; ``d_mean[a] (n, k)`` and ``d_cov[a] (n, k, k)`` are their derivatives in parameter ``wrt[a]``
    (leading axis: the parameters), ``d_mean_se``, ``d_cov_se`` their Monte-Carlo standard errors.
    ``failed[p]`` marks path ``p`` left out (a failed solve, or a non-finite tangent), ``n_failed`` counts them.
    ``ensemble`` is the :func:`~nhsde.simulate` result of the same paths (its moment sums, for storage; paths
    whose values are finite but tangents are not are still in its statistics).
    """

    ts: Float[Array, " n"]
    mean: Float[Array, "n k"]
    cov: Float[Array, "n k k"]
    mean_se: Float[Array, "n k"]
    cov_se: Float[Array, "n k k"]
    d_mean: Float[Array, "p n k"]
    d_cov: Float[Array, "p n k k"]
    d_mean_se: Float[Array, "p n k"]
    d_cov_se: Float[Array, "p n k k"]
    n_used: Int[Array, ""]
    n_failed: Int[Array, ""]
    failed: Bool[Array, " paths"]
    ensemble: Ensemble
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    wrt: tuple[str, ...] = eqx.field(static=True)

    def standard_errors(self):
        return self.mean_se, self.cov_se

    def derivative(self, name: str):
        """``(d_mean, d_cov, d_mean_se, d_cov_se)`` in the parameter ``name`` (one of ``wrt``)."""
        if name not in self.wrt:
            raise ValueError(f"name={name!r} is not a differentiated parameter; wrt={self.wrt}.")
        a = self.wrt.index(name)
        return self.d_mean[a], self.d_cov[a], self.d_mean_se[a], self.d_cov_se[a]


def _sqrt(v):
    pos = v > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, v, 1.0)), 0.0)


def check_wrt(system: StochasticSystem, wrt) -> tuple[str, ...]:
    """``wrt`` as a tuple of distinct scalar float parameter names of ``system``; else raises naming it."""
    if isinstance(wrt, str):
        wrt = (wrt,)
    if not isinstance(wrt, Sequence) or not wrt or not all(isinstance(w, str) for w in wrt):
        raise TypeError(f"wrt={wrt!r}; expected a non-empty tuple of parameter names, e.g. ('eps', 'nu').")
    wrt = tuple(wrt)
    if len(set(wrt)) != len(wrt):
        raise ValueError(f"wrt={wrt!r} names a parameter twice.")
    params = system.params
    if not isinstance(params, AbstractParameters):
        raise TypeError(
            f"system.params is a {type(params).__name__}; wrt names leaves of an nhsde AbstractParameters module."
        )
    allowed = tuple(row[0] for row in params.describe())
    for name in wrt:
        if name not in allowed:
            raise ValueError(f"wrt={wrt!r}: {name!r} is not a parameter of this system; parameters: {allowed}.")
        value = getattr(params, name)
        dtype = getattr(value, "dtype", None)
        if np.ndim(value) != 0 or dtype is None or not jnp.issubdtype(dtype, jnp.floating):
            raise ValueError(
                f"wrt={wrt!r}: parameter {name}={value!r} is not one floating-point number; "
                "moment_sensitivities differentiates scalar float parameter leaves."
            )
    return wrt


def _statistics(paths, tangents, simulation_failed):
    """Moments, their derivatives and all standard errors over the paths whose values and tangents are finite."""
    work = np.promote_types(paths.dtype, jnp.result_type(float))  # float64 sums where enabled
    x = paths.astype(work)  # (N, n, k)
    t = jnp.stack(tangents).astype(work)  # (p, N, n, k)
    failed = simulation_failed | ~jnp.all(jnp.isfinite(t), axis=(0, 2, 3))
    ok = ~failed
    count = jnp.sum(ok, dtype=jnp.int32)
    n = count.astype(work)

    # moments of the values over the paths used (MomentSums' conventions, centred exactly)
    x = jnp.where(ok[:, None, None], x, 0.0)
    mean = jnp.sum(x, axis=0) / n
    f = jnp.where(ok[:, None, None], x - mean, 0.0)
    cov = jnp.einsum("pni,pnj->nij", f, f) / (n - 1)
    mean_se = _sqrt(jnp.diagonal(cov, axis1=1, axis2=2) / n)
    fourth = jnp.einsum("pni,pnj->nij", f * f, f * f) / n
    cov_se = _sqrt(covariance_variance(cov, fourth, n))

    # derivatives: means of the tangents and of the influence terms ψ (never materialised: (p, N, n, k, k))
    t = jnp.where(ok[None, :, None, None], t, 0.0)
    d_mean = jnp.sum(t, axis=1) / n
    tc = jnp.where(ok[None, :, None, None], t - d_mean[:, None], 0.0)
    d_mean_se = _sqrt(jnp.sum(tc**2, axis=1) / (n - 1) / n)
    tf = jnp.einsum("apni,pnj->anij", tc, f)
    psi_sum = tf + jnp.swapaxes(tf, -1, -2)  # Σ_i ψ_i
    d_cov = psi_sum / (n - 1)
    # Σ ψ_ij² = Σ tc_i² f_j² + f_i² tc_j² + 2 (tc_i f_i)(tc_j f_j)
    a = jnp.einsum("apni,pnj->anij", tc**2, f * f)
    b = jnp.einsum("apni,apnj->anij", tc * f, tc * f)
    psi_sq = a + jnp.swapaxes(a, -1, -2) + 2 * b
    psi_var = (psi_sq - psi_sum**2 / n) / (n - 1)
    d_cov_se = n / (n - 1) * _sqrt(psi_var / n)
    moments = (mean, cov, mean_se, cov_se)
    return moments, (d_mean, d_cov, d_mean_se, d_cov_se), count, jnp.sum(failed, dtype=jnp.int32), failed


@eqx.filter_jit
def _sensitivities(system: StochasticSystem, wrt: tuple[str, ...], values, y0, key, run: RunOptions, options: dict):
    """Per-path values and their tangents in ``wrt`` (forward mode), reduced by :func:`_statistics`; one program."""

    def per_path(*theta):
        system_theta = system.replace_params(**dict(zip(wrt, theta, strict=True)))
        # failures are decided by the caller, non-finite tangents included
        ens = simulate_run(system_theta, y0, key, run, on_failure="exclude", **options)
        return ens.paths, ens

    tangents, ens = jax.jacfwd(per_path, argnums=tuple(range(len(wrt))), has_aux=True)(*values)
    assert ens.paths is not None and ens.failed is not None  # Save(paths=True)
    moments, d_moments, count, n_failed, failed = _statistics(ens.paths, tangents, ens.failed)
    # simulate's moments (checked by simulate itself unless in `checked_on_host`), these and their derivatives
    statistics = (ens.mean, ens.cov, ens.mean_se, ens.cov_se, *moments, *d_moments)
    overflow = ~jnp.all(jnp.stack([jnp.all(jnp.isfinite(m)) for m in statistics]))
    return ens, moments, d_moments, count, n_failed, failed, overflow


def _step_checked_here(system: StochasticSystem, y0, values, run: RunOptions) -> float | None:
    """``run``'s step, where the run's checks can be made on the host, else ``None``.

    On the host: a plain call (nothing traced) in which no differentiated parameter is 0 (√ν's derivative is finite
    there).  Its checks are then made by the caller before the run, and the run is traced in
    :func:`~nhsde._params.checked_on_host`: no host callback in the program, which enters JAX's persistent
    compilation cache.
    """
    if under_trace() or not is_concrete(system.params, values, y0):
        return None  # traced: the checks stay in the program (`eqx.error_if`), with the same messages
    if not all(bool(np.all(np.asarray(v) != 0)) for v in values):
        return None  # a derivative at ν = 0 is singular: the program's check raises it
    return float(run.steps.dt)


def moment_sensitivities(
    system: StochasticSystem,
    y0,
    key,
    *,
    wrt: Sequence[str],
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
    first_path: int = 0,
    progress_meter: dfx.AbstractProgressMeter | None = None,
) -> Sensitivities:
    """Means and covariances of :func:`~nhsde.simulate` and their derivatives in the parameters ``wrt``,
    each with its Monte-Carlo standard error (pathwise forward-mode estimator; formulas in the module).

    ``d_mean``, ``d_cov`` equal ``jax.jacfwd`` of ``simulate(system.replace_params(...), ...).mean`` and
    ``.cov`` in those parameters for the same key (to rounding).

    Arguments:
        system, y0, key, n_paths, t0, t1, dt, solver, steps, batching, run, first_path, progress_meter: as for
            :func:`~nhsde.simulate`.
        wrt: names of scalar parameter leaves of ``system.params`` (``('eps', 'nu')``); the derivatives
            are stacked in this order along the leading axis.
        save: which quantities at how many times (:class:`~nhsde.Save`); per-path values are kept
            internally whatever ``save.paths``.
        on_failure: ``'raise'`` raises :class:`~nhsde.SimulationError` if any path fails or has a
            non-finite tangent; ``'exclude'`` leaves such paths out of every statistic and derivative
            alike and marks them in ``failed``.

    Memory: the per-path values and tangents, ``n_paths × n × k × (1 + len(wrt))`` numbers, on top of
    ``simulate``'s chunk; split a very large run into pieces with ``first_path`` and other keys.
    """
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if on_failure not in ("raise", "exclude"):
        raise ValueError(f"on_failure={on_failure!r}; allowed: 'raise', 'exclude'.")
    wrt = check_wrt(system, wrt)
    run = run_options(
        "moment_sensitivities",
        run,
        t0=t0,
        t1=t1,
        dt=dt,
        steps=steps,
        solver=solver,
        save=save,
        batching=batching,
        adaptive=True,
    )
    save = Save() if run.save is None else run.save
    run = dataclasses.replace(run, save=Save(names=save.names, n=save.n, paths=True, about=save.about))
    values = tuple(jnp.asarray(getattr(system.params, name)) for name in wrt)
    options = dict(n_paths=n_paths, first_path=first_path, progress_meter=progress_meter)
    step = _step_checked_here(system, y0, values, run)
    if step is not None:
        # simulate's checks, made now on the concrete parameters (its run, traced with them as tangents, cannot):
        # y0, the ranges in the state's precision and the step's stability (its plain call's messages and warning);
        # too few paths and overflow are checked below, from the run's counts and statistics
        y0 = check_on_host(system, y0, n_paths=n_paths, solver=run.solver, dt=step)
    with watching():  # Ctrl-C stops the compiled run
        with checked_on_host() if step is not None else contextlib.nullcontext():
            out = _sensitivities(system, wrt, values, y0, key, run, options)
        if not under_trace():
            jax.block_until_ready(out)
    ens, moments, d_moments, count, n_failed, failed, overflow = out
    result = failure_result(
        unstable=False, n_failed=n_failed, n_used=count, raise_on_failure=on_failure == "raise", overflow=overflow
    )
    details = ""
    if is_concrete(n_failed) and int(n_failed) > 0:
        details = f"{int(n_failed)} of {n_paths} paths failed (or their tangents were not finite): "
    scale = scale_cause(system.params, y0) if details else ""
    moments, d_moments = check_result((moments, d_moments), result, "moment_sensitivities", details, scale)
    mean, cov, mean_se, cov_se = moments
    d_mean, d_cov, d_mean_se, d_cov_se = d_moments
    return Sensitivities(
        ts=ens.ts,
        mean=mean,
        cov=cov,
        mean_se=mean_se,
        cov_se=cov_se,
        d_mean=d_mean,
        d_cov=d_cov,
        d_mean_se=d_mean_se,
        d_cov_se=d_cov_se,
        n_used=count,
        n_failed=n_failed,
        failed=failed,
        ensemble=ens,
        names=ens.names,
        roles=ens.roles,
        wrt=wrt,
    )
