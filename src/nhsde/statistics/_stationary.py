"""Exact stationary densities of normal systems: S0 Statements 1–2, (4.1) and (4.3).

For the components ``x`` of the state other than the dependent coordinates
``q''`` (which drift and have no stationary law), write the Itô system as
``dx = f(x) dt + B(x) dW``, ``D = BBᵀ``, and let ``f₀`` be ``f`` with friction
and noise switched off (the parameters ``friction`` and ``noise`` set to 0).
Then ``f₁(x) = c N(x) exp(−α H(x))`` is a stationary density if

1. the system is normal (Wiener noise) and ``x`` does not depend on ``q''``;
2. ``H`` is a first integral of ``ẋ = f₀``: ``f₀·∇H = 0``;
3. ``N`` is an invariant density of ``ẋ = f₀``: ``∇·(N f₀) = 0`` (Statement 1:
   ``N = 1``, Liouville; Statement 2: the given ``N``);
4. the rest ``F = f − f₀`` is friction proportional to ``bbᵀ`` (S0 condition 1,
   ``a + aᵀ = 2bbᵀ``): the zero-flux balance ``F ρ = ½ ∇·(Dρ)`` projected on
   ``∇H`` gives ``α(x) = −2 (F − ½∇·D − ½ D∇log N)·∇H / (∇Hᵀ D ∇H)``, which must
   be one positive constant (``α = 4ε/ν`` when ``a_sym = bbᵀ``, S0 (4.1)), and
   the stationary Fokker–Planck residual of ``N e^{−αH}`` (S0 (2.2)) must vanish
   (the antisymmetric part of the friction must conserve it);
5. ``∫ N exp(−αH) dx < ∞`` (S0 condition 3).

:func:`stationary_density` checks 1–5 numerically at test points, one function each, and raises a
``ValueError`` naming the first condition that fails.  In low dimension
(``len(x) ≤ 3``) ``c``, the mean and the covariance come from tensor
Gauss–Legendre quadrature on ``x = c₀ + s tan θ``, checked for convergence.
(S0's condition 2, ``|∂Λ/∂x'| ≠ 0``, concerns the law of ``q̇''`` in (4.1), not
``f₁`` itself.)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, NoReturn

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from .._brownian import Wiener
from .._system import StochasticSystem
from ._drift import StationaryMoments

__all__ = ["StationaryDensity", "stationary_density"]

MAX_QUADRATURE_DIM = 3


class StationaryDensity(eqx.Module):
    """``f₁(x) = c N(x) exp(−α H(x))`` over the components ``names``.

    ``log_normaliser = −log c`` and the moments are ``None`` above
    :data:`MAX_QUADRATURE_DIM` dimensions (then the density is known up to ``c``).
    """

    alpha: Float[Array, ""]
    log_normaliser: Float[Array, ""] | None
    mean: Float[Array, " k"] | None
    cov: Float[Array, "k k"] | None
    params: PyTree
    hamiltonian: Callable = eqx.field(static=True)
    invariant_density: Callable | None = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)

    def log_unnormalised(self, x) -> Array:
        """``log N(x) − α H(x)`` for ``x`` of shape ``(..., k)``."""
        x = jnp.asarray(x)
        flat = x.reshape(-1, x.shape[-1])
        values = jax.vmap(lambda z: _log_weight(self.hamiltonian, self.invariant_density, self.params, self.alpha, z))(
            flat
        )
        return values.reshape(x.shape[:-1])

    def log_pdf(self, x) -> Array:
        if self.log_normaliser is None:
            raise ValueError(
                f"the normalising constant is known only up to {MAX_QUADRATURE_DIM} dimensions "
                f"(here {len(self.names)}); use log_unnormalised."
            )
        return self.log_unnormalised(x) - self.log_normaliser

    def pdf(self, x) -> Array:
        return jnp.exp(self.log_pdf(x))

    def moments(self) -> StationaryMoments:
        """Mean and covariance of ``f₁`` (by quadrature), as the Monte-Carlo :class:`StationaryMoments`."""
        if self.mean is None or self.cov is None:
            raise ValueError(f"moments by quadrature need ≤ {MAX_QUADRATURE_DIM} dimensions (here {len(self.names)}).")
        return StationaryMoments(self.mean, self.cov, self.names)


def _log_weight(hamiltonian, invariant_density, params, alpha, x):
    log_n = 0.0 if invariant_density is None else jnp.log(invariant_density(x, params))
    return log_n - alpha * hamiltonian(x, params)


def _refuse(condition: str, detail: str) -> NoReturn:
    raise ValueError(f"stationary_density: {condition} fails: {detail}.")


class _OnX(NamedTuple):
    """The system's coefficients as functions of the components ``x`` (the dependent coordinates at 0)."""

    f: Callable  # the drift
    f0: Callable  # the drift with friction and noise off
    diff: Callable  # D = bbᵀ
    log_n: Callable  # log N
    h: Callable  # H


