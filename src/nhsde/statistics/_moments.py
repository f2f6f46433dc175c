"""Normal-approximation method (statistical linearisation), S0 §6, and Green–Kubo diffusion.

Gaussian closure of the Itô system ``dZ = a dt + b dW``, ``W`` of intensity
``ν`` per channel (S0 (1.4): Wiener, Poisson or general): with ``E_N`` the
expectation under ``N(m, K)``,

    ṁ = E_N[a],    K̇ = Ā K + K Āᵀ + E_N[b diag(ν) bᵀ],    Ā = E_N[∂a/∂Z]

(``E_N[a Z°ᵀ] = Ā K`` by Stein's lemma).  It is exact for linear systems, with
any driver.  For the dependent coordinates ``q''`` (Chaplygin: ``a`` and ``b``
do not depend on them) ``ṁ_{q''} = E_N[Λ] = Λ₀`` and the ``q''`` rows of ``K̇``
are ``(∂Λ₀/∂m_x) K_{x q''} + …``: the statistically linearised drift
``m_{q''} = ∫Λ₀``, ``K_{q''} = ∫∫ (∂Λ₀/∂m_x) K_x(τ₁, τ₂) (∂Λ₀/∂m_x)ᵀ`` of S0 §6.
Expectations are tensor Gauss–Hermite cubatures of ``order`` nodes per
component over the components on which ``∂a/∂Z`` or ``b`` depend (``a`` is
affine in the others: no cubature at all for a linear system, never over ``q''``
in a Chaplygin system); the moment equations are solved with fixed Dopri8 steps
in a ``lax.scan``, so results are differentiable in every parameter, in forward
and in reverse mode.

In a stationary regime of ``x`` (the components other than ``q''``),
:func:`stationary_drift` gives S0's stationary formulas: ``m_{q''}(t) ≈ Λ₀ t``
and ``K_{q''}(t) ≈ L [M(t) K_x + K_x M(t)ᵀ] Lᵀ`` with ``L = ∂Λ₀/∂m_x``,
``M(t) = ∫₀ᵗ (t − ξ) e^{Āξ} dξ = Ā⁻²(e^{Āt} − I) − t Ā⁻¹`` (the linearised
correlation ``k_x(τ) = e^{Āτ} K_x``; the printed single integral of S0 misses the
symmetrisation), whose slope is the Green–Kubo diffusion
``D = ∫₀^∞ sym(L k_x(τ) Lᵀ) dτ = −½ L (Ā⁻¹K_x + K_x Ā⁻ᵀ) Lᵀ``.
:func:`green_kubo` estimates the same integral from Monte-Carlo paths.
"""

from __future__ import annotations

import math

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import expm
from jaxtyping import Array, Float

from .._params import validated
from .._simulate import Ensemble, Save, _number, _steps
from .._system import StochasticSystem
from ..noise._levy import driver_intensity
from ._drift import DriftStatistics, StationaryMoments

__all__ = ["GreenKubo", "StationaryDrift", "green_kubo", "normal_approximation", "stationary_drift"]

SOLVER_NAME = "normal-approximation"

_expm_batch = jax.jit(jax.vmap(expm))


# ----------------------------------------------------------------------------- closure


def _hermite(order: int, dim: int, dtype):
    """Tensor Gauss–Hermite rule for ``N(0, I_dim)``: nodes ``(P, dim)``, weights ``(P,)``, exactly symmetric."""
    x, w = np.polynomial.hermite_e.hermegauss(order)
    x, w = (x - x[::-1]) / 2, (w + w[::-1]) / 2
    w = w / w.sum()
    grid = np.meshgrid(*([x] * dim), indexing="ij")
    wgrid = np.meshgrid(*([w] * dim), indexing="ij")
    nodes = np.stack([g.reshape(-1) for g in grid], axis=-1) if dim else np.zeros((1, 0))
    weights = np.prod(np.stack([g.reshape(-1) for g in wgrid], axis=-1), axis=-1) if dim else np.ones(1)
    return jnp.asarray(nodes, dtype), jnp.asarray(weights, dtype)


