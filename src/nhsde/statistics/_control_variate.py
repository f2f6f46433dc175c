"""Control variates from the linearised system: the same paths, a control with exact moments.

The control is the system linearised about a reference motion ``p(t)`` and
driven by the same increments (same key, solver and steps; the counter-based
driver gives two systems with one ``noise_dim`` the same Brownian path):

    dC = [a(p) + ∂a/∂Z(p) (C − p)] dt + b(p) dW,   C(t0) = Z(t0),

with ``p`` the noiseless motion ``ṗ = a(p)``, ``p(t0) = y0`` (``linearisation="mean"``,
the mean motion to first order in the noise) or a fixed state (a steady motion).
``C`` is Gaussian; its mean and covariance solve the linear moment (Lyapunov)
equations ``ṁ = a(p) + ∂a(p)(m − p)``, ``K̇ = ∂a(p) K + K ∂a(p)ᵀ + b(p) diag(ν) b(p)ᵀ``
(S0 §6, exact for a linear system), integrated by the library's moment equations
(fixed Dopri8 steps on the pair ``(p, C)``).  A saved observable ``f`` is
controlled by its second-order Taylor polynomial about ``p``,
``f_C = f(p) + gᵀu + ½uᵀHu`` with ``u = C − p`` (``f_C = C_i`` for a state
component, ``f_C = f(C)`` for a quadratic ``f`` such as an energy), whose moments
are exact for Gaussian ``u ~ N(μ, K)``:

    E f_C = f(p) + gᵀμ + ½μᵀHμ + ½ tr(HK),
    Cov(f_C, h_C) = G_fᵀ K G_h + ½ tr(H_f K H_h K),   G = g + Hμ

(Isserlis).  Drivers with centred jumps (S0 (1.3)) enter the moment equations
through their intensity ``ν`` (S0 (1.4)) and the same jumps drive both solves,
but ``C`` is then not Gaussian: only state components may be saved.

Every saved mean and covariance entry ``Y`` (per-path value, or centred
product for a covariance) gets its own coefficient
``β = Cov(Y, C)/Var(C)`` estimated from the same paths, and

    Ŷ_cv = Ŷ − β (Ĉ − E C),   SE² = Var(Y − βC)/N

(Glasserman, *Monte Carlo Methods in Financial Engineering*, 2004, §4.1);
variances and cross-covariances of the per-path influences are those of
:func:`paired_moments` (polarisation of ``Y``, ``C`` and ``Y + C``), so the
conventions are the library's.  ``variance_reduction = Var Y / Var(Y − βC)``.

Bias.  The exact moments are those of the continuous linear SDE, while ``C`` is
simulated by the same discrete scheme as ``Z``: the estimate has bias
``bias(Y) − β·bias(C)`` (plus the ``O(1/N)`` bias of an estimated β).  Where
``Z`` is close to ``C`` (β ≈ 1) the discretisation bias of the linear part is
removed with the variance; for a linear system ``Z ≡ C`` path by path, β = 1 and
the estimate is the exact continuous value up to rounding.

Derivatives.  ``β`` is held fixed under differentiation (``jax.lax.stop_gradient``):
then ``∂Ŷ_cv = ∂Ŷ − β(∂Ĉ − ∂E C)`` is itself a control-variate estimate of the
pathwise derivative (controlled by the tangent of ``C``, whose mean ``∂E C`` is
exact), with the same bias structure as above; no derivative is taken of a ratio
of sample covariances (noisy, and 0/0 where the control has no variance, e.g. at
``t0``).  Differentiating β too would only add ``∂β·(Ĉ − E C)``, a term of mean
zero up to the scheme's bias: more noise, no less bias.  With ``wrt`` the result
carries these derivatives with their standard errors, from the per-path tangents
``T_Y``, ``T_C`` of both solves (forward mode) and ``∂E C`` of the moment equations:

    ∂Ŷ_cv = mean(T_Y − β T_C) + β ∂E C,   SE² = Var(T_Y − β T_C)/N

for a mean, and the same with the influences ``ψ`` of :func:`paired_sensitivities`
for a covariance (weights ``1, −β``; ``∂E C`` is exact and adds no error).

Cost: two solves of ``n_paths`` paths (``cost = 2·n_paths·steps`` path-steps);
a control step also costs one Jacobian-vector product of the drift.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._ensemble import Save
from .._misc import cast_floats, check_key
from .._options import AbstractSteps, Batching, RunOptions, run_options
from .._params import validated
from .._solvers import solver_needs
from .._system import StateLayout, StochasticSystem
from ..noise import driver_intensity
from ._cost import check_memory, path_bytes, peak_bytes
from ._estimate import AbstractEstimate, AbstractStatistic, Cost, Derivatives, MonteCarloEstimate, Stopwatch, Values
from ._moments import GaussianClosure, integrate_moments
from ._paths import (
    array_module,
    checked_paths,
    on_device,
    paired_moments,
    paired_sensitivities,
    paths_save,
    roles_of,
    safe_sqrt,
    solve_paths_with_tangents,
    with_tangents,
)
from ._sensitivities import check_wrt

__all__ = ["ControlVariateEstimate", "PerEntry", "control_variate", "linearised_system"]

_REFERENCE = "@reference"
_ODE_STEPS = 256  # fewest Dopri8 steps of the moment equations (and ≥ 4 per SDE step)


class PerEntry(eqx.Module):
    """A number per saved mean ``(n, k)`` and per covariance entry ``(n, k, k)``."""

    mean: Float[Values, "n k"]
    cov: Float[Values, "n k k"]


class ControlVariateEstimate(AbstractEstimate):
    """Control-variate means and covariances (module docstring) with their standard errors, and

    - ``plain``: the uncorrected estimate of the same paths (its ``cost``: one solve's path-steps);
    - ``coefficient``: β per entry; ``variance_reduction``: ``Var Y / Var(Y − βC)`` per entry
      (``inf`` where the residual has no variance, 1 where neither has any);
    - ``control``: the exact mean and covariance of the control's saved quantities;
    - ``cost``: path-steps of both solves, ``2·n_paths·steps``;
    - ``derivatives``: with ``wrt``, those of ``mean`` and ``cov`` with β fixed, with their standard errors (module).
    """

    ts: Float[Values, " n"]
    mean: Float[Values, "n k"]
    cov: Float[Values, "n k k"]
    mean_se: Float[Values, "n k"]
    cov_se: Float[Values, "n k k"]
    n_paths: Int[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    plain: MonteCarloEstimate
    coefficient: PerEntry
    variance_reduction: PerEntry
    control: PerEntry
    derivatives: Derivatives | None
    cost: Cost = eqx.field(static=True)
    statistic: AbstractStatistic | None = eqx.field(static=True)


# ----------------------------------------------------------------------------- the control system


class _LinearisedDrift(eqx.Module):
    """Drift of ``(p, C)``: ``ṗ = a(p)`` (or 0 for a fixed reference), ``a(p) + ∂a(p)(C − p)`` (one jvp)."""

    drift: Callable = eqx.field(static=True)
    follow: bool = eqx.field(static=True)

    def __call__(self, t, y, params):
        d = y.shape[0] // 2
        p, c = y[:d], y[d:]
        a, lin = jax.jvp(lambda z: self.drift(t, z, params), (p,), (c - p,))
        return jnp.concatenate([a if self.follow else jnp.zeros_like(a), a + lin])


class _FrozenDiffusion(eqx.Module):
    """Diffusion of ``(p, C)``: none on ``p``, ``b(p)`` on ``C``."""

    diffusion: Callable = eqx.field(static=True)

    def __call__(self, t, y, params):
        d = y.shape[0] // 2
        b = self.diffusion(t, y[:d], params)
        return jnp.concatenate([jnp.zeros_like(b), b])


class _BlockLinear(eqx.Module):
    """The declared linear drift ``A`` of ``(p, C)``: ``diag(A, A)`` (``diag(0, A)`` for a fixed reference)."""

    linear: Callable = eqx.field(static=True)
    follow: bool = eqx.field(static=True)

    def __call__(self, params):
        a = self.linear(params)
        z = jnp.zeros_like(a)
        return jnp.block([[a if self.follow else z, z], [z, a]])


class _Taylor2(eqx.Module):
    """``f(p) + gᵀu + ½uᵀHu``, ``u = C − p``: the control of the observable ``f`` on the state ``(p, C)``."""

    fn: Callable = eqx.field(static=True)

    def __call__(self, t, y, params):
        d = y.shape[0] // 2
        p, u = y[:d], y[d:] - y[:d]
        f = lambda z: self.fn(t, z, params)
        g, hu = jax.jvp(jax.grad(f), (p,), (u,))
        return f(p) + jnp.dot(g, u) + 0.5 * jnp.dot(u, hu)


def linearised_system(system: StochasticSystem, *, follow: bool = True) -> StochasticSystem:
    """The control system on the state ``(p, C)`` (names ``'<name>@reference'``, then the original names).

    ``C`` is ``system`` (in Itô form) linearised about ``p``; ``p`` follows the
    noiseless flow (``follow=True``) or stays where it starts.  Same driver,
    ``noise_dim`` and parameters as ``system``; its observables are the
    second-order Taylor polynomials of ``system``'s about ``p``.
    """
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    ito = system.converted("ito")
    layout = StateLayout(
        tuple(n + _REFERENCE for n in ito.layout.names) + ito.layout.names,
        ito.layout.roles + ito.layout.roles,
        tuple(n + _REFERENCE for n in ito.layout.angles) + ito.layout.angles,
    )
    linear = None if ito.linear_drift is None else _BlockLinear(ito.linear_drift, follow)
    return StochasticSystem(
        drift_fn=_LinearisedDrift(ito.drift_fn, follow),
        diffusion_fn=_FrozenDiffusion(ito.diffusion_fn),
        params=ito.params,
        layout=layout,
        noise_dim=ito.noise_dim,
        interpretation="ito",
        additive_noise=ito.additive_noise,
        observables=tuple((name, _Taylor2(fn)) for name, fn in ito.observables),
        noise=ito.noise,
        linear_drift=linear,
    )


# ----------------------------------------------------------------------------- exact moments of the control


def _control_moments(system: StochasticSystem, params, names, ts, p, m, k):
    """Exact ``(mean (n, k), cov (n, k, k))`` of the saved quantities' controls, from the Gaussian ``C ~ N(m, K)``
    and the Taylor point ``p`` at each time (module: Isserlis)."""
    observe = system.observe(names)

    def at(t, p, m, k):
        f = lambda z: observe(t, z, params)
        value, grad, hess = f(p), jax.jacfwd(f)(p), jax.hessian(f)(p)  # (q,), (q, d), (q, d, d)
        mu = m - p
        mean = value + grad @ mu + 0.5 * jnp.einsum("i,qij,j->q", mu, hess, mu) + 0.5 * jnp.einsum("qij,ji->q", hess, k)
        g = grad + hess @ mu
        hk = hess @ k  # (q, d, d)
        cov = g @ k @ g.T + 0.5 * jnp.einsum("aij,bji->ab", hk, hk)
        return mean, cov

    return jax.vmap(at)(ts, p, m, k)


# ----------------------------------------------------------------------------- the estimator


def _split(var_y, var_c, var_sum):
    """``(β, residual variance, reduction)`` from the variances of ``Y``, ``C`` and ``Y + C`` (polarisation).

    Where the control has no variance (no noise, ``ν = 0``, or ``t0``) β is its limit as the noise vanishes, 1: the
    fluctuations of ``Y`` and ``C`` agree to first order in the noise (module), and ``Ŷ − (Ĉ − E C)`` keeps the
    estimate continuous there (the noiseless motion's value, without the scheme's bias of the linear part)."""
    xp = array_module(var_y, var_c, var_sum)
    stop = jax.lax.stop_gradient if xp is jnp else (lambda x: x)
    cross = 0.5 * (var_sum - var_y - var_c)
    ok = var_c > 0
    beta = stop(xp.where(ok, cross / xp.where(ok, var_c, 1.0), 1.0))
    resid = xp.maximum(var_y - 2 * beta * cross + beta**2 * var_c, 0.0)
    vy, vr = stop(var_y), stop(resid)
    reduction = xp.where(vr > 0, vy / xp.where(vr > 0, vr, 1.0), xp.where(vy > 0, xp.inf, 1.0))
    return beta, resid, reduction


def _closure(control: StochasticSystem, dtype) -> GaussianClosure:
    """The moment equations of the control (library's :class:`GaussianClosure`), evaluated at the mean.

    ``p`` has no variance and ``C`` enters the drift linearly with ``b`` independent of ``C``, so expectations
    under ``N(m, K)`` are values at ``m``: no cubature nodes are needed and the equations are exact.
    """
    params = cast_floats(validated(control.params), dtype)
    system = eqx.tree_at(lambda s: s.params, control, params)
    intensity = driver_intensity(control.noise, control.noise_dim, dtype)
    return GaussianClosure(
        system, intensity, (), jax.device_put(np.zeros((1, 0), dtype)), jax.device_put(np.ones((1,), dtype))
    )


@eqx.filter_jit
def _exact(closure, ito, params, names, p0, y0, t0, t1, n_ode, n_save):
    """``(ts, mean, cov)``: the exact moments of the saved quantities' controls at the save times."""
    d = y0.shape[0]
    zeros = jnp.zeros((2 * d, 2 * d), y0.dtype)
    ts, ms, ks = integrate_moments(closure, jnp.concatenate([p0, y0]), zeros, t0, t1, n_ode, n_save)
    return ts, *_control_moments(ito, params, names, ts, ms[:, :d], ms[:, d:], ks[:, d:, d:])


def fitted_controls(ys: list, cs: list, weights: list):
    """Moments of the combination ``Σ_a w_a Y_a`` of the system's per-path sets (:func:`paired_moments`) and of the
    same combination of its controls' sets, and per mean and covariance entry ``(β, residual variance,
    reduction)`` (on the host for concrete paths: ``array_module``)."""
    plain = paired_moments(ys, weights)
    mean_c, cov_c, mvar_c, cvar_c = paired_moments(cs, weights)
    _, _, mvar_s, cvar_s = paired_moments([*ys, *cs], [*weights, *weights])
    split_m, split_c = _split(plain[2], mvar_c, mvar_s), _split(plain[3], cvar_c, cvar_s)
    beta, resid, reduction = zip(split_m, split_c, strict=True)
    return plain, (mean_c, cov_c), beta, resid, reduction


def _reference(system, y0, linearisation, argument: str):
    """``(follow, p0)``: the reference motion's kind and start (``linearisation`` passed as ``argument``)."""
    if isinstance(linearisation, str) or linearisation is None:
        if linearisation not in (None, "mean"):
            raise ValueError(
                f"{argument}={linearisation!r}; allowed: 'mean' (the noiseless motion from y0) or a reference "
                f"state of shape ({system.state_dim},) (e.g. a steady motion)."
            )
        return True, y0
    try:
        p0 = system.state(linearisation, argument)
    except ValueError as e:
        raise ValueError(f"{e} {argument} must be 'mean' or a reference state (e.g. a steady motion).") from None
    return False, p0.astype(y0.dtype)


class LinearisedControl(eqx.Module):
    """The control of ``system`` from ``y0`` (module): :func:`linearised_system` about the reference of
    ``linearisation`` (``'mean'``, ``None`` or a state; the caller's ``argument``), its start ``(p0, y0)``, and its
    exact saved moments."""

    system: StochasticSystem
    start: Values
    follow: bool = eqx.field(static=True)

    def __init__(self, system: StochasticSystem, y0, linearisation, names: tuple[str, ...], argument: str):
        observables = [n for n in names if n not in system.layout.names]
        if not system.noise.continuous and observables:
            raise ValueError(
                f"save.names={names}: with the jump driver {type(system.noise).__name__} the control is not "
                "Gaussian, and the covariance of a nonlinear observable's control needs Gaussian fourth moments "
                f"(Isserlis); save state components only, not {observables}."
            )
        self.follow, p0 = _reference(system, y0, linearisation, argument)
        self.system = linearised_system(system, follow=self.follow)
        self.start = array_module(p0, y0).concatenate([p0, y0])

    def exact(self, system: StochasticSystem, names, t0, t1, n_steps: int, n_save: int, wrt, on_host: bool):
        """``((ts, mean, cov), tangents)``: the exact moments of the saved quantities' controls of ``system`` (its
        parameters may differ from the control's: this is differentiated in them, :func:`with_tangents`), in
        float64 NumPy arrays with ``on_host`` (to combine with the paths' host statistics); ``n_steps`` the SDE's
        steps (the moment equations take ≥ 4 per step)."""
        d = self.start.shape[0] // 2
        p0, y0 = self.start[:d], self.start[d:]
        n_ode = (n_save - 1) * math.ceil(max(4 * n_steps, _ODE_STEPS) / (n_save - 1))

        def exact(s: StochasticSystem):
            ito = s.converted("ito")
            closure = _closure(linearised_system(s, follow=self.follow), y0.dtype)
            return _exact(closure, ito, cast_floats(ito.params, y0.dtype), names, p0, y0, t0, t1, n_ode, n_save)

        moments, tangents = with_tangents(exact, system, wrt)
        if on_host:
            moments = tuple(np.asarray(a, np.float64) for a in moments)
        return moments, tangents


def control_variate(
    system: StochasticSystem,
    y0,
    key,
    *,
    n_paths: int,
    t1: float | None = None,
    dt: float | None = None,
    steps: AbstractSteps | None = None,
    t0: float | None = None,
    solver=None,
    save: Save | None = None,
    linearisation=None,
    batching: Batching | None = None,
    run: RunOptions | None = None,
    wrt=None,
) -> ControlVariateEstimate:
    """Means and covariances of the saved quantities with the linearised system as control variate (module).

    Arguments as :func:`~nhsde.simulate` (``run=`` or its keywords; fixed steps: ``dt`` or
    ``steps=FixedSteps(dt)``; ``y0`` one state ``(d,)``); ``save`` defaults to the
    whole state at ``t0`` and ``t1`` (per-path values are kept internally).
    ``linearisation``: ``'mean'`` (default: about the noiseless motion from ``y0``)
    or a state ``(d,)`` to linearise about (a steady motion; it may be traced).
    Two solves of ``n_paths`` paths on one Brownian path: the system, and the
    control of :func:`linearised_system`.  Any solver ``simulate`` accepts for the
    system (Euler, Milstein, Heun, heun2, SRA1, exponential,
    :class:`~nhsde.PlatenWeak2`); with a jump driver (Euler only), state components
    only.  Differentiable in the
    parameters with β held fixed (module).  ``wrt``: names of scalar parameters
    (``('eps', 'nu')``): ``derivatives`` of the estimate in them (β fixed), with standard errors.
    """
    watch = Stopwatch()
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    wrt = () if wrt is None else check_wrt(system, wrt)
    (n_paths,) = checked_paths("n_paths", n_paths)
    options = run_options(
        "control_variate",
        run,
        t0=t0,
        t1=t1,
        dt=dt,
        steps=steps,
        solver=solver,
        save=save,
        batching=batching,
        brownian_dt=True,
    )
    n_steps = options.n_steps
    y0 = system.state(y0, "y0")
    solver_needs(options.solver, system)  # names the solver if it cannot solve the system
    save = paths_save(options.save, n_steps, system.layout.names)
    assert save.names is not None
    names = save.names
    system.observe(names)  # unknown names raise naming save
    control = LinearisedControl(system, y0, linearisation, names, "linearisation")
    key = check_key(key)

    n_save = save.n
    assert n_save is not None
    check_memory(
        f"n_paths={n_paths}",
        peak_bytes(2 * n_paths * path_bytes(n_save, len(names), len(wrt))),
        "take fewer paths, or average runs of several keys.",
    )

    options = dataclasses.replace(options, save=save)

    def solve(s: StochasticSystem, start):
        return solve_paths_with_tangents(s, start, key, options, wrt, first_path=0, n_paths=n_paths)

    y, t_y = solve(system, y0)
    c, t_c = solve(control.system, control.start)
    on_host = array_module(y, c) is np
    (ts, exact_mean, exact_cov), d_exact = control.exact(
        system, names, options.t0, options.t1, n_steps, n_save, wrt, on_host
    )
    (mean_y, cov_y, mvar_y, cvar_y), (mean_c, cov_c), beta, resid, reduction = fitted_controls([y], [c], [1.0])
    (beta_m, beta_c), (resid_m, resid_c), (red_m, red_c) = beta, resid, reduction
    derivatives = None
    if wrt:
        assert t_y is not None and t_c is not None and d_exact is not None
        d_mean, d_cov, d_mean_var, d_cov_var = paired_sensitivities([y, c], [t_y, t_c], [1.0, -beta_m], [1.0, -beta_c])
        _, d_exact_mean, d_exact_cov = d_exact
        derivatives = Derivatives(
            d_mean + beta_m * d_exact_mean,
            d_cov + beta_c * d_exact_cov,
            safe_sqrt(d_mean_var),
            safe_sqrt(d_cov_var),
            wrt,
        )

    count, roles = jax.device_put(np.asarray(n_paths)), roles_of(system, names)
    plain_estimate = MonteCarloEstimate(
        ts=ts,
        mean=mean_y,
        cov=cov_y,
        mean_se=safe_sqrt(mvar_y),
        cov_se=safe_sqrt(cvar_y),
        n_paths=count,
        names=names,
        roles=roles,
        derivatives=None,
        cost=Cost(float(n_paths * n_steps)),
        statistic=None,
    )
    estimate = ControlVariateEstimate(
        ts=ts,
        mean=mean_y - beta_m * (mean_c - exact_mean),
        cov=cov_y - beta_c * (cov_c - exact_cov),
        mean_se=safe_sqrt(resid_m),
        cov_se=safe_sqrt(resid_c),
        plain=plain_estimate,
        coefficient=PerEntry(mean=beta_m, cov=beta_c),
        variance_reduction=PerEntry(mean=red_m, cov=red_c),
        control=PerEntry(mean=exact_mean, cov=exact_cov),
        derivatives=derivatives,
        n_paths=count,
        names=names,
        roles=roles,
        cost=watch.cost(2 * n_paths * n_steps),
        statistic=None,
    )
    return on_device(estimate, y.dtype)
