"""The stochastic view of a stable steady motion: stationary spread and residence (exit) time.

Near an asymptotically stable steady state ``z₀`` of the Itô system
``dZ = a dt + b dW`` (S4 Theorem 4.1 with friction, S0 (1.15) with noise) the
deviation ``δ = Z − z₀`` of the components ``x`` is, to leading order in the
noise, the Ornstein–Uhlenbeck process

    dδ = A δ dt + B dW,    A = ∂a_x/∂Z_x (z₀),    B = b_x(z₀),

provided ``a_x`` does not depend on the other components to first order (they
may be cyclic, e.g. the heading, or dependent coordinates ``q''``).

- :func:`stationary_spread`: its stationary covariance ``Σ``, the solution of the
  Lyapunov equation ``A Σ + Σ Aᵀ + B diag(ν) Bᵀ = 0`` (``ν`` the driver's intensity
  per channel, 1 for Wiener noise; the same equation as the stationary
  normal approximation of :mod:`nhsde.statistics`, S0 §6, for a linear system).
- :func:`linear_residence_time`: for one component ``i`` whose linearised row is
  closed (``A_ij = 0``, ``j ≠ i``), ``δ_i`` is a scalar OU process
  ``dδ = −κ δ dt + σ dW`` (``κ = −A_ii``, ``σ² = (BBᵀ)_ii``), and the mean time to
  leave ``|δ| < r`` from ``δ = 0`` solves ``½σ² T'' − κ δ T' = −1``,
  ``T(±r) = 0``: with the scale density ``e^{κδ²/σ²}`` and ``ρ = r√κ/σ``,

      T = (2/σ²) ∫₀ʳ e^{κy²/σ²} ∫₀ʸ e^{−κz²/σ²} dz dy = (√π/κ) ∫₀^ρ e^{y²} erf(y) dy,

  (Brownian limit ``ρ → 0``: ``T → r²/σ²``; Kramers limit ``ρ → ∞``:
  ``T ≈ √π e^{ρ²}/(2κρ)``), evaluated by Gauss–Legendre quadrature, so
  ``jax.grad`` in ``ε`` and ``ν`` works.
- :func:`residence_time`: the same mean exit time by Monte Carlo on the full
  nonlinear system, with the Brownian-bridge correction for monitoring on a grid.

Both linearised quantities differentiate in every parameter leaf of the system.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._params import validated
from .._simulate import Save, _number, _steps, simulate
from .._system import StochasticSystem
from ..noise._brownian import Wiener
from ..noise._levy import driver_intensity
from ._stability import jacobian

__all__ = [
    "LinearResidence",
    "Residence",
    "Spread",
    "linear_residence_time",
    "residence_time",
    "stationary_spread",
]

_NODES = 64  # Gauss–Legendre nodes: 1e-13 relative accuracy up to ρ = 8 (T ∝ e^{64})
_MAX_SCALED_RADIUS = 8.0


# ----------------------------------------------------------------------------- linearisation


def _ito_system(system) -> StochasticSystem:
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if system.interpretation != "ito":
        system = system.converted("ito")
    return system


def _concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


@eqx.filter_jit
def _coefficients(system, state, t, idx: tuple[int, ...]):
    """Rows ``idx`` of ``∂a/∂Z``, ``a_idx``, ``A = ∂a_idx/∂Z_idx``, ``Q_idx = (b diag(ν) bᵀ)_idx`` at ``state``."""
    params = validated(system.params)
    b = system.diffusion_fn(t, state, params)
    q = (b * driver_intensity(system.noise, system.noise_dim, b.dtype)) @ b.T
    ix = np.asarray(idx, dtype=int)
    rows = jacobian(system.drift_fn, state, params, t)[ix]
    return rows, system.drift_fn(t, state, params)[ix], rows[:, ix], q[np.ix_(ix, ix)]


def _linearise(system, state, names, t, rtol):
    """``(A, Q)`` of the components ``names`` at the steady ``state``: ``A = ∂a_x/∂Z_x``, ``Q = (b diag(ν) bᵀ)_xx``.

    Checks (with concrete values) that ``a_x(state) ≈ 0`` and that ``a_x`` does not
    depend on the other components to first order.
    """
    idx = tuple(system.layout.index(n) for n in names)
    rest = np.asarray([i for i in range(system.state_dim) if i not in idx], dtype=int)
    rows, drift, a, q = _coefficients(system, state, t, idx)
    if _concrete(rows, drift, state):
        jac_np = np.asarray(rows)
        if not np.all(np.isfinite(jac_np)):
            raise ValueError(f"the drift's Jacobian at state={np.asarray(state)} is not finite.")
        scale = float(np.linalg.norm(jac_np, 2)) or 1.0
        allowed = rtol * scale * max(float(np.linalg.norm(np.asarray(state))), 1.0)
        residual = float(np.linalg.norm(np.asarray(drift)))
        if not residual <= allowed:
            raise ValueError(
                f"state={np.asarray(state)} is not a steady state of the components {names}: the Itô drift there "
                f"has norm {residual:.3e} > rtol*|∂a/∂Z|*max(|state|, 1) = {allowed:.3e} (rtol={rtol})."
            )
        coupling = jac_np[:, rest]
        if rest.size and np.max(np.abs(coupling)) > rtol * scale:
            i, j = np.unravel_index(np.argmax(np.abs(coupling)), coupling.shape)
            raise ValueError(
                f"the linearised drift of {names} depends on {system.layout.names[rest[j]]!r} "
                f"(∂a_{names[i]}/∂{system.layout.names[rest[j]]} = {coupling[i, j]:.3e}): these components are not a "
                "closed linear system at this state; include it in `components=` (stationary_spread) "
                "or choose a component "
                f"whose linearised row is closed (linear_residence_time)."
            )
    return a, q


def _check_hurwitz(a, names, hint):
    if _concrete(a):
        growth = float(np.max(np.real(np.linalg.eigvals(np.asarray(a)))))
        if not growth < 0:
            raise ValueError(
                f"the steady state is not asymptotically stable in {names}: the linearised drift has an eigenvalue "
                f"with real part {growth:.3g} ≥ 0, so there is no stationary spread or finite residence time "
                f"({hint})."
            )


@jax.jit
def _lyapunov(a, q):
    """``Σ`` with ``A Σ + Σ Aᵀ + Q = 0`` (Kronecker form, row-major ``vec``; ``A`` Hurwitz)."""
    n = a.shape[0]
    eye = jnp.eye(n, dtype=a.dtype)
    sigma = jnp.linalg.solve(jnp.kron(a, eye) + jnp.kron(eye, a), -q.reshape(-1)).reshape(n, n)
    return 0.5 * (sigma + sigma.T)


class Spread(eqx.Module):
    """Linearised stationary law ``N(z₀, Σ)`` of the components ``names`` about a steady state.

    ``cov = Σ`` solves ``A Σ + Σ Aᵀ + Q = 0``; ``jacobian = A``; ``noise = Q = B diag(ν) Bᵀ``.
    """

    cov: Float[Array, "k k"]
    jacobian: Float[Array, "k k"]
    noise: Float[Array, "k k"]
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def std(self) -> Float[Array, " k"]:
        return jnp.sqrt(jnp.diagonal(self.cov))


def _components(system, components):
    if components is None:
        dep = system.layout.indices("dependent_coordinate")
        return tuple(n for i, n in enumerate(system.layout.names) if i not in dep)
    components = tuple(components)
    if not components:
        raise ValueError("components is empty; name at least one state component.")
    for n in components:
        system.layout.index(n)  # raises naming the state
    if len(set(components)) != len(components):
        raise ValueError(f"components={components} has repeated names.")
    return components


def stationary_spread(
    system: StochasticSystem, state, *, components=None, t: float = 0.0, rtol: float = 1e-8
) -> Spread:
    """Stationary covariance of the linearisation about a stable steady ``state`` (S0 §6, linear case).

    ``components`` (default: all but the dependent coordinates ``q''``) must form a
    closed linear system at ``state`` with a Hurwitz ``A`` (S4 Theorem 4.1:
    asymptotic stability in those variables); cyclic coordinates (e.g. the
    heading) are neutral and must be left out.  Differentiable in the parameters.
    """
    system = _ito_system(system)
    state = system.state(state, "state")
    names = _components(system, components)
    a, q = _linearise(system, state, names, t, rtol)
    _check_hurwitz(a, names, "exclude neutral components such as cyclic coordinates with `components=`")
    return Spread(cov=_lyapunov(a, q), jacobian=a, noise=q, names=names)


# ----------------------------------------------------------------------------- linearised residence time


class LinearResidence(eqx.Module):
    """Mean exit time of the scalar OU mode ``dδ = −κ δ dt + σ dW`` from ``|δ| < r``, started at 0.

    ``mean = (√π/κ) ∫₀^ρ e^{y²} erf(y) dy`` with ``ρ = scaled_radius = r√κ/σ``;
    ``rate = κ``, ``noise = σ²``, ``spread = σ²/(2κ)`` (the stationary variance).
    """

    mean: Float[Array, ""]
    rate: Float[Array, ""]
    noise: Float[Array, ""]
    spread: Float[Array, ""]
    scaled_radius: Float[Array, ""]
    name: str = eqx.field(static=True)


@jax.jit
def _ou_mode(a, q, radius):
    """``(T, κ, σ², ρ)`` of the scalar mode ``(A, Q) = (−κ, σ²)``: ``T = (√π/κ) ∫₀^ρ e^{y²} erf(y) dy``, ``ρ = r√κ/σ``.

    Gauss–Legendre on ``y = ρ s``, ``s ∈ [0, 1]``.
    """
    kappa, noise = -a[0, 0], q[0, 0]
    rho = jnp.asarray(radius, kappa.dtype) * jnp.sqrt(kappa / noise)
    x, w = np.polynomial.legendre.leggauss(_NODES)
    s, w = jnp.asarray((x + 1) / 2, rho.dtype), jnp.asarray(w / 2, rho.dtype)
    y = rho * s
    mean = math.sqrt(math.pi) / kappa * rho * jnp.sum(w * jnp.exp(y * y) * jax.scipy.special.erf(y))
    return mean, kappa, noise, rho


def _radius(radius):
    if isinstance(radius, jax.core.Tracer):
        return radius
    r = np.asarray(radius)
    if r.shape != () or not np.isfinite(r) or not r > 0:
        raise ValueError(f"radius={radius!r}; must be a finite number > 0 (the half-width of the region |δ| < radius).")
    return radius


def _wiener_only(system, what):
    if not isinstance(system.noise, Wiener):
        raise TypeError(
            f"{what} assumes continuous paths (a Wiener driver); this system is driven by "
            f"{type(system.noise).__name__}, whose jumps overshoot the boundary."
        )


def linear_residence_time(
    system: StochasticSystem, state, *, component: str, radius, t: float = 0.0, rtol: float = 1e-8
) -> LinearResidence:
    """Mean residence time in ``|Z_i − z₀_i| < radius`` of the linearisation about a stable steady ``state``.

    The linearised row of ``component`` must be closed (``∂a_i/∂Z_j = 0`` for
    ``j ≠ i`` at ``state``) with ``κ = −∂a_i/∂Z_i > 0``: then ``δ_i`` is a scalar
    Ornstein–Uhlenbeck process and the mean exit time from 0 is the closed form in
    :class:`LinearResidence`.  Differentiable in the parameters (and ``radius``).
    """
    system = _ito_system(system)
    _wiener_only(system, "linear_residence_time")
    state = system.state(state, "state")
    radius = _radius(radius)
    (a, q) = _linearise(system, state, (component,), t, rtol)
    _check_hurwitz(a, (component,), "choose a `component=` whose linearised row is damped")
    mean, kappa, noise, rho = _ou_mode(a, q, radius)
    if _concrete(noise) and not float(noise) > 0:
        raise ValueError(
            f"the noise on {component!r} vanishes at the steady state ((b bᵀ)_ii = {float(noise):.3g}): "
            "the residence time is infinite."
        )
    if _concrete(rho) and not float(rho) <= _MAX_SCALED_RADIUS:
        raise ValueError(
            f"radius={radius} is {float(rho):.3g} > {_MAX_SCALED_RADIUS:g} scaled units r√κ/σ "
            f"({float(rho) * math.sqrt(2):.3g} stationary standard deviations): the residence time "
            f"≈ √π e^(ρ²)/(2κρ) is beyond any simulation and this quadrature; choose a smaller radius."
        )
    return LinearResidence(
        mean=mean,
        rate=kappa,
        noise=noise,
        spread=noise / (2 * kappa),
        scaled_radius=rho,
        name=component,
    )


# ----------------------------------------------------------------------------- Monte Carlo


def _mean_and_se(x, ok):
    """Sample mean of ``x`` over ``ok`` and its standard error."""
    n = jnp.sum(ok).astype(x.dtype)
    mean = jnp.sum(jnp.where(ok, x, 0.0)) / n
    var = jnp.sum(jnp.where(ok, (x - mean) ** 2, 0.0)) / (n - 1)
    return mean, jnp.sqrt(var / n)


class Residence(eqx.Module):
    """Monte-Carlo residence times in ``|Z_i − z₀_i| < radius``, monitored on a grid of spacing ``spacing``.

    Per path: ``times`` = ``E[min(τ, t1) | grid values]`` with the Brownian-bridge
    correction (a crossing between two grid values inside the region has
    probability ``exp(−2 (r ∓ δ_k)(r ∓ δ_{k+1}) / (σ² h))`` at each boundary);
    ``grid_times`` = the first grid time outside (``t1`` if none), which
    overestimates ``τ`` by ``O(σ√h)`` in space, ``O(√h)`` in time.  ``censored``:
    the path stayed inside at every grid time up to ``t1``; ``failed``: a
    non-finite value before it left.  ``survival[p]`` is the bridge probability of
    staying in the region up to ``t1``.  Failed paths enter no statistic.

    ``mean`` estimates ``E[min(τ, t1)]``, a lower bound of ``E[τ]`` short by about
    ``survival_mean · E[τ − t1 | τ > t1]``: run until ``survival_mean`` is negligible.
    """

    times: Float[Array, " paths"]
    grid_times: Float[Array, " paths"]
    survival: Float[Array, " paths"]
    censored: Bool[Array, " paths"]
    failed: Bool[Array, " paths"]
    radius: Float[Array, ""]
    spacing: float = eqx.field(static=True)
    t1: float = eqx.field(static=True)
    name: str = eqx.field(static=True)

    def _stats(self, x):
        return _mean_and_se(x, ~self.failed)

    @property
    def mean(self) -> Float[Array, ""]:
        return self._stats(self.times)[0]

    @property
    def mean_se(self) -> Float[Array, ""]:
        return self._stats(self.times)[1]

    @property
    def grid_mean(self) -> Float[Array, ""]:
        return self._stats(self.grid_times)[0]

    @property
    def grid_mean_se(self) -> Float[Array, ""]:
        return self._stats(self.grid_times)[1]

    @property
    def survival_mean(self) -> Float[Array, ""]:
        return self._stats(self.survival)[0]

    def extrapolated(self, coarse: Residence) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """Richardson extrapolation of the ``O(h)`` bias (time step and bridge): ``(q T_h − T_qh)/(q − 1)``.

        ``self`` and ``coarse`` (spacing ``q h``, ``q > 1``) must come from the same
        paths: the same ``key``, ``n_paths`` and ``brownian_dt``, ``save_every=1``.
        Returns the mean and its standard error from the paired per-path values;
        paths failed in either run are left out.
        """
        if not isinstance(coarse, Residence) or coarse.times.shape != self.times.shape:
            raise ValueError("coarse must be a Residence of the same paths (same key, n_paths and brownian_dt).")
        q = coarse.spacing / self.spacing
        if not q > 1 + 1e-9:
            raise ValueError(f"coarse.spacing={coarse.spacing} must exceed spacing={self.spacing}.")
        return _mean_and_se((q * self.times - coarse.times) / (q - 1), ~(self.failed | coarse.failed))

    @property
    def n_censored(self):
        return jnp.sum(self.censored & ~self.failed)

    @property
    def n_failed(self):
        return jnp.sum(self.failed)


@functools.partial(jax.jit, static_argnames=("spacing", "t1"))
def _exit_times(delta, var, radius, spacing, t1):
    """``(times, grid_times, survival, censored, failed)`` from grid values ``delta`` ``(paths, n)``.

    ``var``: ``σ²`` of the monitored component at each grid value (broadcastable).
    """
    finite = jnp.isfinite(delta)
    inside = finite & (jnp.abs(delta) < radius)
    on_grid = jnp.cumprod(inside, axis=1).astype(bool)  # inside at every grid time so far
    censored = on_grid[:, -1]
    first_out = jnp.argmin(on_grid, axis=1)
    failed = ~censored & ~jnp.take_along_axis(finite, first_out[:, None], axis=1)[:, 0]
    grid_times = jnp.where(censored, t1, first_out.astype(delta.dtype) * spacing)
    # Brownian bridge between consecutive grid values: stay below r and above −r.
    x = jnp.where(inside, delta, 0.0)
    v = jnp.broadcast_to(var, delta.shape)[:, :-1]
    up = (radius - x[:, :-1]) * (radius - x[:, 1:])
    down = (radius + x[:, :-1]) * (radius + x[:, 1:])
    stay = (1 - jnp.exp(-2 * up / (v * spacing))) * (1 - jnp.exp(-2 * down / (v * spacing)))
    stay = jnp.where(inside[:, :-1] & inside[:, 1:], stay, 0.0)
    alive = jnp.concatenate([jnp.ones_like(stay[:, :1]), jnp.cumprod(stay, axis=1)], axis=1)
    times = spacing * jnp.sum(0.5 * (alive[:, :-1] + alive[:, 1:]), axis=1)
    return times, grid_times, alive[:, -1], censored, failed


def residence_time(
    system: StochasticSystem,
    state,
    key,
    *,
    component: str,
    radius,
    n_paths: int,
    t1: float,
    dt: float,
    save_every: int = 1,
    solver: str = "euler",
    brownian_dt: float | None = None,
    chunk_size: int | None = None,
) -> Residence:
    """Mean residence time in ``|Z_i − z₀_i| < radius`` of the full system started at ``state``, by Monte Carlo.

    ``n_paths`` paths from ``state`` with step ``dt`` up to ``t1`` (see
    :func:`~nhsde.simulate`); the component is monitored every ``save_every``
    steps (spacing ``h = save_every·dt``; the whole state is kept per path, memory
    ``8·n_paths·d·t1/h`` bytes) and the exit time taken from the grid
    with the Brownian-bridge correction (:class:`Residence`), whose error is
    ``O(h)`` against ``O(√h)`` for the first grid exit.  ``σ²`` for the bridge is
    ``(b bᵀ)_ii`` at each grid value (at ``state`` for additive noise).  Paths
    that fail are reported in ``failed``, not averaged; paths still inside at
    ``t1`` are reported in ``censored``.  The time step adds an ``O(dt)`` bias
    (Euler–Maruyama: ``≈ −2 %`` at ``κ dt = 0.02`` for an OU mode leaving ±2
    standard deviations; ``'sra1'``, for additive noise: below 0.3 %); two runs
    on one Brownian path (``brownian_dt``) remove it with
    :meth:`Residence.extrapolated`.  The corrected per-path times are continuous in the
    path values (the stay factor vanishes as a grid value reaches ``±r``), so
    ``jax.jacfwd`` through this function gives pathwise estimates of
    ``∂E[min(τ, t1)]/∂θ`` for the parameters ``θ`` of the system.
    """
    system = _ito_system(system)
    _wiener_only(system, "residence_time")
    state = system.state(state, "state")
    i = system.layout.index(component)
    radius = _radius(radius)
    t1 = _number("t1", t1, positive=True)
    dt = _number("dt", dt, positive=True)
    save_every = _number("save_every", save_every, integer=True, positive=True)
    n_steps = _steps("dt", t1, dt)
    if n_steps % save_every:
        raise ValueError(f"save_every={save_every} must divide the {n_steps} steps of t1/dt.")
    ens = simulate(
        system,
        state,
        key,
        n_paths=n_paths,
        t1=t1,
        dt=dt,
        solver=solver,
        brownian_dt=brownian_dt,
        chunk_size=chunk_size,
        save=Save(None, n_steps // save_every + 1, paths=True),
        on_failure="exclude",
    )
    params = system.params

    def variance(t, y):
        b = system.diffusion_fn(t, y, params)[i]
        return b @ b

    if system.additive_noise:
        var = jax.vmap(variance, in_axes=(0, None))(ens.ts, state)[None, :]
    else:
        safe = jnp.where(jnp.isfinite(ens.paths), ens.paths, state)
        var = jax.vmap(jax.vmap(variance), in_axes=(None, 0))(ens.ts, safe)
    values = ens.paths[..., i]
    spacing = save_every * dt
    times, grid_times, survival, censored, failed = _exit_times(
        values - state[i], var, jnp.asarray(radius, values.dtype), spacing=spacing, t1=t1
    )
    return Residence(
        times=times,
        grid_times=grid_times,
        survival=survival,
        censored=censored,
        failed=failed,
        radius=jnp.asarray(radius, values.dtype),
        spacing=spacing,
        t1=t1,
        name=component,
    )