def _nonlinear_components(system: StochasticSystem, dtype) -> tuple[int, ...]:
    """Components on which ``∂a/∂Z`` or ``b`` depend; ``a`` is affine in the others with constant coefficients,
    so Gaussian expectations need cubature over these only (none for a linear system).

    Found by differentiating ``(∂a/∂Z, b)`` along each component at random states, with every parameter leaf
    replaced by a random value in ``[0.5, 1.5]``: the structure, not the current (possibly traced) values, decides.
    """
    rng = np.random.default_rng(0)
    drift, diffusion = system.drift_fn, system.diffusion_fn
    d = system.state_dim
    with jax.ensure_compile_time_eval():  # concrete even inside an outer jit
        params = jax.tree_util.tree_map(
            lambda p: (
                jnp.asarray(rng.uniform(0.5, 1.5, np.shape(p)), dtype)
                if jnp.issubdtype(jnp.result_type(p), jnp.floating)
                else p
            ),
            system.params,
        )

        def coefficients(z):
            return jax.jacfwd(lambda y: drift(0.0, y, params))(z), diffusion(0.0, z, params)

        def tangents(z, direction):
            return jax.jvp(coefficients, (z,), (direction,))[1]

        probe = jax.jit(jax.vmap(jax.vmap(tangents, in_axes=(None, 0)), in_axes=(0, None)))
        out = probe(jnp.asarray(rng.normal(size=(3, d)), dtype), jnp.eye(d, dtype=dtype))  # (point, direction, …)
        found = np.zeros(d, bool)
        for t in out:  # NaN counts as dependence
            found |= np.asarray(jnp.any(t.reshape(3, d, -1) != 0, axis=(0, 2)))
    return tuple(int(i) for i in np.flatnonzero(found))


def _cholesky(k, floor):
    """Lower Cholesky factor of a symmetric positive semi-definite ``k``, robust to rounding.

    A pivot at or below ``floor`` (a direction without variance; Runge–Kutta
    stages of a covariance that starts at 0 can even be slightly indefinite)
    gets a zero column below the diagonal and ``√floor`` on it.  Plain
    arithmetic, so differentiable everywhere.
    """
    n = k.shape[0]
    below = jnp.arange(n)
    cols = []
    for j in range(n):
        c = k[:, j] - sum((cols[i] * cols[i][j] for i in range(j)), jnp.zeros_like(k[:, j]))
        ok = c[j] > floor
        pivot = jnp.sqrt(jnp.where(ok, c[j], floor))
        cols.append(jnp.where(ok & (below > j), c / pivot, 0.0).at[j].set(pivot))
    return jnp.stack(cols, axis=1)


class _Closure(eqx.Module):
    """Gaussian expectations of the drift, its Jacobian and the noise covariance of ``system``."""

    system: StochasticSystem
    intensity: Array  # ν per channel
    active: tuple[int, ...] = eqx.field(static=True)  # components ∂a/∂Z and b depend on
    nodes: Array
    weights: Array

    def expectations(self, t, m, k):
        """``(E_N[a], E_N[∂a/∂Z], E_N[b diag(ν) bᵀ])`` under ``N(m, K)``."""
        idx = np.asarray(self.active, dtype=int)
        z = jnp.broadcast_to(m, (self.weights.shape[0], m.shape[0]))
        if idx.size:
            k_a = k[np.ix_(idx, idx)]
            tiny = jnp.finfo(m.dtype).eps
            chol = _cholesky(0.5 * (k_a + k_a.T), tiny * jnp.max(jnp.abs(jnp.diagonal(k_a))) + tiny**2)
            z = z.at[:, idx].add(self.nodes @ chol.T)
        params = self.system.params

        def drift_twice(y):
            a = self.system.drift(t, y, params)
            return a, a

        jac, drift = jax.vmap(jax.jacfwd(drift_twice, has_aux=True))(z)
        b = jax.vmap(lambda y: self.system.diffusion(t, y, params))(z)
        w = self.weights
        return (
            jnp.einsum("p,pi->i", w, drift),
            jnp.einsum("p,pij->ij", w, jac),
            jnp.einsum("p,pik,k,pjk->ij", w, b, self.intensity, b),
        )

    def rhs(self, t, state, args):
        m, k = state
        mean_a, jac, q = self.expectations(t, m, k)
        return mean_a, jac @ k + k @ jac.T + q


def _closure(system: StochasticSystem, dtype, order: int) -> _Closure:
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    order = _number("order", order, integer=True)
    if order < 1:
        raise ValueError(f"order={order}; must be ≥ 1 (Gauss–Hermite nodes per component).")
    if system.interpretation != "ito":
        system = system.converted("ito")
    params = validated(system.params)
    params = jax.tree_util.tree_map(
        lambda p: p.astype(dtype) if jnp.issubdtype(jnp.result_type(p), jnp.floating) else p, params
    )
    system = eqx.tree_at(lambda s: s.params, system, params)
    active = _nonlinear_components(system, dtype)
    nodes, weights = _hermite(order, len(active), dtype)
    return _Closure(system, driver_intensity(system.noise, system.noise_dim, dtype), active, nodes, weights)


