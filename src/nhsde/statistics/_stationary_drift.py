"""The stationary regime of the normal approximation and the drift of q'' it causes: S0 §6's stationary formulas.

In a stationary regime of ``x`` (the components other than ``q''``), Newton's
method on the moment equations gives ``m_x``, ``K_x`` and the linearised drift
``Ā``; then ``m_{q''}(t) ≈ Λ₀ t`` and
``K_{q''}(t) ≈ L [M(t) K_x + K_x M(t)ᵀ] Lᵀ`` with ``L = ∂Λ₀/∂m_x``,
``M(t) = ∫₀ᵗ (t − ξ) e^{Āξ} dξ = Ā⁻²(e^{Āt} − I) − t Ā⁻¹`` (the linearised
correlation ``k_x(τ) = e^{Āτ} K_x``; the printed single integral of S0 misses the
symmetrisation), whose slope is the Green–Kubo diffusion
``D = ∫₀^∞ sym(L k_x(τ) Lᵀ) dτ = −½ L (Ā⁻¹K_x + K_x Ā⁻ᵀ) Lᵀ``;
:func:`~nhsde.statistics.green_kubo` estimates the same integral from Monte-Carlo paths.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._misc import check_number, check_steps, is_concrete
from .._solvers import expm
from .._system import StochasticSystem
from ._drift import DriftStatistics, StationaryMoments
from ._moments import GaussianClosure, gaussian_closure, initial_moments, integrate_moments

__all__ = ["StationaryDrift", "stationary_drift"]

_expm_batch = jax.jit(jax.vmap(expm))


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
def _newton(closure: GaussianClosure, m, k, components: tuple[int, ...], steps: int):
    """Newton's method on ``ṁ_x = 0``, ``K̇_x = 0`` (``K_x`` by its upper triangle) from ``(m, K)``.

    ``components`` index ``x``.  Returns ``m_x``, ``K_x``, the expectations ``E_N[a]``, ``E_N[∂a/∂Z]`` there and
    the largest residual.
    """
    x = np.asarray(components)
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

    Arguments:
        system: the SDE, with dependent coordinates ``q''`` in its state.
        y0, cov0: initial mean and covariance (default 0) of the relaxation run.
        t_relax: length of the relaxation run before Newton's method.
        dt: its Dopri8 step (a linear autonomous system's relaxation is exact at any step).
        order: Gauss–Hermite nodes per component.
        newton_steps: Newton iterations on the stationary moment equations.
        rtol: accepted relative residual.

    Returns:
        a :class:`StationaryDrift`: ``rate = Λ₀``, ``gain = L``, ``jacobian = Ā``, the stationary moments of
        ``x``, the Green–Kubo ``diffusion`` and ``systematic(ts)``/``fluctuation(ts)`` of ``q''``.
    """
    y0, cov0 = initial_moments(system, y0, cov0)
    closure = gaussian_closure(system, y0.dtype, order)
    layout = closure.system.layout
    dep = np.asarray(layout.indices("dependent_coordinate"), dtype=int)
    x = np.asarray([i for i in range(layout.size) if i not in dep], dtype=int)
    t_relax = check_number("t_relax", t_relax, positive=True)
    n_steps = check_steps("dt", t_relax, check_number("dt", dt, positive=True))
    _, ms, ks = integrate_moments(closure, y0, cov0, 0.0, t_relax, n_steps, 2)
    newton_steps = int(check_number("newton_steps", newton_steps, integer=True))
    mx, kx, mean_a, jac, res = _newton(closure, ms[-1], ks[-1], tuple(x.tolist()), newton_steps)
    ja = jac[np.ix_(x, x)]
    if is_concrete(res):
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
