"""Martingale (regression) control variates: a control of mean exactly zero for the discretisation itself.

For a statistic ``f(X_N)`` of the discretised paths the control is the discrete martingale

    M_N = Σₙ Zₙ(Xₙ)·ΔWₙ,   Zₙ(x) = Σ_k β_k ψ_k(tₙ, x) ≈ ∇u(tₙ, x) b(x),   u(t, x) = E[f(X_N) | X(t) = x]

(Milstein & Tretyakov 2009, "Practical variance reduction via regression for simulating diffusions";
Belomestny, Häfner, Nefedov & Urusov, arXiv 1510.03141), whose ideal ``Z`` makes ``f − M`` constant.  ``ΔWₙ`` is
independent of ``Xₙ`` and centred, so ``E M_N = 0`` whatever ``β`` is: a poor fit costs variance, never bias.

- **How ``M`` is computed.**  The controls ``M_k = Σₙ ψ_k(tₙ, Xₙ)·ΔWₙ`` are extra state components of the Itô
  system with drift 0 and diffusion rows ``ψ_k(t, x)`` (:func:`martingale_system`), solved with the system on the
  same increments.  Euler–Maruyama adds exactly ``ψ_k(tₙ, Xₙ)·ΔWₙ``.  Platen's weak scheme
  (:class:`~nhsde.PlatenWeak2`, KP (15.1.3)) adds ``¼[ψ(R₊) + ψ(R₋) + 2ψ]·ΔŴ + ¼[ψ(R₊) − ψ(R₋)](ΔŴ² − h)/√h``
  (+ the ``U`` terms in ``ΔŴʳΔŴʲ + V_rj``, ``r ≠ j``): supporting values are functions of ``Xₙ``, and every
  increment polynomial has mean zero given the past.  This is the discrete analogue built on the scheme's own
  increments (arXiv 1701.00273, three-point increments included).  Other schemes (Heun, Milstein) evaluate ``ψ`` at
  predicted states, and their control's mean is zero only to the scheme's order; they are refused.
- **The basis.**  ``ψ = τʲ ∇(x^α)ᵀ b(x)``: gradients of the monomials ``u = x^α``, ``1 ≤ |α| ≤ degree``, times
  ``b``, and time polynomials ``τʲ``, ``τ = (t − t0)/(t1 − t0)``, ``j ≤ time_degree``.  Monomials whose gradient
  meets only noiseless rows of ``b`` (rows zero at two states) are dropped.  ``degree=2`` spans, with ``τʲ``, the
  gradient of the linearised system's quadratic value function (:func:`~nhsde.statistics.control_variate`) up to its
  time dependence.  A callable basis ``(t, x, params) -> (K, m)`` may replace the monomials.
- **The fit.**  ``β`` minimises the sample variance of ``f − β·M`` per saved entry and time on a pilot of
  ``n_pilot`` independent paths (paths ``n_paths …`` of the same key); least squares by the pseudo-inverse of the
  standardised Gram matrix, on the host in float64.  This is the variance-optimal ``β`` for the basis (global in
  time through ``τʲ``), rather than per-step regressions; it is held outside the derivative (``stop_gradient``).
- **Means and covariances.**  A mean entry ``Y`` is estimated by ``mean(Y − β·M)``, ``SE² = Var(Y − β·M)/N``.  A
  covariance entry by the controlled second moment about the pilot's means ``c``: with ``F = (Yᵢ − cᵢ)(Yⱼ − cⱼ)`` and
  ``Y' = Y − β·M``, ``Ĉ = mean(F − β_F·M) − dᵢdⱼ + ŝ(Y'ᵢ, Y'ⱼ)/N``, ``d = mean(Y') − c``: unbiased (without
  control it is the unbiased sample covariance), with the delta-method influence ``F' − dⱼY'ᵢ − dᵢY'ⱼ``.
- **Derivatives** in scalar parameters (``wrt``; or ``jax.grad`` through the estimate) are those of the same
  formulas with ``β`` and ``c`` fixed, from the per-path tangents of ``Y`` and ``M`` (forward mode).  ``∂M`` has mean
  zero too (``∂ψ(Xₙ)`` is adapted), so the derivative estimates are unbiased for the scheme's derivative.

- **The run carries the fitted combinations only.**  The pilot solves all ``K`` controls; the run then accumulates
  ``M̃_r = Σₙ Z_r(tₙ, Xₙ)·ΔWₙ``, ``Z_r = Σ_k β_rk ψ_k``, one component per saved entry after ``t0`` (a
  covariance's ``(i, j)`` and ``(j, i)`` share one), which equals ``β_r·M`` on the same increments
  (:func:`fitted_system`), whenever those ``R`` are fewer than ``K``.  For the monomial basis ``Z_r = ∇g_r(τ, x)ᵀ b``
  with ``g_r = Σ β_rk τʲ x^α``, evaluated as a polynomial of degree ≤ 2 in ``x`` on the noisy rows only; ``β`` is data
  of the program (one compile for every fit).

Cost: a pilot of ``n_pilot`` paths of the state with ``K`` extra components (``K`` the basis size ``×
(time_degree + 1)``), one ``K × K`` pseudo-inverse per save time, and the run of ``n_paths`` paths with
``min(R, K)`` extra components.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable
from typing import Any, cast

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._ensemble import Save
from .._misc import check_key, check_number, fold_key, is_concrete
from .._options import AbstractSteps, Batching, RunOptions, run_options
from .._solvers import solver_needs
from .._system import StateLayout, StochasticSystem
from .._weak import PlatenWeak2
from ._control_variate import ControlVariateEstimate, PerEntry
from ._cost import check_memory, path_bytes, peak_bytes
from ._estimate import Cost, Derivatives, MonteCarloEstimate, Stopwatch, as_statistic
from ._paths import (
    RUN_PATHS,
    array_module,
    checked_paths,
    coupled_paths,
    on_device,
    paired_moments,
    paths_save,
    roles_of,
    safe_sqrt,
    solve_paths,
    solve_paths_with_tangents,
)
from ._sensitivities import check_wrt

__all__ = ["MartingaleControl", "martingale_control_variate", "martingale_system"]

_CONTROL = "@martingale"
_BASES = ("linear", "quadratic", "cubic")
_RCOND = 1e-10  # relative cut-off of the standardised Gram matrix's eigenvalues
_PILOT_FOLD = 1 << 30  # the key of a multilevel control's pilot: fold_key(key, level) drives level ℓ's paths


# ----------------------------------------------------------------------------- the basis and the augmented system


def _monomials(d: int, degree: int, noisy: tuple[int, ...]) -> tuple[tuple[int, ...], ...]:
    """Exponents ``α`` of the monomials ``x^α``, ``1 ≤ |α| ≤ degree``, whose support meets the ``noisy`` rows."""
    out = []
    for n in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(range(d), n):
            if set(combo) & set(noisy):
                out.append(tuple(combo.count(i) for i in range(d)))
    return tuple(out)


class _Basis(eqx.Module):
    """``ψ(t, x, b) (K·(time_degree + 1), m)``: ``τʲ ∇(x^α)ᵀ b`` (or ``τʲ`` times a user basis's rows)."""

    exponents: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    user: Callable | None = eqx.field(static=True)
    time_degree: int = eqx.field(static=True)
    t0: float = eqx.field(static=True)
    t1: float = eqx.field(static=True)
    noisy: tuple[int, ...] = eqx.field(static=True, default=())

    def powers(self, t, dtype):
        """``(τʲ)ⱼ``, ``j ≤ time_degree``."""
        tau = (t - self.t0) / (self.t1 - self.t0)
        powers = [jnp.ones((), dtype)]
        for _ in range(self.time_degree):
            powers.append(powers[-1] * tau)
        return jnp.stack(powers).astype(dtype)

    def __call__(self, t, x, params, b):
        if self.user is not None:
            psi = jnp.asarray(self.user(t, x, params), b.dtype)
        else:
            # ∂(x^α)/∂x_l = α_l x^(α − e_l): products of gathered entries (no powers, whose derivative at 0 is nan)
            alpha = np.array(self.exponents)  # (K, d)
            d = alpha.shape[1]
            width = max(1, int(alpha.sum(axis=1).max()) - 1)
            index = np.full(alpha.shape + (width,), d)  # d: the padding entry 1
            for k, l in zip(*np.nonzero(alpha), strict=True):
                reduced = alpha[k].copy()
                reduced[l] -= 1
                factors = np.repeat(np.arange(d), reduced)
                index[k, l, : factors.size] = factors
            extended = jnp.concatenate([x, jnp.ones((1,), x.dtype)])
            gradients = jnp.asarray(alpha, x.dtype) * jnp.prod(extended[index], axis=-1)
            rows = np.asarray(self.noisy or range(d))  # the noiseless rows of b are zero
            psi = gradients[:, rows].astype(b.dtype) @ b[rows]
        powers = self.powers(t, b.dtype)
        return (powers[:, None, None] * psi[None]).reshape(-1, b.shape[1])

    def polynomial(self, beta):
        """The fitted rows ``Σ_k β_rk ψ_k = ∇g_r(τ, x)ᵀ b`` of the monomial basis as the coefficients of
        ``∂g_r/∂x_i`` on the noisy rows ``i``, a polynomial of degree ≤ 2 in ``x``: ``(C0 (R, J, n), C1 (R, J, n, d),
        C2 (R, J, n, d, d) or None)`` from ``β (R, J·K)`` (module; ``J = time_degree + 1``)."""
        alpha = np.array(self.exponents)
        n_k, d = alpha.shape
        rows = self.noisy or tuple(range(d))
        top = int(alpha.sum(axis=1).max()) - 1  # the gradient's degree
        sizes = (1, d, d * d)[: top + 1]
        maps = [np.zeros((n_k, len(rows), size)) for size in sizes]
        for k in range(n_k):
            for i, row in enumerate(rows):
                if alpha[k, row] == 0:
                    continue
                reduced = alpha[k].copy()
                reduced[row] -= 1
                factors = np.repeat(np.arange(d), reduced)  # x^(α − e_i) = Π x_factors
                where = 0 if factors.size == 0 else (factors[0] if factors.size == 1 else factors[0] * d + factors[1])
                maps[factors.size][k, i, where] += alpha[k, row]
        r = beta.shape[0]
        beta = beta.reshape(r, self.time_degree + 1, n_k)
        out = [jnp.einsum("rjk,kis->rjis", beta, jnp.asarray(m, beta.dtype)) for m in maps]
        c0 = out[0][..., 0]
        c1 = out[1] if top >= 1 else None
        c2 = out[2].reshape(out[2].shape[:-1] + (d, d)) if top >= 2 else None
        return c0, c1, c2


class _Drift(eqx.Module):
    """``(a(x), 0)``: the system's drift, none on the controls."""

    drift: Callable = eqx.field(static=True)
    size: int = eqx.field(static=True)

    def __call__(self, t, y, params):
        a = self.drift(t, y[: y.shape[0] - self.size], params)
        return jnp.concatenate([a, jnp.zeros((self.size,), a.dtype)])


class _Diffusion(eqx.Module):
    """``(b(x), ψ(t, x))``: the system's diffusion, the basis on the controls."""

    diffusion: Callable = eqx.field(static=True)
    basis: _Basis = eqx.field(static=True)
    size: int = eqx.field(static=True)

    def __call__(self, t, y, params):
        x = y[: y.shape[0] - self.size]
        b = self.diffusion(t, x, params)
        return jnp.concatenate([b, self.basis(t, x, params, b)])


class _OnState(eqx.Module):
    """An observable of the system read from the augmented state."""

    fn: Callable = eqx.field(static=True)
    size: int = eqx.field(static=True)

    def __call__(self, t, y, params):
        return self.fn(t, y[: y.shape[0] - self.size], params)


class _Fitted(eqx.Module):
    """The system's parameters with the fitted rows' coefficients, which are data (one program for every fit)."""

    inner: Any
    coefficients: tuple

    def replace(self, **changes):
        return _Fitted(self.inner.replace(**changes), self.coefficients)

    def __getattr__(self, name):
        if name.startswith("_") or name in ("inner", "coefficients"):
            raise AttributeError(name)
        return getattr(self.inner, name)


class _Unwrapped(eqx.Module):
    """A drift or observable of the system called with the parameters inside :class:`_Fitted`."""

    fn: Callable = eqx.field(static=True)

    def __call__(self, t, y, params):
        return self.fn(t, y, params.inner)


class _FittedDiffusion(eqx.Module):
    """``(b(x), Z_r(t, x))``: the system's diffusion and the fitted combinations ``Z_r = Σ_k β_rk ψ_k`` only."""

    diffusion: Callable = eqx.field(static=True)
    basis: _Basis = eqx.field(static=True)
    size: int = eqx.field(static=True)

    def __call__(self, t, y, params):
        x = y[: y.shape[0] - self.size]
        b = self.diffusion(t, x, params.inner)
        powers = self.basis.powers(t, b.dtype)
        if self.basis.user is not None:
            (weights,) = params.coefficients  # (R, J, K)
            psi = jnp.asarray(self.basis.user(t, x, params.inner), b.dtype)
            z = jnp.einsum("j,rjk->rk", powers, weights) @ psi
        else:
            c0, c1, c2 = params.coefficients
            gradient = jnp.einsum("j,rjn->rn", powers, c0)
            if c1 is not None:
                gradient = gradient + jnp.einsum("j,rjnl,l->rn", powers, c1, x)
            if c2 is not None:
                gradient = gradient + jnp.einsum("j,rjnlp,l,p->rn", powers, c2, x, x)
            rows = np.asarray(self.basis.noisy or range(x.shape[0]))
            z = gradient @ b[rows]
        return jnp.concatenate([b, z])


def fitted_system(augmented: StochasticSystem, d: int, beta) -> StochasticSystem:
    """The Itô system of :func:`martingale_system` ``augmented`` (``d`` the system's components) with only the
    fitted combinations ``M̃_r = Σ_k β_rk M_k`` (``β (R, K)``, outside the derivative) as extra components, named
    ``'@martingale<r>'``; the same increments' control, at the cost of ``R`` rows instead of ``K``."""
    diffusion = augmented.diffusion_fn
    assert isinstance(diffusion, _Diffusion)
    basis, r = diffusion.basis, beta.shape[0]
    beta = jax.lax.stop_gradient(beta)
    if basis.user is not None:
        coefficients = (beta.reshape(r, basis.time_degree + 1, -1),)
    else:
        coefficients = basis.polynomial(beta)
    drift = augmented.drift_fn
    assert isinstance(drift, _Drift)
    return StochasticSystem(
        drift_fn=_Drift(_Unwrapped(drift.drift), r),
        diffusion_fn=_FittedDiffusion(diffusion.diffusion, basis, r),
        params=_Fitted(augmented.params, coefficients),
        layout=StateLayout(
            augmented.layout.names[:d] + tuple(f"{_CONTROL}{k}" for k in range(r)),
            augmented.layout.roles[:d] + ("independent_coordinate",) * r,
            augmented.layout.angles,
        ),
        noise_dim=augmented.noise_dim,
        interpretation="ito",
        additive_noise=False,
        observables=tuple((name, _OnState(_Unwrapped(cast(_OnState, fn).fn), r)) for name, fn in augmented.observables),
        noise=augmented.noise,
    )


def _noisy_rows(system: StochasticSystem, y0) -> tuple[int, ...]:
    """Rows of ``b`` not zero at ``y0`` or at a perturbed state (traced values read as ones); all where unknown."""
    d = system.state_dim
    concrete = lambda v: v if is_concrete(v) else np.ones(np.shape(v))  # noqa: E731
    with jax.ensure_compile_time_eval():
        try:
            params = jax.tree.map(concrete, system.params)
            x = np.asarray(concrete(y0), np.float64)
            rows = np.zeros(d, bool)
            for z in (x, x + 0.37 * (1.0 + np.arange(d))):
                b = np.asarray(system.diffusion_fn(jnp.zeros((), y0.dtype), jnp.asarray(z, y0.dtype), params))
                rows |= ~np.all(b == 0, axis=1) | ~np.all(np.isfinite(b), axis=1)
        except Exception:  # a diffusion that cannot run eagerly: keep every row
            return tuple(range(d))
    noisy = tuple(int(i) for i in np.nonzero(rows)[0])
    return noisy or tuple(range(d))  # no noise at these parameters (ν = 0): keep every row


def _basis(system: StochasticSystem, y0, basis, time_degree: int, t0: float, t1: float) -> _Basis:
    if callable(basis):
        shape = jax.eval_shape(basis, jnp.zeros((), y0.dtype), y0, system.params)
        if len(getattr(shape, "shape", ())) != 2 or shape.shape[1] != system.noise_dim or shape.shape[0] < 1:
            raise ValueError(
                f"basis={basis!r} returns shape {getattr(shape, 'shape', shape)}; a callable basis returns "
                f"(K, noise_dim) = (K, {system.noise_dim}) rows ψ_k of Z = Σ β_k ψ_k."
            )
        return _Basis((), basis, time_degree, t0, t1, ())
    if basis not in _BASES:
        raise ValueError(
            f"basis={basis!r}; allowed: {', '.join(map(repr, _BASES))} (gradients of monomials of the state of that "
            "degree times b) or a callable (t, x, params) -> (K, noise_dim)."
        )
    noisy = _noisy_rows(system, y0)
    exponents = _monomials(system.state_dim, _BASES.index(basis) + 1, noisy)
    return _Basis(exponents, None, time_degree, t0, t1, noisy)


def _size(basis: _Basis, system: StochasticSystem, y0) -> int:
    if basis.user is not None:
        k = jax.eval_shape(basis.user, jnp.zeros((), y0.dtype), y0, system.params).shape[0]
    else:
        k = len(basis.exponents)
    return k * (basis.time_degree + 1)


def martingale_system(
    system: StochasticSystem, y0, basis="quadratic", *, time_degree: int = 2, t0: float = 0.0, t1: float = 1.0
) -> StochasticSystem:
    """``system`` (in Itô form) with the controls ``M_k = ∫ ψ_k(t, X)·dW`` as extra state components (module), named
    ``'@martingale<k>'`` after the system's; its initial state is ``(y0, 0)``.  ``basis``: ``'linear'``,
    ``'quadratic'``, ``'cubic'`` or a callable ``(t, x, params) -> (K, noise_dim)``; ``τ = (t − t0)/(t1 − t0)``."""
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    time_degree = check_number("time_degree", time_degree, integer=True)
    if not 0 <= time_degree <= 4:
        raise ValueError(f"time_degree={time_degree}; allowed: 0 … 4 (powers of τ = (t − t0)/(t1 − t0)).")
    ito = system.converted("ito")
    y0 = ito.state(y0, "y0")
    made = _basis(ito, y0, basis, time_degree, float(t0), float(t1))
    size = _size(made, ito, y0)
    names = ito.layout.names + tuple(f"{_CONTROL}{k}" for k in range(size))
    roles = ito.layout.roles + ("independent_coordinate",) * size
    return StochasticSystem(
        drift_fn=_Drift(ito.drift_fn, size),
        diffusion_fn=_Diffusion(ito.diffusion_fn, made, size),
        params=ito.params,
        layout=StateLayout(names, roles, ito.layout.angles),
        noise_dim=ito.noise_dim,
        interpretation="ito",
        additive_noise=False,
        observables=tuple((name, _OnState(fn, size)) for name, fn in ito.observables),
        noise=ito.noise,
    )


# ----------------------------------------------------------------------------- the fit and the estimate


def check_martingale_solver(solver):
    euler = (isinstance(solver, str) and solver == "euler") or type(solver) is dfx.Euler
    weak = (isinstance(solver, str) and solver == "weak2") or isinstance(solver, PlatenWeak2)
    if not (euler or weak):
        raise ValueError(
            f"solver={solver!r}; allowed: 'euler', 'weak2' or nhsde.PlatenWeak2(increments=...): schemes whose "
            "increment of the control Σ Z(Xₙ)·ΔWₙ has mean exactly zero given the past (Heun and Milstein "
            "evaluate Z at predicted states, which biases the control at the scheme's order)."
        )


def _targets(y, c):
    """Per-path ``(Y, F)``, ``F = (Y − c)(Y − c)ᵀ``: ``(N, n, k)``, ``(N, n, k, k)``."""
    f = y - c
    return y, f[..., :, None] * f[..., None, :]


def fit_coefficients(y, m):
    """``(β_mean (n, k, K), β_cov (n, k, k, K), c (n, k))`` minimising the sample variances of ``Y − β·M`` and
    ``F − β·M`` (``F`` about the means ``c`` of ``y``) at each save time, from pilot values ``y (N, n, k)`` and
    controls ``m (N, n, K)`` (module); outside the derivative."""
    xp = array_module(y, m)
    if xp is np:
        y, m = np.asarray(y, np.float64), np.asarray(m, np.float64)
    else:
        y, m = jax.lax.stop_gradient(y), jax.lax.stop_gradient(m)
    n_paths, n, k = y.shape
    c = xp.mean(y, axis=0)
    values, products = _targets(y, c)
    targets = xp.concatenate([values, products.reshape(n_paths, n, k * k)], axis=-1)
    mc = m - xp.mean(m, axis=0)
    scale = xp.sqrt(xp.mean(mc**2, axis=0))  # (n, K)
    live = scale > 0
    z = mc / xp.where(live, scale, 1.0)
    gram = xp.einsum("pnk,pnl->nkl", z, z) / n_paths
    cross = xp.einsum("pnk,pnq->nkq", z, targets - xp.mean(targets, axis=0)) / n_paths
    beta = xp.linalg.pinv(gram, rtol=_RCOND, hermitian=True) @ cross  # (n, K, q)
    beta = xp.where(live[..., None], beta / xp.where(live, scale, 1.0)[..., None], 0.0)
    beta = beta.swapaxes(-1, -2)  # (n, q, K)
    return beta[:, :k], beta[:, k:].reshape(n, k, k, -1), c


def controlled_moments(y, m, beta_mean, beta_cov, c):
    """``(mean, cov, mean_var, cov_var)`` of the controlled estimates (module) from values ``y (N, n, k)`` and
    controls ``m (N, n, K)`` of the run's paths."""
    xp = array_module(y, m, beta_mean)
    n_paths = y.shape[0]
    values, products = _targets(y, c)
    yc = values - xp.einsum("nkK,pnK->pnk", beta_mean, m)
    fc = products - xp.einsum("nijK,pnK->pnij", beta_cov, m)
    mean = xp.mean(yc, axis=0)
    mean_var = xp.var(yc, axis=0, ddof=1) / n_paths
    d = mean - c
    dev = yc - mean
    sample = xp.einsum("pni,pnj->nij", dev, dev) / (n_paths - 1)
    cov = xp.mean(fc, axis=0) - d[..., :, None] * d[..., None, :] + sample / n_paths
    influence = fc - d[..., None, :] * yc[..., :, None] - d[..., :, None] * yc[..., None, :]
    cov_var = xp.var(influence, axis=0, ddof=1) / n_paths
    return mean, cov, mean_var, cov_var


def controlled_sensitivities(y, m, t_y, t_m, beta_mean, beta_cov, c):
    """``(d_mean, d_cov, d_mean_var, d_cov_var)``: derivatives of :func:`controlled_moments` with ``β`` and ``c``
    fixed, from tangents ``t_y (p, N, n, k)``, ``t_m (p, N, n, K)``, with the squared standard errors of their
    per-path influences."""
    xp = array_module(y, m, t_y, t_m, beta_mean)
    n_paths = y.shape[0]
    yc = y - xp.einsum("nkK,pnK->pnk", beta_mean, m)
    f = y - c
    ty = t_y - xp.einsum("nkK,apnK->apnk", beta_mean, t_m)
    tf = t_y[..., :, None] * f[..., None, :] + f[..., :, None] * t_y[..., None, :]
    tf = tf - xp.einsum("nijK,apnK->apnij", beta_cov, t_m)
    d_mean = xp.mean(ty, axis=1)
    d_mean_var = xp.var(ty, axis=1, ddof=1) / n_paths
    d, dd = xp.mean(yc, axis=0) - c, d_mean
    dev, tdev = yc - xp.mean(yc, axis=0), ty - d_mean[:, None]
    d_sample = (xp.einsum("apni,pnj->anij", tdev, dev) + xp.einsum("pni,apnj->anij", dev, tdev)) / (n_paths - 1)
    outer = dd[..., :, None] * d[..., None, :] + d[..., :, None] * dd[..., None, :]
    d_cov = xp.mean(tf, axis=1) - outer + d_sample / n_paths
    influence = (
        tf
        - dd[:, None, :, None, :] * yc[None, ..., :, None]
        - d[None, None, :, None, :] * ty[..., :, None]
        - dd[:, None, :, :, None] * yc[None, ..., None, :]
        - d[None, None, :, :, None] * ty[..., None, :]
    )
    d_cov_var = xp.var(influence, axis=1, ddof=1) / n_paths
    return d_mean, d_cov, d_mean_var, d_cov_var


def _fitted_rows(n_save: int, k: int):
    """``(select_mean (n, k, R), select_cov (n, k, k, R))``: 0/1 maps of each saved mean and covariance entry after
    ``t0`` to its fitted combination ``r`` (a covariance's ``(i, j)`` and ``(j, i)`` share one), ``R = (n − 1)
    (k + k(k + 1)/2)``; at ``t0`` every control is 0.  ``None`` for a single save."""
    if n_save < 2:
        return None
    pairs = [(i, j) for i in range(k) for j in range(i, k)]
    per = k + len(pairs)
    r = (n_save - 1) * per
    select_mean, select_cov = np.zeros((n_save, k, r)), np.zeros((n_save, k, k, r))
    for s in range(1, n_save):
        base = (s - 1) * per
        for q in range(k):
            select_mean[s, q, base + q] = 1.0
        for p, (i, j) in enumerate(pairs):
            select_cov[s, i, j, base + k + p] = select_cov[s, j, i, base + k + p] = 1.0
    return select_mean, select_cov


def _upper(select_cov):
    """``select_cov`` with only the upper triangle ``i ≤ j`` kept: one ``β`` per fitted combination."""
    return select_cov * np.triu(np.ones(select_cov.shape[1:3]))[None, :, :, None]


def _reduction(plain, controlled):
    xp = array_module(plain, controlled)
    return xp.where(controlled > 0, plain / xp.where(controlled > 0, controlled, 1.0), xp.where(plain > 0, xp.inf, 1.0))


class MartingaleControl:
    """The martingale control inside multilevel Monte Carlo (``control='martingale'``): each saved mean entry ``Y``
    after ``t0`` gets ``M̃ = Σₙ Z(tₙ, Xₙ)·ΔWₙ``, ``Z = β·ψ`` fitted (:func:`fit_coefficients`) on ``n_pilot``
    independent paths at the coarsest step ``h₀``, then held fixed.  Each discretisation's ``M̃``, on its own
    increments (:func:`fitted_system`), has mean exactly zero, so any level may use it or not and the levels still
    telescope to ``E Y_L``, with no term to add at level 0.  Level 0 always does.  The level differences (fine −
    coarse) use it per entry where it lowered the variance of the first difference ``(h₀/2, h₀)`` on another
    ``n_pilot`` independent paths: the fine and coarse controls differ at the scheme's strong order, which can add
    more variance than they remove (measured on Chaplygin's ball's energy with weak order 2, and on the sleigh with
    Euler); where no entry uses it there, those levels solve the system alone.  In the interface of
    :class:`~nhsde.statistics._control_variate.LinearisedControl` inside the levels: the control's sets, the
    coefficients per level (``1`` or ``0`` on each mean, ``0`` on the covariances, not controlled) and its exact
    moments ``(0, 0)``."""

    def __init__(self, system: StochasticSystem, y0, key, run: RunOptions, n_pilot: int | None = None):
        check_martingale_solver(run.solver)
        assert run.save is not None and run.save.names is not None and run.save.n is not None
        self.names, n_save, k = run.save.names, run.save.n, len(run.save.names)
        self.plain, y0 = system, system.state(y0, "y0")
        self.y0 = y0
        augmented = martingale_system(system, y0, "quadratic", time_degree=2, t0=run.t0, t1=run.t1)
        size = augmented.state_dim - system.state_dim
        self.n_pilot = RUN_PATHS * max(1, math.ceil(10 * size / RUN_PATHS)) if n_pilot is None else n_pilot
        controls = augmented.layout.names[system.state_dim :]
        pilot_run = dataclasses.replace(run, save=Save(names=self.names + controls, n=n_save, paths=True))
        start = jnp.concatenate([y0, jnp.zeros((size,), y0.dtype)])
        pilot = solve_paths(augmented, start, fold_key(key, _PILOT_FOLD), pilot_run, first_path=0, n_paths=self.n_pilot)
        beta_mean = fit_coefficients(pilot[..., :k], pilot[..., k:])[0]  # (n, k, K)
        del pilot
        xp = array_module(beta_mean)
        self.select = np.zeros((n_save, k, max(n_save - 1, 0) * k))  # entry (s, q) → its combination r
        for s_, q in itertools.product(range(1, n_save), range(k)):
            self.select[s_, q, (s_ - 1) * k + q] = 1.0
        rows = xp.einsum("nqr,nqK->rK", self.select, beta_mean)
        if xp is not np:
            rows = jax.lax.stop_gradient(rows)
        self.system = fitted_system(augmented, system.state_dim, jnp.asarray(rows, y0.dtype))
        self.start = jnp.concatenate([y0, jnp.zeros((rows.shape[0],), y0.dtype)])
        self.coefficient = PerEntry(mean=beta_mean, cov=xp.zeros((n_save, k, k, beta_mean.shape[-1])))
        self.finer = np.ones((n_save, k))  # the level differences' use of the control, per mean entry
        h0 = run.dt
        first = dict(dts=(h0 / 2, h0), brownian_dt=h0 / 2, n_paths=self.n_pilot, antithetic=False)
        (fine, coarse, m_fine, m_coarse), _ = self.sets(1, fold_key(key, _PILOT_FOLD + 1), run, **first)
        xp = array_module(fine)  # traced under jax transformations: then every level solves the control
        plain_var = xp.var(fine - coarse, axis=0)
        controlled_var = xp.var((fine - m_fine) - (coarse - m_coarse), axis=0)
        self.finer = xp.where(controlled_var < plain_var, 1.0, 0.0)
        self.pilot_path_steps = float(self.n_pilot * run.n_steps * (1 + 2 + 1))  # the fit; the first difference

    def sets(self, level: int, key, run: RunOptions, **options) -> tuple[list, list]:
        """:func:`~nhsde.statistics._paths.coupled_paths` of level ``level``: the system's sets, then the controls'
        sets ``M̃`` of each entry ``(N, n, k)`` (tangents likewise); zeros where the level does not use them."""
        assert run.save is not None
        k = len(self.names)
        if level and is_concrete(self.finer) and not np.any(self.finer):  # no difference uses it: the system alone
            paths, tangents = coupled_paths(self.plain, self.y0, key, run, **options)
            xp = array_module(paths)
            return paths + [xp.zeros_like(z) for z in paths], tangents + [xp.zeros_like(t) for t in tangents]
        fitted = self.system.layout.names[self.start.shape[0] - self.select.shape[-1] :]
        run = dataclasses.replace(run, save=dataclasses.replace(run.save, names=self.names + fitted))
        paths, tangents = coupled_paths(self.system, self.start, key, run, **options)
        split = lambda z: (z[..., :k], array_module(z).einsum("nqr,...nr->...nq", self.select, z[..., k:]))  # noqa: E731
        values, controls = zip(*map(split, paths), strict=True)
        out_tangents: list = []
        if tangents:
            t_values, t_controls = zip(*map(split, tangents), strict=True)
            out_tangents = list(t_values) + list(t_controls)
        return list(values) + list(controls), out_tangents

    def coefficients(self, level: int):
        """``(β_mean, β_cov)`` on level ``level``'s control sets: ``1`` on every mean at level 0 (``M̃`` carries its
        fitted ``β``), on the level differences ``1`` where the control pays there, else ``0``; ``0`` on the
        covariances (not controlled)."""
        n, k = self.select.shape[:2]
        return (self.finer if level else np.ones((n, k))), np.zeros((n, k, k))

    def exact(self, system, names, t0, t1, n_steps, n_save, wrt, on_host):
        """The control's exact moments: zero, and so their tangents."""
        zeros = (np.linspace(t0, t1, n_save), np.zeros((n_save, len(names))), np.zeros((n_save,) + (len(names),) * 2))
        return zeros, (zeros if wrt else None)


def martingale_control_variate(
    system: StochasticSystem,
    y0,
    key,
    statistic,
    *,
    n_paths: int,
    t1: float | None = None,
    dt: float | None = None,
    steps: AbstractSteps | None = None,
    t0: float | None = None,
    n_pilot: int | None = None,
    solver=None,
    basis="quadratic",
    time_degree: int = 2,
    save: Save | None = None,
    batching: Batching | None = None,
    run: RunOptions | None = None,
    wrt=None,
) -> ControlVariateEstimate:
    """Means and covariances with the martingale control ``Σₙ Zₙ(Xₙ)·ΔWₙ`` fitted on an independent pilot (module).

    ``statistic``: :class:`Mean` or :class:`Covariance` (or ``('mean', name)``, ``('cov', a, b)``), the estimate's
    default for ``value()``; ``save`` defaults to its names at ``t0`` and ``t1``, and every saved mean and covariance
    entry gets its own control.  The run's options as :func:`~nhsde.simulate`'s (``run=`` or its keywords), fixed
    steps (``dt`` or ``steps=FixedSteps(dt)``); ``solver``: ``'euler'``,
    ``'weak2'`` or :class:`~nhsde.PlatenWeak2` (either increments).  ``basis``: ``'linear'``, ``'quadratic'``
    (default) or ``'cubic'`` (gradients of monomials of the state times ``b``), or a callable
    ``(t, x, params) -> (K, noise_dim)``; times ``τʲ``, ``j ≤ time_degree``.  ``n_pilot``: the fit's paths
    (default ``10 K`` rounded up to 1024s, whose excess variance from the fit is about ``K/n_pilot``;
    paths ``n_paths …`` of ``key``).  ``wrt``: scalar parameter names whose
    derivatives (``β`` fixed) are returned with standard errors; ``jax.grad`` through the estimate works too.

    Returns a :class:`ControlVariateEstimate`: ``plain`` the uncontrolled estimate of the same paths,
    ``coefficient`` ``β`` per entry (trailing axis ``K``), ``variance_reduction`` per entry, ``control`` the
    control's exact mean (zero); ``cost`` the path-steps of pilot and run.
    """
    watch = Stopwatch()
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    statistic = as_statistic(statistic)
    wrt = () if wrt is None else check_wrt(system, wrt)
    (n_paths,) = checked_paths("n_paths", n_paths)
    options = run_options(
        "martingale_control_variate",
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
    check_martingale_solver(options.solver)
    solver_needs(options.solver, system)
    y0 = system.state(y0, "y0")
    n_steps = options.n_steps
    save = options.save
    save = paths_save(Save(names=statistic.names, n=2) if save is None else save, n_steps, statistic.names)
    assert save.names is not None and save.n is not None
    names = save.names
    system.observe(names)  # unknown names raise naming save
    statistic.check(names)
    augmented = martingale_system(system, y0, basis, time_degree=time_degree, t0=options.t0, t1=options.t1)
    size = augmented.state_dim - system.state_dim
    if n_pilot is None:
        n_pilot = RUN_PATHS * max(1, math.ceil(10 * size / RUN_PATHS))
    (n_pilot,) = checked_paths("n_pilot", n_pilot)
    if n_pilot < 2 * size:
        raise ValueError(
            f"n_pilot={n_pilot}; the fit of {size} coefficients per entry needs ≥ {2 * size} pilot paths "
            f"(take ≥ {20 * size}, or a smaller basis or time_degree)."
        )
    key = check_key(key)
    controls = tuple(augmented.layout.names[system.state_dim :])
    check_memory(
        f"n_paths={n_paths}",
        peak_bytes(max(n_paths, n_pilot) * path_bytes(save.n, len(names) + size, len(wrt))),
        "take fewer paths, or average runs of several keys.",
    )
    run = dataclasses.replace(options, save=Save(names=names + controls, n=save.n, paths=True))
    start = jnp.concatenate([y0, jnp.zeros((size,), y0.dtype)])
    k = len(names)

    pilot = solve_paths(augmented, start, key, run, first_path=n_paths, n_paths=n_pilot)
    beta_mean, beta_cov, c = fit_coefficients(pilot[..., :k], pilot[..., k:])
    del pilot
    if array_module(beta_mean) is not np:
        beta_mean, beta_cov, c = (jax.lax.stop_gradient(jnp.asarray(a, y0.dtype)) for a in (beta_mean, beta_cov, c))
    # the run: each entry's control β·M is read from M (K components), or where fewer, from the fitted combinations
    # M̃_r = β_r·M (R components) that the run accumulates alone; then "β" of the run selects each entry's M̃_r
    solved, run_beta_mean, run_beta_cov = augmented, beta_mean, beta_cov
    selection = _fitted_rows(save.n, k)
    if selection is not None and selection[0].shape[-1] < size:
        run_beta_mean, run_beta_cov = selection
        xp = array_module(beta_mean)
        rows = xp.einsum("nqr,nqK->rK", run_beta_mean, beta_mean)  # each row is one entry's β at one save time
        rows = rows + xp.einsum("nijr,nijK->rK", _upper(run_beta_cov), beta_cov)
        solved = fitted_system(augmented, system.state_dim, jnp.asarray(rows, y0.dtype))
        fitted = tuple(solved.layout.names[system.state_dim :])
        run = dataclasses.replace(run, save=Save(names=names + fitted, n=save.n, paths=True))
        start = jnp.concatenate([y0, jnp.zeros((len(fitted),), y0.dtype)])
    paths, tangents = solve_paths_with_tangents(solved, start, key, run, wrt, first_path=0, n_paths=n_paths)
    xp = array_module(paths, beta_mean)
    if xp is np:
        paths = np.asarray(paths, np.float64)
    else:
        run_beta_mean, run_beta_cov = (jnp.asarray(a, paths.dtype) for a in (run_beta_mean, run_beta_cov))
    y, m = paths[..., :k], paths[..., k:]
    mean, cov, mean_var, cov_var = controlled_moments(y, m, run_beta_mean, run_beta_cov, c)
    plain_mean, plain_cov, plain_mean_var, plain_cov_var = paired_moments([y], [1.0])
    derivatives = None
    if wrt:
        assert tangents is not None
        t_y, t_m = tangents[..., :k], tangents[..., k:]
        if xp is np:
            t_y, t_m = np.asarray(t_y, np.float64), np.asarray(t_m, np.float64)
        d_mean, d_cov, d_mean_var, d_cov_var = controlled_sensitivities(y, m, t_y, t_m, run_beta_mean, run_beta_cov, c)
        derivatives = Derivatives(d_mean, d_cov, safe_sqrt(d_mean_var), safe_sqrt(d_cov_var), wrt)

    ts = xp.linspace(options.t0, options.t1, save.n)
    count, roles = jax.device_put(np.asarray(n_paths)), roles_of(system, names)
    plain = MonteCarloEstimate(
        ts=ts,
        mean=plain_mean,
        cov=plain_cov,
        mean_se=safe_sqrt(plain_mean_var),
        cov_se=safe_sqrt(plain_cov_var),
        n_paths=count,
        names=names,
        roles=roles,
        derivatives=None,
        cost=Cost(float(n_paths * n_steps)),
        statistic=statistic,
    )
    estimate = ControlVariateEstimate(
        ts=ts,
        mean=mean,
        cov=cov,
        mean_se=safe_sqrt(mean_var),
        cov_se=safe_sqrt(cov_var),
        plain=plain,
        coefficient=PerEntry(mean=beta_mean, cov=beta_cov),
        variance_reduction=PerEntry(mean=_reduction(plain_mean_var, mean_var), cov=_reduction(plain_cov_var, cov_var)),
        control=PerEntry(mean=xp.zeros_like(mean), cov=xp.zeros_like(cov)),
        derivatives=derivatives,
        n_paths=count,
        names=names,
        roles=roles,
        cost=watch.cost((n_paths + n_pilot) * n_steps),
        statistic=statistic,
    )
    return on_device(estimate, y0.dtype)
