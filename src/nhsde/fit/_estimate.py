"""Estimate physical parameters from observed statistics, with optax.

The estimator is the minimum-distance (Gaussian quasi-likelihood) estimator of
the statistics ``s`` of :mod:`._observations`:

    θ̂ = argmin_θ  ½ (s_obs − s(θ))ᵀ Σ_obs⁻¹ (s_obs − s(θ)),

where ``s(θ)`` comes from a model: :class:`Simulated` (``nhsde.simulate`` with a
fixed key — common random numbers make ``s(θ)`` a smooth function, and the
simulator is differentiable in every parameter leaf), :class:`MomentEquations`
(the normal-approximation method) or :class:`ClosedForm` (closed forms).  Positive parameters are optimised as
``log(θ − lower)``, so the search never leaves their range.

Uncertainty: with ``G = ∂s/∂θ`` at ``θ̂`` and the Fisher information
``H = Gᵀ Σ_obs⁻¹ G`` of the Gaussian likelihood of ``s``,

    Cov(θ̂) = H⁻¹ + H⁻¹ Gᵀ Σ_obs⁻¹ Σ_model Σ_obs⁻¹ G H⁻¹,

the second term being the Monte-Carlo noise ``Σ_model`` of a simulated model
(about ``H⁻¹ n_obs/n_sim``; zero for moment equations and closed forms).  ``χ² = rᵀ(Σ_obs + Σ_model)⁻¹ r``
with ``S − p`` degrees of freedom tests whether the model fits at all.

A simulated ``G`` is itself a Monte-Carlo estimate (pathwise, same key), with
standard errors ``se(G)`` from :func:`~nhsde.statistics.moment_sensitivities`.
With ``W = L⁻¹`` (``Σ_obs = L Lᵀ``), the relative error of the information about
parameter ``a``,

    ρ_a = ‖W se(G)_a‖ / ‖W G_a‖        (columns ``a``),

is ``FitResult.jacobian_relative_se``; the formula for ``Cov(θ̂)`` ignores it, and
:func:`estimate` warns where ``ρ_a > 0.3`` (more model paths shrink it as ``1/√n_paths``).

A summary table (``Observations.from_statistics`` without ``covariance``) gives each statistic's
standard error but not the correlations between statistics at different times of the same paths, which
are strong (a coordinate accumulates); ``Σ_obs = diag(se²)`` then makes ``Cov(θ̂)`` too small.  So
:func:`estimate` fits with ``diag(se²)``, asks the model for the covariance ``Σ_m`` of the statistics of
as many paths at ``θ̂`` (``statistics_covariance``: a simulated model's own paths, a closed form's two-time
covariance through the Gaussian moments) and fits again from ``θ̂`` with ``Σ_obs = D R D`` — ``D`` the
data's standard errors, ``R`` the correlations of ``Σ_m`` (``FitResult.correlations = "model"``).  Where
the model gives none, it warns and multiplies ``Cov(θ̂)`` by ``max(1, χ²/dof)`` (``FitResult.inflation``),
which cannot repair positive correlations: ``χ²`` sees only the variances.
"""

from __future__ import annotations

import abc
import contextlib
import dataclasses
import functools
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from .._ensemble import Save
from .._misc import real_state
from .._options import Batching, FixedSteps, RunOptions
from .._params import checked_on_host
from .._simulate import simulate
from .._system import StochasticSystem
from ..statistics import moment_sensitivities, normal_approximation

if TYPE_CHECKING:
    import optax  # imported where a fit runs: a process that only simulates need not spend its import time

from ._observations import (
    Observations,
    gaussian_statistic_covariance,
    statistic_covariance,
    statistic_size,
    statistic_vector,
)

__all__ = ["AbstractStatisticsModel", "ClosedForm", "FitResult", "MomentEquations", "Simulated", "estimate"]

_MAX_JACOBIAN_RELATIVE_SE = 0.3
"""Above this relative Monte-Carlo error of a column of ``G = ∂s/∂θ``, :func:`estimate` warns."""