def _initial(system, y0, cov0):
    d = system.state_dim
    y0 = system.state(y0)
    cov0 = jnp.zeros((d, d), y0.dtype) if cov0 is None else jnp.asarray(cov0).astype(y0.dtype)
    if cov0.shape != (d, d):
        raise ValueError(f"cov0 has shape {cov0.shape}; expected ({d}, {d}).")
    if not isinstance(cov0, jax.core.Tracer):
        c = np.asarray(cov0, np.float64)
        if (
            not np.all(np.isfinite(c))
            or not np.allclose(c, c.T)
            or np.min(np.linalg.eigvalsh(c)) < -1e-12 * max(1.0, np.abs(c).max())
        ):
            raise ValueError("cov0 must be a finite, symmetric, positive semi-definite matrix.")
    return y0, cov0


@eqx.filter_jit
def _integrate(closure: _Closure, m0, k0, t0: float, t1: float, n_steps: int, n_save: int):
    """``(ts, means, covs)`` at ``n_save`` equally spaced times, fixed Dopri8 steps."""
    dtype = m0.dtype
    solver = dfx.Dopri8(scan_kind="bounded")  # differentiable in forward and reverse mode (the default is reverse only)
    term = dfx.ODETerm(closure.rhs)
    dt = jnp.asarray((t1 - t0) / n_steps, dtype)
    per_save = n_steps // (n_save - 1)
    state0 = (m0, k0)
    solver_state = solver.init(term, jnp.asarray(t0, dtype), jnp.asarray(t0, dtype) + dt, state0, None)

    def interval(carry, j):
        def step(c, i):
            y, s = c
            t = t0 + (j * per_save + i).astype(dtype) * dt
            y1, _, _, s1, _ = solver.step(term, t, t + dt, y, None, s, False)
            return (y1, s1), None

        carry, _ = jax.lax.scan(step, carry, jnp.arange(per_save))
        return carry, carry[0]

    _, (ms, ks) = jax.lax.scan(interval, (state0, solver_state), jnp.arange(n_save - 1))
    ts = jnp.linspace(t0, t1, n_save, dtype=dtype)
    return ts, jnp.concatenate([m0[None], ms]), jnp.concatenate([k0[None], ks])


def normal_approximation(
    system: StochasticSystem,
    y0,
    cov0=None,
    *,
    t1: float,
    dt: float,
    t0: float = 0.0,
    save: Save | None = None,
    order: int = 5,
) -> Ensemble:
    """Mean and covariance of the state under Gaussian closure, S0 §6, as an :class:`~nhsde.Ensemble`.

    ``y0``, ``cov0`` (default 0) are the initial mean and covariance; ``dt`` the
    fixed Dopri8 step; ``save`` picks state components and save times as in
    :func:`~nhsde.simulate`; ``order`` Gauss–Hermite nodes per component.  The
    standard errors are zero and ``solver`` is ``'normal-approximation'``, so
    :func:`~nhsde.statistics.drift_statistics` and the other ensemble statistics
    apply unchanged.
    """
    y0, cov0 = _initial(system, y0, cov0)
    closure = _closure(system, y0.dtype, order)
    t0, t1 = _number("t0", t0), _number("t1", t1)
    if t1 <= t0:
        raise ValueError(f"t1={t1} must be > t0={t0}.")
    dt = _number("dt", dt, positive=True)
    n_steps = _steps("dt", t1 - t0, dt)
    save = Save() if save is None else save
    if not isinstance(save, Save):
        raise TypeError(f"save={save!r}; expected nhsde.Save(...).")
    if save.paths:
        raise ValueError("save.paths: the normal approximation has moments only, no paths.")
    names = system.layout.names if save.names is None else tuple(save.names)
    for name in names:
        if name not in system.layout.names:
            raise ValueError(f"save: {name!r} is not a state component; the state is {system.layout.names}.")
    n_save = save.n if save.n is not None else max(k for k in range(2, 12) if n_steps % (k - 1) == 0)
    n_save = _number("save.n", n_save, integer=True)
    if n_save < 2 or n_steps % (n_save - 1):
        raise ValueError(f"save.n={n_save}: n − 1 must be ≥ 1 and divide the {n_steps} steps.")
    ts, ms, ks = _integrate(closure, y0, cov0, t0, t1, n_steps, n_save)
    idx = np.asarray([system.layout.index(n) for n in names])
    mean, cov = ms[:, idx], ks[:, idx[:, None], idx[None, :]]
    return Ensemble(
        ts=ts,
        mean=mean,
        cov=cov,
        mean_se=jnp.zeros_like(mean),
        cov_se=jnp.zeros_like(cov),
        n_used=jnp.zeros((), jnp.int32),
        failed=jnp.zeros((0,), bool),
        paths=None,
        names=names,
        roles=tuple(system.layout.roles[i] for i in idx),
        solver=SOLVER_NAME,
        dt=(t1 - t0) / n_steps,
    )