def stationary_density(
    system: StochasticSystem,
    hamiltonian: Callable,
    *,
    invariant_density: Callable | None = None,
    friction: str = "eps",
    noise: str = "nu",
    points=None,
    rtol: float = 1e-7,
    quadrature_nodes: int | None = None,
) -> StationaryDensity:
    """The exact stationary density ``c N exp(−αH)`` of S0 Statements 1–2, or a ``ValueError`` naming the failing
    condition.

    Arguments:
        system: a normal (Wiener-driven) system; its dependent coordinates are left out.
        hamiltonian: ``hamiltonian(x, params)``, the first integral ``H`` of the frictionless,
            noiseless flow, ``x`` the state without the dependent coordinates.
        invariant_density: ``invariant_density(x, params) > 0``, ``N`` of Statement 2 (default 1: Statement 1).
        friction, noise: names of the parameters that switch friction and noise off at 0.
        points: test points ``(n, k)`` for the conditions (default: 64 standard normal points).
        rtol: relative tolerance of the checks of conditions 1–4.
        quadrature_nodes: Gauss–Legendre nodes per dimension for the normalising integral; by default they are
            doubled from 96 until the integral converges (at most 2²² points), and a given number is only checked.

    Returns:
        a :class:`StationaryDensity` with ``alpha``, ``pdf``/``log_pdf`` and, up to three dimensions, the
        normaliser and moments.

    Raises:
        ValueError: naming the first of the conditions 1–5 that fails.

    Examples:
        The ball's velocity (S0 (3.1)) with ``H = |u|²/2``: ``α = 4ε/(νδ²)``, S0 (4.1):

        >>> import nhsde
        >>> system = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0, drift=False).build()
        >>> rho = nhsde.statistics.stationary_density(system, lambda x, p: 0.5 * (x[0] ** 2 + x[1] ** 2))
        >>> print(round(float(rho.alpha), 4), round(4 / (5 / 7) ** 2, 4))
        7.84 7.84
        >>> print(rho.moments().cov.diagonal().round(4))
        [0.1276 0.1276]
    """
    system = _normal_ito_system(system)
    layout = system.layout
    x_idx = np.asarray([i for i, r in enumerate(layout.roles) if r != "dependent_coordinate"])
    dep = np.asarray(layout.indices("dependent_coordinate"), dtype=int)
    names = tuple(layout.names[i] for i in x_idx)
    k = len(x_idx)
    params = system.params
    try:
        params0 = params.replace(**{friction: 0.0, noise: 0.0})
    except (AttributeError, TypeError) as err:
        raise ValueError(
            f"friction={friction!r}, noise={noise!r}: the system's parameters must have both, to "
            f"switch them off ({err})."
        ) from None
    dtype = jnp.result_type(float)
    pts = jax.random.normal(jax.random.key(0), (64, k), dtype) if points is None else jnp.asarray(points, dtype)
    if pts.ndim != 2 or pts.shape[1] != k:
        raise ValueError(f"points has shape {pts.shape}; expected (n, {k}) over {names}.")
    on_x = _on_x(system, x_idx, params, params0, hamiltonian, invariant_density)

    _check_decoupling(system, x_idx, dep, pts, rtol)  # 1.
    grad_h, f0_pts, jac_nf0, alphas = _at_points(on_x, pts)
    _check_first_integral(grad_h, f0_pts, pts, rtol)  # 2.
    _check_invariant_density(jac_nf0, pts, rtol, statement=1 if invariant_density is None else 2)  # 3.
    alpha = _friction_exponent(on_x, alphas, pts, rtol)  # 4.

    def log_rho(x):
        return on_x.log_n(x) - alpha * on_x.h(x)

    _check_integrability(log_rho, k, dtype)  # 5.
    log_c = mean = cov = None
    if k <= MAX_QUADRATURE_DIM:
        log_c, mean, cov = _quadrature(log_rho, k, dtype, quadrature_nodes)
    return StationaryDensity(alpha, log_c, mean, cov, params, hamiltonian, invariant_density, names)


