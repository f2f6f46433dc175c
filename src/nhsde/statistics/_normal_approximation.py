"""The normal approximation of S0 §6: the moment equations' mean and covariance over time, as an ensemble.

For the dependent coordinates ``q''`` (Chaplygin: ``a`` and ``b`` do not depend
on them) ``ṁ_{q''} = E_N[Λ] = Λ₀`` and the ``q''`` rows of ``K̇`` are
``(∂Λ₀/∂m_x) K_{x q''} + …``: the statistically linearised drift
``m_{q''} = ∫Λ₀``, ``K_{q''} = ∫∫ (∂Λ₀/∂m_x) K_x(τ₁, τ₂) (∂Λ₀/∂m_x)ᵀ`` of S0 §6,
which :func:`~nhsde.statistics.drift_statistics` reads from the result like
from a Monte-Carlo ensemble.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._ensemble import AbstractMoments, Save, SimulationResult, check_result
from .._misc import check_number, check_steps
from .._params import parameters_checked_on_host
from .._system import StochasticSystem
from ._moments import gaussian_closure, initial_moments, integrate_moments

__all__ = ["normal_approximation"]


class NormalApproximation(AbstractMoments):
    """Means and covariances from the normal-approximation moment equations (S0 §6): no paths, no Monte-Carlo
    error; :func:`~nhsde.statistics.drift_statistics` and the other moment statistics apply unchanged."""

    ts: Float[Array, " n"]
    mean: Float[Array, "n k"]
    cov: Float[Array, "n k k"]
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    dt: float = eqx.field(static=True)


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
) -> NormalApproximation:
    """Mean and covariance of the state under Gaussian closure, S0 §6, as a :class:`NormalApproximation`.

    ``ṁ = E_N[a]``, ``K̇ = E_N[a (Z − m)ᵀ] + E_N[(Z − m) aᵀ] + E_N[b bᵀ]``, the expectations ``E_N`` over the
    normal law ``N(m, K)`` by Gauss–Hermite quadrature; exact for linear systems such as the ball of S0 (3.1).

    Arguments:
        system: the SDE (a scene's ``build()``), driven by Wiener noise.
        y0: initial mean ``(d,)``.
        cov0: initial covariance ``(d, d)`` (default 0: a deterministic start).
        t0, t1: time interval.
        dt: the fixed Dopri8 step (divides ``t1 − t0``); a linear autonomous system's moments follow their exact
            flow whatever the step.
        save: state components and save times as in :func:`~nhsde.simulate` (no ``paths``).
        order: Gauss–Hermite nodes per component.

    Returns:
        a :class:`NormalApproximation` (``ts``, ``mean``, ``cov``, ``names``, ``roles``), read by
        :func:`drift_statistics` and the other moment statistics like a Monte-Carlo ensemble.

    Examples:
        >>> import nhsde
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0)
        >>> moments = nhsde.statistics.normal_approximation(
        ...     scene.build(), scene.initial_state(), t1=8.0, dt=0.5, order=3
        ... )
        >>> print(moments.ts)
        [0. 1. 2. 3. 4. 5. 6. 7. 8.]
        >>> print(round(float(moments.cov[-1, 2, 2]), 4))  # νδ²/(4ε) with δ = 5/7
        0.1276
    """
    y0, cov0 = initial_moments(system, y0, cov0)
    closure = gaussian_closure(system, y0.dtype, order)
    t0, t1 = check_number("t0", t0), check_number("t1", t1)
    if t1 <= t0:
        raise ValueError(f"t1={t1} must be > t0={t0}.")
    dt = check_number("dt", dt, positive=True)
    n_steps = check_steps("dt", t1 - t0, dt)
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
    n_save = int(check_number("save.n", n_save, integer=True))
    if n_save < 2 or n_steps % (n_save - 1):
        raise ValueError(f"save.n={n_save}: n − 1 must be ≥ 1 and divide the {n_steps} steps.")
    ts, ms, ks = integrate_moments(closure, y0, cov0, t0, t1, n_steps, n_save)
    if not parameters_checked_on_host():  # else the caller checks the outcome on the host (a fit's loss)
        overflow = ~(jnp.all(jnp.isfinite(ms)) & jnp.all(jnp.isfinite(ks)))
        result = SimulationResult.where(overflow, SimulationResult.moments_overflow, SimulationResult.successful)
        details = "the moment equations' solution is not finite (a parameter's scale, or dt, too large?): "
        ms, ks = check_result((ms, ks), result, "normal_approximation", details)
    idx = np.asarray([system.layout.index(n) for n in names])
    mean, cov = ms[:, idx], ks[:, idx[:, None], idx[None, :]]
    roles = tuple(system.layout.roles[i] for i in idx)
    return NormalApproximation(ts=ts, mean=mean, cov=cov, names=names, roles=roles, dt=(t1 - t0) / n_steps)