class AbstractStatisticsModel(eqx.Module):
    """Model means and covariances of named components at given times.

    ``exact_in_range``: the model's moments need no run-time check at parameters inside their ranges (no
    simulation whose step or outcome depends on them), so a fit, whose search stays inside the ranges, traces its
    programs without the parameters' host callbacks and they enter the persistent compilation cache.
    """

    exact_in_range: ClassVar[bool] = False

    @abc.abstractmethod
    def moments(self, system: StochasticSystem, ts: tuple[float, ...], names: tuple[str, ...]) -> tuple[Array, Array]:
        """``(mean (T, k), cov (T, k, k))``, differentiable in ``system.params``."""

    @abc.abstractmethod
    def noise_covariance(self, system: StochasticSystem, ts: tuple[float, ...], names: tuple[str, ...]) -> np.ndarray:
        """Covariance of the model's own statistic vector (its Monte-Carlo error)."""

    def jacobian_se(
        self, system: StochasticSystem, ts: tuple[float, ...], names: tuple[str, ...], vary: tuple[str, ...]
    ) -> np.ndarray:
        """Monte-Carlo standard errors ``(S, p)`` of ``∂s/∂θ`` (``s``: the statistic vector, ``θ``: ``vary``).

        Zero here: a model without Monte-Carlo noise has an exact Jacobian.
        """
        return np.zeros((statistic_size(len(ts), len(names)), len(vary)))

    def at_estimate(
        self, system: StochasticSystem, ts: tuple[float, ...], names: tuple[str, ...], vary: tuple[str, ...]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What a fit reports at its estimate, at ``system``'s parameters: the statistic vector ``s (S,)``, its
        Jacobian ``∂s/∂θ (S, p)`` in ``vary`` and the Jacobian's Monte-Carlo standard errors, and the covariance
        ``(S, S)`` of the model's own Monte-Carlo error.  Here ``s`` and ``∂s/∂θ`` come from one compiled forward-mode
        pass of :meth:`moments`."""
        value, jacobian = _value_and_jacobian(self, system, ts, names, vary)
        return (
            np.asarray(value, np.float64),
            np.asarray(jacobian, np.float64),
            np.asarray(self.jacobian_se(system, ts, names, vary), np.float64),
            np.asarray(self.noise_covariance(system, ts, names), np.float64),
        )

    def statistics_covariance(
        self, system: StochasticSystem, ts: tuple[float, ...], names: tuple[str, ...], n_paths: int
    ) -> np.ndarray | None:
        """The covariance ``Σ`` of the statistic vector of ``n_paths`` observed paths, as the model predicts it
        (correlations across times included), or ``None`` where the model cannot tell (here)."""
        return None

    def check_times(self, ts) -> None:
        """Refuse, before any run, observation times ``ts`` the model cannot give (here: none)."""


def check_step_budget(t0: float, t1: float, steps: FixedSteps, remedy: str) -> int:
    """The steps of ``steps.dt`` over ``(t0, t1)``; beyond the budget ``steps.max_steps`` refused by
    :class:`~nhsde._options.RunOptions`' rule, in its words, with ``remedy`` for its advice."""
    try:
        return RunOptions(t0=t0, t1=t1, steps=steps, solver="euler").n_steps
    except ValueError as e:
        reason, cut, _ = str(e).partition("; raise it with")
        raise ValueError(f"{reason}; {remedy}" if cut else str(e)) from None


def _save_grid(ts, t0: float, model: str) -> np.ndarray:
    """Indices ``j`` of the observation times ``ts = t0 + j·h`` on an equally spaced save grid."""
    ts = np.asarray(ts, np.float64)
    if len(ts) and ts[0] < t0:
        raise ValueError(
            f"{model}: t0={t0:g} is after the first observation time {ts[0]:g}; the model runs from t0 and gives "
            f"statistics at times ≥ t0: take t0 ≤ {ts[0]:g}."
        )
    h = ts[0] - t0 if len(ts) == 1 else ts[1] - ts[0]
    index = np.round((ts - t0) / h).astype(int) if h > 0 else None
    if index is None or np.any(np.abs(t0 + index * h - ts) > 1e-9 * max(1.0, abs(ts[-1]))):
        raise ValueError(f"{model}: observation times {ts.tolist()} are not on an equally spaced grid from t0={t0}.")
    return index


def _as_steps(steps):
    return steps if isinstance(steps, FixedSteps) else FixedSteps(steps)


class Simulated(AbstractStatisticsModel):
    """Statistics of ``n_paths`` paths of ``nhsde.simulate`` from ``y0`` with ``key``.

    The observation times must lie on an equally spaced grid ``t0 + j·h``; the
    run saves on that grid and the step must divide ``h``.  ``steps`` is a
    :class:`~nhsde.FixedSteps` (or a number: its ``dt``); ``solver`` and
    ``batching`` as in :func:`~nhsde.simulate`.  Use a key other than the
    data's: the model's Monte-Carlo noise then enters the reported errors.

    Arguments:
        y0: the initial state ``(d,)``.
        key: a JAX random key, not the data's.
        n_paths: paths per evaluation.
        steps: a :class:`~nhsde.FixedSteps` or its ``dt``.
        solver, batching: as in :func:`~nhsde.simulate`.
        t0: the start time.
    """

    y0: Array
    key: PRNGKeyArray
    n_paths: int = eqx.field(static=True)
    steps: FixedSteps = eqx.field(static=True, converter=_as_steps)
    solver: str | dfx.AbstractSolver = eqx.field(static=True, default="euler")
    batching: Batching | None = eqx.field(static=True, default=None)
    t0: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        real_state("y0", self.y0)

    def check_times(self, ts) -> None:
        """Observation times on the save grid from ``t0``, within the step budget ``steps.max_steps``."""
        _save_grid(ts, self.t0, "Simulated")
        check_step_budget(
            self.t0, float(ts[-1]), self.steps, "raise it with Simulated(steps=FixedSteps(dt, max_steps=…))."
        )

    def _options(self, ts, names, paths: bool) -> tuple[np.ndarray, dict[str, Any]]:
        """Indices of ``ts`` on the save grid and the keyword arguments of the run (``simulate``'s)."""
        index = _save_grid(ts, self.t0, "Simulated")
        options = dict(
            n_paths=self.n_paths,
            t0=self.t0,
            t1=float(ts[-1]),
            steps=self.steps,
            solver=self.solver,
            batching=self.batching,
            save=Save(names=names, n=int(index[-1]) + 1, paths=paths),
        )
        return index, options

    def _run(self, system, ts, names, paths):
        index, options = self._options(ts, names, paths)
        return simulate(system, self.y0, self.key, **options), index

    def sensitivities(self, system, ts, names, vary) -> tuple[np.ndarray, np.ndarray]:
        """``(∂s/∂θ, its standard errors)``, both ``(S, p)``, from the same paths as :meth:`moments`.

        :func:`~nhsde.statistics.moment_sensitivities` (per-path tangents, forward mode); its
        Jacobian equals ``jax.jacfwd`` of :meth:`moments`' statistic vector to rounding.
        """
        return self.at_estimate(system, ts, names, vary)[1:3]

    def jacobian_se(self, system, ts, names, vary):
        return self.sensitivities(system, ts, names, vary)[1]

    def at_estimate(self, system, ts, names, vary):
        """One run of :func:`~nhsde.statistics.moment_sensitivities` gives it all, from the same paths: ``s``,
        ``∂s/∂θ`` and its errors from the per-path tangents, the covariance of ``s`` from the per-path values."""
        index, options = self._options(ts, names, paths=True)
        sens = moment_sensitivities(system, self.y0, self.key, wrt=tuple(vary), **options)

        def columns(d_mean, d_cov):
            cols = [statistic_vector(d_mean[a][index], d_cov[a][index]) for a in range(len(vary))]
            return np.stack([np.asarray(c, np.float64) for c in cols], axis=-1)

        value = np.asarray(statistic_vector(sens.mean[index], sens.cov[index]), np.float64)
        paths = sens.ensemble.paths
        assert paths is not None  # moment_sensitivities keeps the paths
        noise = statistic_covariance(np.asarray(paths)[:, index])
        return value, columns(sens.d_mean, sens.d_cov), columns(sens.d_mean_se, sens.d_cov_se), noise

    def moments(self, system, ts, names):
        ens, index = self._run(system, ts, names, paths=False)
        return ens.mean[index], ens.cov[index]

    def noise_covariance(self, system, ts, names):
        ens, index = self._run(system, ts, names, paths=True)
        return statistic_covariance(np.asarray(ens.paths)[:, index])

    def statistics_covariance(self, system, ts, names, n_paths):
        """From the model's own paths: their statistics' covariance (influence functions), scaled from the
        model's paths to ``n_paths``."""
        ens, index = self._run(system, ts, names, paths=True)
        assert ens.paths is not None and ens.failed is not None
        good = ~np.asarray(ens.failed)
        return statistic_covariance(np.asarray(ens.paths)[good][:, index]) * (int(good.sum()) / n_paths)


class MomentEquations(AbstractStatisticsModel):
    """Statistics from the normal-approximation moment equations (S0 §6), exact for linear systems.

    ``nhsde.statistics.normal_approximation`` from ``y0`` (covariance ``cov0``,
    default 0) with Dopri8 steps ``dt``; no Monte-Carlo noise, but for a
    nonlinear system the Gaussian closure's bias enters the estimates — the
    ``chi2`` of the fit shows whether it matters at the data's precision.

    Arguments:
        y0: the initial mean ``(d,)``.
        cov0: the initial covariance (default 0).
        dt: the Dopri8 step (a linear autonomous system's moments are exact at any step).
        t0: the start time.
        order: Gauss–Hermite nodes per component.
        max_steps: the step budget (as :class:`~nhsde.FixedSteps`'): a longer span is refused before any run.
    """

    exact_in_range: ClassVar[bool] = True

    y0: Array
    cov0: Array | None = None
    dt: float = eqx.field(static=True, default=0.01)
    t0: float = eqx.field(static=True, default=0.0)
    order: int = eqx.field(static=True, default=5)
    max_steps: int = eqx.field(static=True, default=FixedSteps.max_steps)

    def __check_init__(self):
        real_state("y0", self.y0)
        if self.cov0 is not None:
            real_state("cov0", self.cov0)

    def check_times(self, ts) -> None:
        """Observation times on the save grid from ``t0``, within the step budget ``max_steps``."""
        _save_grid(ts, self.t0, "MomentEquations")
        steps = FixedSteps(self.dt, max_steps=self.max_steps)
        check_step_budget(self.t0, float(ts[-1]), steps, "raise it with MomentEquations(max_steps=…).")

    def moments(self, system, ts, names):
        self.check_times(ts)
        index = _save_grid(ts, self.t0, "MomentEquations")
        ens = normal_approximation(
            system,
            self.y0,
            self.cov0,
            t0=self.t0,
            t1=float(ts[-1]),
            dt=self.dt,
            save=Save(names=names, n=int(index[-1]) + 1),
            order=self.order,
        )
        return ens.mean[index], ens.cov[index]

    def noise_covariance(self, system, ts, names):
        return _no_noise(ts, names)


class ClosedForm(AbstractStatisticsModel):
    """Statistics from ``fn(params, ts) -> (mean (T, k), cov (T, k, k))``: closed forms, moment equations.

    ``fn`` must return the components in the order of the observed names.

    With ``cross(params, ts) -> (T, T, k, k)``, ``cross[a, b] = Cov(z(t_a), z(t_b))`` (the two-time
    covariance, e.g. :func:`~nhsde.scenes.ball_two_time_covariances`), the model also gives the covariance of
    the statistics of Gaussian paths (:func:`~nhsde.fit.gaussian_statistic_covariance`), which a fit to a
    summary without correlations uses.

    Arguments:
        fn: ``fn(params, ts) -> (mean (T, k), cov (T, k, k))``, differentiable in ``params``.
        cross: optional ``cross(params, ts) -> (T, T, k, k)``, the two-time covariance of Gaussian paths.
    """

    exact_in_range: ClassVar[bool] = True

    fn: Callable = eqx.field(static=True)
    cross: Callable | None = eqx.field(static=True, default=None)

    def moments(self, system, ts, names):
        mean, cov = self.fn(system.params, jnp.asarray(ts))
        t, k = len(ts), len(names)
        if jnp.shape(mean) != (t, k) or jnp.shape(cov) != (t, k, k):
            raise ValueError(
                f"ClosedForm: fn returned mean {jnp.shape(mean)} and cov {jnp.shape(cov)}; expected ({t}, {k}) "
                f"and ({t}, {k}, {k}) for {t} times and names {names}."
            )
        return mean, cov

    def noise_covariance(self, system, ts, names):
        return _no_noise(ts, names)

    def statistics_covariance(self, system, ts, names, n_paths):
        if self.cross is None:
            return None
        return gaussian_statistic_covariance(np.asarray(self.cross(system.params, jnp.asarray(ts))), n_paths)


def _no_noise(ts, names) -> np.ndarray:
    size = statistic_size(len(ts), len(names))
    return np.zeros((size, size))


class _Problem(eqx.Module):
    """One fit: the loss in the unconstrained variables ``φ`` (θ = lower + e^φ, or θ = φ)."""

    system: StochasticSystem
    model: AbstractStatisticsModel
    observed: Array  # the used statistics
    whiten: Array  # L⁻¹ with Σ_obs = L Lᵀ, of the used statistics
    ts: tuple[float, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    vary: tuple[str, ...] = eqx.field(static=True)
    lower: tuple[float | None, ...] = eqx.field(static=True)
    used: tuple[int, ...] = eqx.field(static=True)  # Observations.used: the statistics of nonzero variance

    def theta(self, phi):
        # |φ| ≤ 0.9·log(max float): θ − lower = e^φ stays finite and positive (normal) in the precision of φ
        bound = 0.9 * float(np.log(jnp.finfo(phi.dtype).max))
        return jnp.stack(
            [p if lo is None else lo + jnp.exp(jnp.clip(p, -bound, bound)) for p, lo in zip(phi, self.lower)]
        )

    def system_at(self, theta) -> StochasticSystem:
        params = self.system.params.replace(**{n: theta[i] for i, n in enumerate(self.vary)})
        return eqx.tree_at(lambda s: s.params, self.system, params)

    def statistics(self, theta):
        moments = self.model.moments(self.system_at(theta), self.ts, self.names)
        s = statistic_vector(*moments).astype(self.observed.dtype)
        return s if len(self.used) == s.shape[0] else s[np.asarray(self.used)]

    def loss(self, phi):
        r = self.whiten @ (self.statistics(self.theta(phi)) - self.observed)
        return 0.5 * jnp.sum(r**2)


FORWARD_MODE_UP_TO = 4
"""A fit of at most this many parameters takes its loss's gradient in forward mode."""


def _gradient_in_forward_mode(f):
    """``f(φ)`` whose reverse-mode gradient is computed in forward mode: one tangent per parameter, vmapped, the
    value computed once.  For a few parameters forward mode through a solve is one pass of the solver's step
    with a few tangents, where reverse mode stores the solve and runs it backwards; and its program is smaller
    to trace and compile (the moment-equations fit of the ball, 2 parameters: 10–15 % less wall time per process).
    """

    @jax.custom_vjp
    def g(phi):
        return f(phi)

    def forward(phi):
        values, slopes = jax.vmap(lambda v: jax.jvp(f, (phi,), (v,)))(jnp.eye(phi.shape[0], dtype=phi.dtype))
        return values[0], slopes

    g.defvjp(forward, lambda slopes, cotangent: (cotangent * slopes,))
    return g


@eqx.filter_jit
def _step(phi, state, problem: _Problem, optimizer, reuse: bool, forward_mode: bool):
    import optax

    loss = _gradient_in_forward_mode(problem.loss) if forward_mode else problem.loss
    if reuse:  # line-search optimizers keep the value and gradient at the accepted point
        value, grad = optax.value_and_grad_from_state(loss)(phi, state=state)
    else:
        value, grad = jax.value_and_grad(loss)(phi)
    with jax.numpy_dtype_promotion("standard"):  # optax's L-BFGS mixes int32 and int64 counters
        updates, state = optimizer.update(grad, state, phi, value=value, grad=grad, value_fn=loss)
    return optax.apply_updates(phi, updates), state, value, grad


@eqx.filter_jit
def _value_and_jacobian(model: AbstractStatisticsModel, system: StochasticSystem, ts, names, vary):
    """The statistic vector ``s`` of ``model`` and ``∂s/∂θ`` in the parameters ``vary``, in forward mode (a few
    parameters; every solver of ``simulate`` has it): one pass, the primal computed once."""

    def statistics(theta):
        params = system.params.replace(**{n: theta[i] for i, n in enumerate(vary)})
        return statistic_vector(*model.moments(eqx.tree_at(lambda x: x.params, system, params), ts, names))

    theta = jnp.stack([jnp.asarray(getattr(system.params, n)) for n in vary])
    values, columns = jax.vmap(lambda v: jax.jvp(statistics, (theta,), (v,)))(jnp.eye(len(vary), dtype=theta.dtype))
    return values[0], columns.T


@functools.cache
def _lbfgs():
    import optax

    return optax.lbfgs()


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Estimates ``values`` of the parameters ``names``, their covariance and the fit's diagnostics.

    ``history[i] = (loss, *values)`` at optimizer step ``i`` (of both fits where the model gave the
    correlations of a summary, which ``steps`` counts together); ``chi2`` with ``dof``
    degrees of freedom measures the misfit (``chi2 ≈ dof`` when the model fits).
    ``jacobian`` is ``G = ∂s/∂θ (S, p)`` at ``values``, ``jacobian_se`` its Monte-Carlo standard errors
    (zero for an exact model) and ``whitening`` ``W = L⁻¹`` with ``Σ_obs = L Lᵀ``;
    :attr:`jacobian_relative_se` combines them.  ``correlations`` says where the correlations of the
    observed statistics came from (``"paths"``, ``"given"``, ``"model"`` at the estimate, or ``"unknown"``),
    ``inflation`` the factor ``max(1, χ²/dof)`` the covariance was multiplied by where they are unknown, and ``note``
    what the fit left out (:attr:`Observations.note`: statistics of zero variance; "" where nothing).
    ``jacobian`` and ``whitening`` are over the statistics used (:attr:`Observations.used`).
    """

    names: tuple[str, ...]
    values: np.ndarray
    cov: np.ndarray
    init: np.ndarray
    chi2: float
    dof: int
    steps: int
    converged: bool
    history: np.ndarray
    jacobian: np.ndarray | None = None
    jacobian_se: np.ndarray | None = None
    whitening: np.ndarray | None = None
    correlations: str = "paths"
    inflation: float = 1.0
    note: str = ""

    @property
    def se(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def jacobian_relative_se(self) -> np.ndarray:
        """Per parameter ``‖W se(G)_a‖ / ‖W G_a‖``: the relative Monte-Carlo error of its information.

        Zero for an exact model; NaN where the errors are unknown.
        """
        if self.jacobian is None or self.jacobian_se is None or self.whitening is None:
            return np.full(len(self.names), np.nan)
        norm = functools.partial(np.linalg.norm, axis=0)
        return norm(self.whitening @ self.jacobian_se) / norm(self.whitening @ self.jacobian)

    @property
    def params(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, self.values)}

    def __str__(self):
        rel = self.jacobian_relative_se
        noisy = bool(np.any(rel > 0))  # a simulated model: show the Monte-Carlo error of ∂s/∂θ
        rows = [f"{'parameter':<12}{'estimate':>14}{'std. error':>14}{'start':>12}" + (f"{'MC err ∂s':>12}" * noisy)]
        rows += [
            f"{n:<12}{v:>14.6g}{s:>14.3g}{i:>12.4g}" + (f"{100 * r:>11.1f}%" * noisy)
            for n, v, s, i, r in zip(self.names, self.values, self.se, self.init, rel)
        ]
        rows.append(
            f"chi2 = {self.chi2:.2f} on {self.dof} degrees of freedom; {self.steps} optimizer steps"
            + ("" if self.converged else " (NOT converged)")
        )
        note = {
            "given": "the statistics' correlations across times: given with the data",
            "model": "the statistics' correlations across times: the model's at the estimate (the data gave "
            "standard errors only)",
            "unknown": f"the statistics' correlations across times are unknown: errors inflated by chi2/dof = "
            f"{self.inflation:.3g}, and still too small where the statistics are positively correlated",
        }.get(self.correlations)
        return "\n".join(rows + [n for n in (note, self.note) if n])


def _vary_bounds(params, vary):
    fields = {f.name: f for f in dataclasses.fields(params)}
    leaves = [n for n, f in fields.items() if "lower" in f.metadata]
    lower = []
    for name in vary:
        if name not in leaves:
            raise ValueError(f"vary: {name!r} is not a parameter of {type(params).__name__}; parameters: {leaves}.")
        lo = fields[name].metadata["lower"]
        lower.append(None if lo is None else float(lo))
    return tuple(lower)


def _cholesky(cov: np.ndarray) -> np.ndarray | None:
    """The lower Cholesky factor of ``cov``, or ``None`` where it is not (numerically) positive definite."""
    if not np.all(np.isfinite(cov)):
        return None
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None


def estimate(
    system: StochasticSystem,
    observed: Observations,
    model: AbstractStatisticsModel,
    *,
    vary: tuple[str, ...] = ("eps", "nu"),
    init: dict[str, float] | None = None,
    optimizer: optax.GradientTransformation | None = None,
    max_steps: int = 100,
    gtol: float = 1e-4,
    progress: Callable[[int, float, dict[str, float]], None] | None = None,
) -> FitResult:
    """Fit the parameters ``vary`` of ``system`` to ``observed`` statistics through ``model``.

    - ``init``: start values (default: the system's current values).
    - ``optimizer``: any optax transformation (default ``optax.lbfgs()`` with its
      zoom line search); it minimises the loss in ``log(θ − lower)``.  The loss's gradient is taken in
      forward mode (one tangent per parameter) for up to :data:`FORWARD_MODE_UP_TO` parameters, in reverse
      mode above.
    - stops when the gradient of the loss (a χ²/2) in ``φ = log(θ − lower)``
      falls below ``gtol`` in norm — a Newton step of at most about
      ``gtol·se(φ)`` standard errors — or after ``max_steps`` steps.

    Arguments:
        system: the SDE whose parameters are fitted (a scene's ``build()``); its values are the default start.
        observed: the data (:class:`Observations`).
        model: how the statistics are computed (:class:`Simulated`, :class:`MomentEquations`, :class:`ClosedForm`).
        vary: names of the parameters to fit.
        init: start values (default: the system's current values).
        optimizer: any optax transformation (default ``optax.lbfgs()``).
        max_steps: the most optimizer steps.
        gtol: the gradient norm at which the fit stops.
        progress: called on the host after each optimizer step as ``progress(step, loss, {name: value})``
            (the values at which the loss was evaluated); the command line prints these on a terminal.

    Returns:
        a :class:`FitResult`: ``values``, their covariance ``cov`` and ``se``, ``chi2`` on ``dof`` degrees of
        freedom, ``converged``, the ``history``, and the Jacobian ``∂s/∂θ`` with its Monte-Carlo errors
        (``jacobian``, ``jacobian_se``, ``jacobian_relative_se``).

    Warns:
        UserWarning: where the relative Monte-Carlo error of a column of ``∂s/∂θ`` exceeds
        0.3 (a :class:`Simulated` model with too few paths).

    Examples:
        ``ν`` from one measured variance ``k_xx(3) = 2.7 ± 0.11`` of the ball's position, S0 (3.1), through its
        closed form (:func:`~nhsde.scenes.ball_covariances`):

        >>> import nhsde
        >>> from nhsde import fit
        >>> def closed_form(p, ts):
        ...     k_xx = nhsde.scenes.ball_covariances(ts, p.eps, p.nu, p.delta)[0]
        ...     return 0.0 * ts[:, None], k_xx[:, None, None]
        >>> observed = fit.Observations.from_statistics([3.0], ("x",), [[0.0]], [[[2.7]]], [[0.05]], [[[0.11]]], 1000)
        >>> start = nhsde.scenes.BallOnVibratingPlane(eps=0.8, nu=0.4).build()
        >>> result = fit.estimate(start, observed, fit.ClosedForm(closed_form), vary=("nu",))
        >>> result.converged, result.dof
        (True, 1)
        >>> print(f"nu = {result.values[0]:.3f} ± {result.se[0]:.3f}")
        nu = 6.536 ± 0.266
    """
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if not isinstance(observed, Observations):
        raise TypeError(f"observed={type(observed).__name__}; expected nhsde.fit.Observations.")
    if not isinstance(model, AbstractStatisticsModel):
        raise TypeError(f"model={type(model).__name__}; expected nhsde.fit.Simulated, MomentEquations or ClosedForm.")
    vary = tuple(vary)
    if not vary or len(set(vary)) != len(vary):
        raise ValueError(f"vary={vary}; name each parameter to fit once.")
    lower = _vary_bounds(system.params, vary)
    system.observe(observed.names)  # checks the names
    init = {} if init is None else dict(init)
    unknown = sorted(set(init) - set(vary))
    if unknown:
        raise ValueError(f"init: {unknown} are not among vary={vary}.")
    theta0 = np.array([float(init[n] if n in init else getattr(system.params, n)) for n in vary])
    for name, value, lo in zip(vary, theta0, lower):
        if lo is not None and not value > lo:
            raise ValueError(
                f"init: {name}={value} must be > {lo} to start a fit (it is optimised as log({name} − {lo}))."
            )
    max_steps = int(max_steps)
    if max_steps < 1:
        raise ValueError(f"max_steps={max_steps}; must be ≥ 1.")
    model.check_times(observed.ts)  # before any run: the span and the step budget

    dtype = jnp.result_type(float)
    used = observed.used
    both = np.ix_(used, used)
    cov_obs = np.asarray(observed.covariance, np.float64)[both]
    observed_s = observed.statistics()[used]
    factor = _cholesky(cov_obs)
    if factor is None:
        raise ValueError(
            "observed: the covariance of the observed statistics is not positive definite (statistics that are "
            "linear combinations of others, or non-finite entries); leave out the dependent statistics."
        )
    whiten = np.linalg.inv(factor)
    problem = _Problem(
        system=system,
        model=model,
        observed=jnp.asarray(observed_s, dtype),
        whiten=jnp.asarray(whiten, dtype),
        ts=tuple(float(t) for t in observed.ts),
        names=observed.names,
        vary=vary,
        lower=lower,
        used=tuple(int(u) for u in used),
    )
    import optax

    given_optimizer = optimizer
    optimizer = _lbfgs() if optimizer is None else optax.with_extra_args_support(optimizer)
    phi = jnp.asarray([t if lo is None else np.log(t - lo) for t, lo in zip(theta0, lower)], dtype)
    # Strong dtypes: the state after a step has no weak types, and the step compiles once.
    state = jax.tree.map(lambda x: jnp.asarray(x, jnp.result_type(x)), optimizer.init(phi))
    reuse = optax.tree_utils.tree_get(state, "value") is not None
    forward_mode = len(vary) <= FORWARD_MODE_UP_TO
    history, converged, steps = [], False, 0
    # θ = lower + e^φ (clipped) is inside every range: an exact model's programs need none of the run-time checks
    in_range = checked_on_host if model.exact_in_range else contextlib.nullcontext
    for steps in range(1, max_steps + 1):
        with in_range():
            new_phi, state, value, grad = _step(phi, state, problem, optimizer, reuse, forward_mode)
        loss = float(np.asarray(value))
        history.append([loss, *np.asarray(problem.theta(phi))])
        if progress is not None:
            progress(steps, loss, {n: float(v) for n, v in zip(vary, history[-1][1:])})
        if not np.isfinite(loss) or not np.all(np.isfinite(np.asarray(grad))):  # the programs leave it to the host
            raise FloatingPointError(
                f"estimate: the loss is {loss} and its gradient {np.asarray(grad).tolist()} at "
                + ", ".join(f"{n}={float(v):.6g}" for n, v in zip(vary, history[-1][1:]))
                + "; the model's statistics are not finite there."
            )
        if float(jnp.linalg.norm(grad)) <= gtol:
            converged = True
            break
        phi = new_phi
    theta = problem.theta(phi)

    with in_range():
        value, g, g_se, cov_model = model.at_estimate(problem.system_at(theta), problem.ts, observed.names, vary)
    value, g, g_se, cov_model = value[used], g[used], g_se[used], cov_model[both]
    if not (np.all(np.isfinite(value)) and np.all(np.isfinite(g))):
        at = ", ".join(f"{n}={float(v):.6g}" for n, v in zip(vary, np.asarray(theta)))
        raise FloatingPointError(f"estimate: the model's statistics or their ∂s/∂θ are not finite at {at}.")
    w_g = np.linalg.solve(cov_obs, g)  # Σ_obs⁻¹ G
    fisher = g.T @ w_g
    if not np.all(np.isfinite(fisher)) or np.linalg.cond(fisher) > 1e12:
        raise ValueError(
            f"estimate: the observed statistics do not determine {vary} separately (the Fisher information "
            f"{fisher.tolist()} is singular); observe more times or components, or vary fewer parameters."
        )
    h_inv = np.linalg.inv(fisher)
    cov = h_inv + h_inv @ w_g.T @ cov_model @ w_g @ h_inv
    r = value - observed_s
    chi2 = float(r @ np.linalg.solve(cov_obs + cov_model, r))
    result = FitResult(
        names=vary,
        values=np.asarray(theta, np.float64),
        cov=0.5 * (cov + cov.T),
        init=theta0,
        chi2=chi2,
        dof=len(used) - len(vary),
        steps=steps,
        converged=converged,
        history=np.asarray(history),
        jacobian=g,
        jacobian_se=g_se,
        whitening=whiten,
        correlations=observed.correlations,
        note=observed.note,
    )
    if observed.correlations == "unknown":
        sigma = model.statistics_covariance(problem.system_at(theta), problem.ts, observed.names, observed.n_paths)
        why = f"the model ({type(model).__name__}) gives none"
        if sigma is not None and _cholesky(np.asarray(sigma, np.float64)[both]) is None:
            why = (
                f"the model's ({type(model).__name__}) correlations at the estimate are singular (a statistic it "
                "holds constant there, or fewer model paths than statistics), so they are not used"
            )
            sigma = None
        if sigma is not None:  # the model's correlations at θ̂, the data's own errors: fit again from θ̂
            again = observed.with_correlations(sigma, "model")
            refit = estimate(
                system,
                again,
                model,
                vary=vary,
                init=result.params,
                optimizer=given_optimizer,
                max_steps=max_steps,
                gtol=gtol,
                progress=progress,
            )
            history = np.concatenate([result.history, refit.history])  # both fits, in order
            return dataclasses.replace(refit, init=theta0, history=history, steps=result.steps + refit.steps)
        inflation = max(1.0, chi2 / result.dof) if result.dof > 0 else 1.0
        warnings.warn(
            f"estimate: the observed statistics are a summary without correlations across times, and {why}; the "
            "errors assume independent statistics, inflated by "
            f"chi2/dof = {inflation:.3g}, and are too small where the statistics are positively correlated (a "
            "coordinate at several times): fit the paths, pass from_statistics(covariance=...), or use a model that "
            "gives them (Simulated, ClosedForm(cross=...)).",
            UserWarning,
            stacklevel=2,
        )
        result = dataclasses.replace(result, cov=result.cov * inflation, inflation=inflation)
    for name, rel in zip(vary, result.jacobian_relative_se):
        if rel > _MAX_JACOBIAN_RELATIVE_SE:
            warnings.warn(
                f"estimate: the relative Monte-Carlo error of ∂s/∂{name} is {rel:.2f} (> {_MAX_JACOBIAN_RELATIVE_SE}), "
                f"so the information about {name} and its standard error are unreliable; "
                "use more n_paths in the model.",
                UserWarning,
                stacklevel=2,
            )
    return result