def _normal_ito_system(system) -> StochasticSystem:
    """``system`` in Itô form; a normal system (Wiener noise) is the first part of condition 1."""
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem.")
    if not isinstance(system.noise, Wiener):
        _refuse(
            "normal system (Wiener noise)",
            f"the system is driven by {type(system.noise).__name__}; Statements 1–2 hold for Wiener noise only "
            "(use nhsde.statistics.normal_approximation)",
        )
    if system.interpretation != "ito":
        system = system.converted("ito")
    return system


def _on_x(system, x_idx, params, params0, hamiltonian, invariant_density) -> _OnX:
    size = system.layout.size

    def full(x):
        return jnp.zeros(size, x.dtype).at[x_idx].set(x)

    def f(x):
        return system.drift(0.0, full(x), params)[x_idx]

    def f0(x):
        return system.drift(0.0, full(x), params0)[x_idx]

    def diff(x):
        b = system.diffusion(0.0, full(x), params)[x_idx]
        return b @ b.T

    def log_n(x):
        return jnp.zeros((), x.dtype) if invariant_density is None else jnp.log(invariant_density(x, params))

    def h(x):
        return hamiltonian(x, params)

    return _OnX(f, f0, diff, log_n, h)


def _at_points(on_x: _OnX, pts):
    """``∇H``, ``f₀``, ``∂(N f₀)/∂x`` and the flux-balance ``α`` (condition 4) at each test point, in one program."""

    def n_f0(x):
        return jnp.exp(on_x.log_n(x)) * on_x.f0(x)

    def alpha_at(x):
        gh = jax.grad(on_x.h)(x)
        d = on_x.diff(x)
        div_d = jnp.trace(jax.jacfwd(on_x.diff)(x), axis1=1, axis2=2)
        rest = on_x.f(x) - on_x.f0(x) - 0.5 * div_d - 0.5 * d @ jax.grad(on_x.log_n)(x)
        return -2.0 * (rest @ gh) / (gh @ d @ gh)

    @jax.jit
    def conditions(pts):
        return (
            jax.vmap(jax.grad(on_x.h))(pts),
            jax.vmap(on_x.f0)(pts),
            jax.vmap(jax.jacfwd(n_f0))(pts),
            jax.vmap(alpha_at)(pts),
        )

    return conditions(pts)


def _check_decoupling(system, x_idx, dep, pts, rtol) -> None:
    """Condition 1 (Chaplygin decoupling): the drift and noise of ``x`` do not depend on ``q''``."""
    if not dep.size:
        return
    params, size = system.params, system.layout.size

    def x_part(z):
        return system.drift(0.0, z, params)[x_idx], system.diffusion(0.0, z, params)[x_idx]

    def full(x):
        return jnp.zeros(size, x.dtype).at[x_idx].set(x)

    jac = jax.jit(jax.vmap(lambda x: jax.jacfwd(x_part)(full(x))))(pts)
    coupling = max(float(jnp.max(jnp.abs(j[..., dep]))) for j in jac)
    scale = max(float(jnp.max(jnp.abs(j))) for j in jac)
    if coupling > rtol * scale:
        layout = system.layout
        _refuse(
            "Chaplygin decoupling",
            f"the drift or noise of {tuple(layout.names[i] for i in x_idx)} depends on "
            f"{tuple(layout.names[i] for i in dep)}",
        )


