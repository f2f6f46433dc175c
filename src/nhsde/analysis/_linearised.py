"""The linearised (Ornstein–Uhlenbeck) view of a stable steady motion: stationary spread and residence time.

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

Both differentiate in every parameter leaf of the system.  The same mean exit
time on the full nonlinear system, by Monte Carlo: :func:`~nhsde.analysis.residence_time`.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._misc import is_concrete
from .._params import validated
from .._system import StochasticSystem
from ..noise import driver_intensity
from ._inputs import check_radius, ito_system, require_wiener
from ._stability import jacobian

__all__ = ["LinearResidence", "Spread", "linear_residence_time", "stationary_spread"]

_NODES = 64  # Gauss–Legendre nodes: 1e-13 relative accuracy up to ρ = 8 (T ∝ e^{64})
_MAX_SCALED_RADIUS = 8.0


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
    if is_concrete(rows, drift, state):
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
    if is_concrete(a):
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

    Arguments:
        system: the SDE (a scene's ``build()``).
        state: the steady state ``(d,)`` of the noiseless system.
        components: names of the components of the closed linear system (default: all but ``q''``).
        t: the time at which the coefficients are evaluated.
        rtol: relative tolerance of the checks (steadiness, closure).

    Returns:
        a :class:`Spread`: the Lyapunov solution ``cov`` of ``A K + K Aᵀ + Q = 0``, ``jacobian = A``,
        ``noise = Q`` and ``std``.

    Examples:
        The ball at rest (S0 (3.1)): ``K = νδ²/(4ε)`` per axis, as the normal approximation finds it:

        >>> import nhsde
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0)
        >>> spread = nhsde.analysis.stationary_spread(scene.build(), scene.initial_state())
        >>> spread.names
        ('u_x', 'u_y')
        >>> print(spread.cov.diagonal().round(4))
        [0.1276 0.1276]
    """
    system = ito_system(system)
    state = system.state(state, "state")
    names = _components(system, components)
    a, q = _linearise(system, state, names, t, rtol)
    _check_hurwitz(a, names, "exclude neutral components such as cyclic coordinates with `components=`")
    return Spread(cov=_lyapunov(a, q), jacobian=a, noise=q, names=names)


# ----------------------------------------------------------------------------- residence time of the OU mode


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


def linear_residence_time(
    system: StochasticSystem, state, *, component: str, radius, t: float = 0.0, rtol: float = 1e-8
) -> LinearResidence:
    """Mean residence time in ``|Z_i − z₀_i| < radius`` of the linearisation about a stable steady ``state``.

    The linearised row of ``component`` must be closed (``∂a_i/∂Z_j = 0`` for
    ``j ≠ i`` at ``state``) with ``κ = −∂a_i/∂Z_i > 0``: then ``δ_i`` is a scalar
    Ornstein–Uhlenbeck process and the mean exit time from 0 is the closed form in
    :class:`LinearResidence`.  Differentiable in the parameters (and ``radius``).

    Arguments:
        system: a Wiener-driven SDE.
        state: the stable steady state ``(d,)``.
        component: the monitored state component ``i``.
        radius: the half-width ``r`` of the interval ``|Z_i − z₀_i| < r``.
        t: the time at which the coefficients are evaluated.
        rtol: relative tolerance of the checks.

    Returns:
        a :class:`LinearResidence`: ``mean`` exit time, ``rate`` ``κ``, ``noise`` ``σ²``, ``spread`` and
        ``scaled_radius``.

    Examples:
        The ball's velocity (S0 (3.1)) is exactly an Ornstein–Uhlenbeck mode with ``κ = 2ε``, ``σ² = νδ²``:

        >>> import nhsde
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0)
        >>> stay = nhsde.analysis.linear_residence_time(
        ...     scene.build(), scene.initial_state(), component="u_x", radius=0.5
        ... )
        >>> print(float(stay.rate), round(float(stay.noise), 4), round(float(stay.mean), 4))
        2.0 0.5102 0.7025
    """
    system = ito_system(system)
    require_wiener(system, "linear_residence_time")
    state = system.state(state, "state")
    radius = check_radius(radius)
    (a, q) = _linearise(system, state, (component,), t, rtol)
    _check_hurwitz(a, (component,), "choose a `component=` whose linearised row is damped")
    mean, kappa, noise, rho = _ou_mode(a, q, radius)
    if is_concrete(noise) and not float(noise) > 0:
        raise ValueError(
            f"the noise on {component!r} vanishes at the steady state ((b bᵀ)_ii = {float(noise):.3g}): "
            "the residence time is infinite."
        )
    if is_concrete(rho) and not float(rho) <= _MAX_SCALED_RADIUS:
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