# ----------------------------------------------------------------------------- stationary regime


class StationaryDrift(eqx.Module):
    """Statistically linearised stationary regime of ``x`` and the drift of ``q''`` it causes (S0 §6).

    ``rate = Λ₀`` (``m_{q''}(t) ≈ Λ₀ t``), ``gain = L = ∂Λ₀/∂m_x``,
    ``jacobian = Ā`` (stationary, Hurwitz), ``moments``: stationary ``m_x``, ``K_x``.
    """

    rate: Float[Array, " k"]
    gain: Float[Array, "k n"]
    jacobian: Float[Array, "n n"]
    moments: StationaryMoments
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def diffusion(self) -> Float[Array, "k k"]:
        """Green–Kubo ``D = ∫₀^∞ sym(L k_x(τ) Lᵀ) dτ = −½ L (Ā⁻¹K + K Ā⁻ᵀ) Lᵀ``."""
        c = -jnp.linalg.solve(self.jacobian, self.moments.cov)
        return 0.5 * self.gain @ (c + c.T) @ self.gain.T

    def velocity_autocorrelation(self, taus) -> Float[Array, "n k k"]:
        """``E[Λ°(t+τ) Λ°(t)ᵀ] ≈ L e^{Āτ} K Lᵀ`` for ``τ ≥ 0``."""
        taus = jnp.asarray(taus, self.jacobian.dtype)
        e = _expm_batch(self.jacobian * taus[:, None, None])
        return jnp.einsum("ki,tij,jl,ml->tkm", self.gain, e, self.moments.cov, self.gain)

    def systematic(self, ts) -> Float[Array, "n k"]:
        """``m_{q''}(t) ≈ Λ₀ t`` (``q''(0) = 0``)."""
        return jnp.asarray(ts, self.rate.dtype)[:, None] * self.rate

    def fluctuation(self, ts) -> Float[Array, "n k k"]:
        """``K_{q''}(t) ≈ L [M(t) K + K M(t)ᵀ] Lᵀ``, ``M(t) = Ā⁻²(e^{Āt} − I) − t Ā⁻¹`` (``q''(0) = 0``)."""
        a, k, gain = self.jacobian, self.moments.cov, self.gain
        ts = jnp.asarray(ts, a.dtype)
        a_inv = jnp.linalg.inv(a)
        e = _expm_batch(a * ts[:, None, None]) - jnp.eye(a.shape[0], dtype=a.dtype)
        m = jnp.einsum("ij,tjk->tik", a_inv @ a_inv, e) - ts[:, None, None] * a_inv
        mk = jnp.einsum("tij,jk->tik", m, k)
        return jnp.einsum("ki,tij,lj->tkl", gain, mk + jnp.swapaxes(mk, 1, 2), gain)

    def statistics(self, ts) -> DriftStatistics:
        """The stationary-regime drift as :class:`DriftStatistics` (zero standard errors)."""
        ts = jnp.asarray(ts, self.rate.dtype)
        m, k = self.systematic(ts), self.fluctuation(ts)
        return DriftStatistics(ts, m, jnp.zeros_like(m), k, jnp.zeros_like(k), self.names)


@eqx.filter_jit
def _newton(closure: _Closure, m, k, x: tuple[int, ...], steps: int):
    """Newton's method on ``ṁ_x = 0``, ``K̇_x = 0`` (``K_x`` by its upper triangle) from ``(m, K)``.

    Returns ``m_x``, ``K_x``, the expectations ``E_N[a]``, ``E_N[∂a/∂Z]`` there and the largest residual.
    """
    x = np.asarray(x)
    n = len(x)
    iu = np.triu_indices(n)
    t = jnp.zeros((), m.dtype)

    def unpack(v):
        kx = jnp.zeros((n, n), v.dtype).at[iu].set(v[n:])
        return v[:n], kx + jnp.triu(kx, 1).T

    def residual(v):
        mx, kx = unpack(v)
        mean_a, jac, q = closure.expectations(t, m.at[x].set(mx), k.at[np.ix_(x, x)].set(kx))
        ja = jac[np.ix_(x, x)]
        return jnp.concatenate([mean_a[x], (ja @ kx + kx @ ja.T + q[np.ix_(x, x)])[iu]])

    def newton(v, _):
        return v - jnp.linalg.solve(jax.jacfwd(residual)(v), residual(v)), None

    v, _ = jax.lax.scan(newton, jnp.concatenate([m[x], k[np.ix_(x, x)][iu]]), None, length=steps)
    mx, kx = unpack(v)
    mean_a, jac, _ = closure.expectations(t, m.at[x].set(mx), k.at[np.ix_(x, x)].set(kx))
    return mx, kx, mean_a, jac, jnp.max(jnp.abs(residual(v)))