def _check_first_integral(grad_h, f0_pts, pts, rtol) -> None:
    """Condition 2: ``H`` is a first integral of the frictionless, noiseless flow, ``f₀·∇H = 0``."""
    power = jnp.sum(f0_pts * grad_h, axis=1)
    ref = jnp.linalg.norm(f0_pts, axis=1) * jnp.linalg.norm(grad_h, axis=1)
    if not bool(jnp.all(jnp.abs(power) <= rtol * ref)):
        worst = int(jnp.argmax(jnp.abs(power) - rtol * ref))
        _refuse(
            "H is a first integral of the frictionless, noiseless flow",
            f"f₀·∇H = {float(power[worst]):.3g} at x = {pts[worst]}",
        )


def _check_invariant_density(jac_nf0, pts, rtol, statement: int) -> None:
    """Condition 3: ``N`` is an invariant density of the frictionless, noiseless flow, ``∇·(N f₀) = 0``."""
    div = jnp.trace(jac_nf0, axis1=1, axis2=2)
    ref = jnp.sqrt(jnp.sum(jac_nf0**2, axis=(1, 2)))
    if not bool(jnp.all(jnp.abs(div) <= rtol * ref)):
        worst = int(jnp.argmax(jnp.abs(div) - rtol * ref))
        which = "N = 1 (Liouville, Statement 1)" if statement == 1 else "the given N (Statement 2)"
        _refuse(
            "invariant measure of the frictionless, noiseless flow",
            f"{which} is not invariant: ∇·(N f₀) = {float(div[worst]):.3g} at x = {pts[worst]}",
        )


def _friction_exponent(on_x: _OnX, alphas, pts, rtol) -> Array:
    """Condition 4, friction proportional to ``bbᵀ``: the flux-balance ``α`` at the test points is one positive
    constant, and ``N e^{−αH}`` solves the stationary Fokker–Planck equation; returns ``α``."""
    alphas = alphas[jnp.isfinite(alphas)]
    if alphas.size == 0:
        _refuse(
            "friction proportional to bbᵀ (S0 condition 1)",
            "∇Hᵀ bbᵀ ∇H = 0 at every test point: the noise does not reach H",
        )
    alpha = jnp.median(alphas)
    spread = float(jnp.max(jnp.abs(alphas - alpha)))
    if not (float(alpha) > 0 and spread <= rtol * abs(float(alpha))):
        _refuse(
            "friction proportional to bbᵀ (S0 condition 1, a + aᵀ = 2bbᵀ)",
            f"the flux-balance α = −2(F − ½∇·D − ½D∇log N)·∇H/(∇Hᵀ D ∇H) ranges over "
            f"[{float(jnp.min(alphas)):.6g}, {float(jnp.max(alphas)):.6g}] at the test points; it "
            "must be one positive constant",
        )

    def log_rho(x):
        return on_x.log_n(x) - alpha * on_x.h(x)

    def fpk_terms(x):
        g, hess = jax.grad(log_rho)(x), jax.hessian(log_rho)(x)
        fx, jf = on_x.f(x), jax.jacfwd(on_x.f)(x)
        d, dd = on_x.diff(x), jax.jacfwd(on_x.diff)(x)  # dd[i, j, l] = ∂_l D_ij
        ddd = jax.jacfwd(jax.jacfwd(on_x.diff))(x)
        return jnp.stack(
            [
                -jnp.trace(jf),
                -fx @ g,
                0.5 * jnp.einsum("ijij->", ddd),
                jnp.einsum("iji,j->", dd, g),
                0.5 * g @ d @ g,
                0.5 * jnp.sum(d * hess),
            ]
        )

    terms = jax.jit(jax.vmap(fpk_terms))(pts)
    residual = jnp.sum(terms, axis=1)
    ref = jnp.sum(jnp.abs(terms), axis=1)
    if not bool(jnp.all(jnp.abs(residual) <= rtol * ref)):
        worst = int(jnp.argmax(jnp.abs(residual) / ref))
        _refuse(
            "friction proportional to bbᵀ (S0 condition 1: the antisymmetric part must conserve N e^{−αH})",
            f"the stationary Fokker–Planck residual of N e^{{−αH}} is {float(residual[worst]):.3g} "
            f"(terms of size {float(ref[worst]):.3g}) at x = {pts[worst]}",
        )
    return alpha


def _check_integrability(log_rho, k, dtype) -> None:
    """Condition 5, ``∫ N exp(−αH) dx < ∞``: ``log ρ`` must fall by more than ``(k + 1) log 2`` per doubling of
    the radius, along every test ray."""
    dirs = np.concatenate([np.eye(k), -np.eye(k), np.random.default_rng(0).normal(size=(16, k))])
    dirs = jnp.asarray(dirs / np.linalg.norm(dirs, axis=1, keepdims=True), dtype)
    radii = jnp.asarray(2.0 ** np.arange(0, 13), dtype)
    values = jax.jit(jax.vmap(lambda u: jax.vmap(lambda r: log_rho(r * u))(radii)))(dirs)  # (rays, radii)
    drops = values[:, -4:-1] - values[:, -3:]
    ok = jnp.where(jnp.isnan(drops), False, drops > (k + 1) * np.log(2.0))
    if not bool(jnp.all(ok)):
        ray = int(np.argmin(np.asarray(jnp.all(ok, axis=1))))
        _refuse(
            "integrability ∫ N exp(−αH) < ∞ (S0 condition 3)",
            f"along the ray x = r·{np.round(np.asarray(dirs[ray]), 3)} log(N e^(−αH)) changes by "
            f"{np.round(np.asarray(-drops[ray]), 3)} per doubling of r at r ≈ {float(radii[-3]):g}; "
            f"it must fall faster than {(k + 1) * np.log(2.0):.3g}",
        )


QUADRATURE_NODES = 96
"""Gauss–Legendre nodes per dimension the normalising integral starts from."""
QUADRATURE_POINTS = 2**22
"""The most quadrature points the automatic refinement uses (nodes per dimension ** dimensions)."""


def _quadrature(log_rho, k, dtype, n):
    """``(log ∫ρ, mean, cov)`` by Gauss–Legendre on ``x = c₀ + s tan θ``; a second pass recentres; the nodes are
    doubled from :data:`QUADRATURE_NODES` until halving them changes ``log ∫ρ`` by at most 1e-8 (``n`` given: that
    many nodes, checked the same way)."""

    def rule(nodes):
        theta, w = np.polynomial.legendre.leggauss(nodes)
        grids = np.meshgrid(*([theta * np.pi / 2] * k), indexing="ij")
        wgrid = np.meshgrid(*([w * np.pi / 2] * k), indexing="ij")
        t = np.stack([g.reshape(-1) for g in grids], -1)
        return jnp.asarray(t, dtype), jnp.asarray(
            np.log(np.prod(np.stack([g.reshape(-1) for g in wgrid], -1), -1)), dtype
        )

    @jax.jit
    def integrate(centre, scale, t, log_w):
        x = centre + scale * jnp.tan(t)
        lw = jax.vmap(log_rho)(x) + jnp.sum(jnp.log(scale / jnp.cos(t) ** 2), axis=-1) + log_w
        top = jnp.max(lw)
        p = jnp.exp(lw - top)
        z = jnp.sum(p)
        mean = p @ x / z
        xc = x - mean
        return top + jnp.log(z), mean, (p[:, None] * xc).T @ xc / z

    given = n is not None
    n = QUADRATURE_NODES if n is None else n
    _, mean, cov = integrate(jnp.zeros(k, dtype), jnp.ones(k, dtype), *rule(n))
    centre, scale = mean, 2 * jnp.sqrt(jnp.diagonal(cov))
    log_z_half, _, _ = integrate(centre, scale, *rule(n // 2))
    while True:  # double the nodes until halving them no longer changes the integral
        log_z, mean, cov = integrate(centre, scale, *rule(n))
        change = float(log_z - log_z_half)
        if abs(change) <= 1e-8:
            return log_z, mean, cov
        if given or (2 * n) ** k > QUADRATURE_POINTS:
            raise ValueError(
                f"stationary_density: the normalising integral did not converge with quadrature_nodes={n} "
                f"(log ∫ changes by {change:.3g} from {n // 2} nodes); pass a larger quadrature_nodes "
                f"(nodes per dimension; {k} dimensions) or rescale the variables."
            )
        n, log_z_half = 2 * n, log_z