def stationary_drift(
    system: StochasticSystem,
    y0,
    cov0=None,
    *,
    t_relax: float,
    dt: float,
    order: int = 5,
    newton_steps: int = 8,
    rtol: float = 1e-9,
) -> StationaryDrift:
    """Stationary regime of the normal approximation and S0 §6's stationary drift formulas.

    The moment equations run from ``(y0, cov0)`` for ``t_relax``; Newton's method
    then solves ``ṁ_x = 0``, ``K̇_x = 0`` for the components ``x`` other than
    ``q''``.  Raises if the residual stays above ``rtol`` (relative) or if the
    linearised drift ``Ā`` of ``x`` is not Hurwitz (no stationary regime).
    """
    y0, cov0 = _initial(system, y0, cov0)
    closure = _closure(system, y0.dtype, order)
    layout = closure.system.layout
    dep = np.asarray(layout.indices("dependent_coordinate"), dtype=int)
    x = np.asarray([i for i in range(layout.size) if i not in dep], dtype=int)
    t_relax = _number("t_relax", t_relax, positive=True)
    n_steps = _steps("dt", t_relax, _number("dt", dt, positive=True))
    _, ms, ks = _integrate(closure, y0, cov0, 0.0, t_relax, n_steps, 2)
    newton_steps = _number("newton_steps", newton_steps, integer=True)
    mx, kx, mean_a, jac, res = _newton(closure, ms[-1], ks[-1], tuple(x.tolist()), newton_steps)
    ja = jac[np.ix_(x, x)]
    if not isinstance(res, jax.core.Tracer):
        res = float(res)
        scale = max(float(jnp.max(jnp.abs(mx))), float(jnp.max(jnp.abs(kx)))) * max(1.0, float(jnp.max(jnp.abs(ja))))
        if not res <= rtol * scale:
            raise ValueError(
                f"no stationary regime found: moment-equation residual {res:.3g} after {newton_steps} Newton steps "
                f"(scale {scale:.3g}); increase t_relax or check that "
                f"x = {tuple(layout.names[i] for i in x)} is stationary."
            )
        growth = float(jnp.max(jnp.real(jnp.linalg.eigvals(ja))))
        if not growth < 0:
            raise ValueError(
                f"no stationary regime: the linearised drift of {tuple(layout.names[i] for i in x)} has an eigenvalue "
                f"with real part {growth:.3g} ≥ 0."
            )
    return StationaryDrift(
        rate=mean_a[dep],
        gain=jac[np.ix_(dep, x)],
        jacobian=ja,
        moments=StationaryMoments(mx, kx, tuple(layout.names[i] for i in x)),
        names=tuple(layout.names[i] for i in dep),
    )


# ----------------------------------------------------------------------------- Green–Kubo from paths


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
    """
    if ens.paths is None or ens.names != system.layout.names:
        raise ValueError(
            f"green_kubo needs the whole state {system.layout.names} per path: simulate with Save(paths=True)."
        )
    dep = np.asarray(system.layout.indices("dependent_coordinate"), dtype=int)
    if dep.size == 0:
        raise ValueError(f"the state {system.layout.names} has no dependent coordinates.")
    ts = np.asarray(ens.ts)
    spacing = float(ts[1] - ts[0])
    window = np.flatnonzero(ts >= t_from - 1e-9 * spacing)
    n_lag = round(_number("max_lag", max_lag, positive=True) / spacing)
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

    def per_path(v):  # (lags, k, k): C_p(τ_j) averaged over time origins
        return (
            jax.vmap(lambda j: jnp.einsum("nk,nl->kl", jax.lax.dynamic_slice_in_dim(v, j, n_origin), v[:n_origin]))(
                jnp.arange(n_lag + 1)
            )
            / n_origin
        )

    per_path = jax.jit(jax.vmap(per_path))(vel)  # (p, lags, k, k)
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
