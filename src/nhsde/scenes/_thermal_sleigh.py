"""The Chaplygin sleigh in a heat bath: the ideal, the naive thermal and the soft (viscous-contact) model.

Conventions of :mod:`._sleigh`: the knife point ``P`` moves with speed ``v`` along the body axis ``e₁`` and
``w`` across it (the slip), the centre of mass is a distance ``a`` ahead of ``P``, ``J = I + m a²``, and the
friction is ``R = ε (m v² + J ω²)``.  The bath has temperature ``kT``.

- ``model="ideal"``: the knife keeps ``w = 0`` exactly and nothing is random (``kT``, ``γ`` unused):
  ``v̇ = a ω² − 2ε v``, ``ω̇ = −(m a/J) v ω − 2ε ω``.
- ``model="naive"``: the same ideal constraint with the friction's fluctuation–dissipation noise,
  ``+ √(4εkT/m) V₁`` and ``+ √(4εkT/J) V₂``: :class:`~nhsde.scenes.ChaplyginSleigh` at ``ν = 4εkT``.  Its
  reaction at the knife has no noise, and the sleigh drifts forward, ``⟨v⟩ = a⟨ω²⟩/(2ε) > 0`` at stationarity,
  against the second law (Jagla, Bloch & Rojo, arXiv 2603.14424).
- ``model="soft"``: the knife is a viscous contact, force ``−γ w e₂`` at ``P`` with its noise ``√(2γkT) V_c``.
  Newton–Euler with ``F = F₁ e₁ + F₂ e₂`` at ``P`` and a couple ``τ``:

      m (v̇ − ω w − a ω²) = F₁,    m (ẇ + a ω̇ + ω v) = F₂,    I ω̇ = τ − a F₂,
      F₁ = −2εm v + √(4εkTm) V₁,   F₂ = −γ w + √(2γkT) V_c,   τ = −2εJ ω + √(4εkTJ) V₂.

  This is a Langevin system with ``T = ½ m (v² + (w + aω)²) + ½ I ω²``: its stationary law is Gibbs,
  ``exp(−T/kT)``, so ``m⟨v²⟩ = m⟨(w + aω)²⟩ = I⟨ω²⟩ = kT`` and ``⟨v⟩ = 0``.  As ``γ → ∞`` at ``kT = 0`` the
  ideal sleigh returns, on the contact time scale ``m/γ``.

A load ``F`` (``load``, default 0) pulls along ``−e₁`` and adds ``−F/m`` to ``v̇`` in every model (no torque: its
line passes through ``P`` and the centre of mass).  The power extracted against it is ``F⟨v⟩``.  In the soft model
it is ``≤ 0``: with ``f`` the load and ``D`` the friction and contact, the steady state's energy balance
``0 = d⟨T⟩/dt = ⟨f·q̇⟩ − Q̇`` and its entropy production ``Q̇/kT ≥ 0`` (``Q̇`` the heat into the bath; the
steady entropy production of a Langevin system, Sekimoto) give ``−F⟨v⟩ ≥ 0``: one bath does no net work.  The naive
model's constrained flow compresses phase space (``div = −(ma/J) v``), Gibbs is not its stationary law, the bound
does not hold, and ``⟨v⟩ = (a⟨ω²⟩ − F/m)/(2ε) > 0`` for a small ``F``: work from a single bath.

Positions (``drift=True``): ``ẋ = v cos θ − w sin θ``, ``ẏ = v sin θ + w cos θ``, ``θ̇ = ω``.  The velocity
damping is linear with constant coefficients in ``(v, w, ω)`` (the body frame), so it is declared as the
system's ``linear_drift``: explicit solvers past their stability limit on ``γ`` are refused before the run,
and the exponential solver treats the stiff contact exactly, its damping and its noise: Gibbs at any ``γ`` and step
(docs guide "Constraints at finite temperature").
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ._bath import AbstractBathScene, on_velocities, with_positions

__all__ = ["BathSleighParameters", "ChaplyginSleighInBath"]


class BathSleighParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="friction ε, 1/s")
    kT: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="bath temperature kT (energy)")
    gamma: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="contact viscosity γ of the soft knife")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    inertia: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="central moment of inertia I")
    offset: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="distance a from the knife to the centre of mass")
    load: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="load force F along −e₁, opposing forward motion")


def _j(p):
    return p.inertia + p.mass * p.offset**2


# ---------------------------------------------------------------- ideal and naive: state (v, ω)


def _ideal_velocity_drift(v, w, p):
    forward = p.offset * w**2 - 2 * p.eps * v - p.load / p.mass
    return jnp.stack([forward, -(p.mass * p.offset / _j(p)) * v * w - 2 * p.eps * w])


def _naive_noise(p, dtype):
    """``√(4εkT) diag(1/√m, 1/√J)``: the friction's fluctuation–dissipation noise."""
    scale = sqrt_intensity(p.kT) * jnp.sqrt(4 * p.eps)
    return (scale * jnp.diag(jnp.stack([1 / jnp.sqrt(p.mass), 1 / jnp.sqrt(_j(p))]))).astype(dtype)


def _ideal_linear(p):
    return -2.0 * p.eps * jnp.eye(2, dtype=p.eps.dtype)


# ---------------------------------------------------------------- soft: state (v, w, ω)


def _soft_linear(p):
    """``−M⁻¹ D`` on ``(v, w, ω)``: ``M`` the body-frame mass matrix, ``D = diag(2εm, γ, 2εJ)``."""
    a, m, i, eps, gamma = p.offset, p.mass, p.inertia, p.eps, p.gamma
    zero = jnp.zeros_like(eps)
    return jnp.stack(
        [
            jnp.stack([-2 * eps, zero, zero]),
            jnp.stack([zero, -gamma * (1 / m + a**2 / i), 2 * eps * a * _j(p) / i]),
            jnp.stack([zero, a * gamma / i, -2 * eps * _j(p) / i]),
        ]
    )


def _soft_velocity_drift(v, w, omega, p):
    linear = _soft_linear(p).astype(v.dtype) @ jnp.stack([v, w, omega])
    forward = omega * w + p.offset * omega**2 - p.load / p.mass
    return linear + jnp.stack([forward, -omega * v, jnp.zeros_like(v)])


def _soft_noise(p, dtype):
    """``M⁻¹ √(2kT) D^{1/2}`` on channels (friction force, friction torque, contact)."""
    a, m, i = p.offset, p.mass, p.inertia
    force, torque, contact = jnp.sqrt(4 * p.eps * m), jnp.sqrt(4 * p.eps * _j(p)), jnp.sqrt(2 * p.gamma)
    zero = jnp.zeros_like(force)
    b = jnp.stack(
        [
            jnp.stack([force / m, zero, zero]),
            jnp.stack([zero, -a * torque / i, contact * (1 / m + a**2 / i)]),
            jnp.stack([zero, torque / i, -a * contact / i]),
        ]
    )
    return (sqrt_intensity(p.kT) * b).astype(dtype)


# ---------------------------------------------------------------- the vector fields (module level: static, hashable)


def _ideal_drift(t, u, p):
    return _ideal_velocity_drift(u[0], u[1], p)


def _ideal_diffusion(t, u, p):
    return jnp.zeros((2, 2), u.dtype)


def _naive_diffusion(t, u, p):
    return _naive_noise(p, u.dtype)


def _soft_drift(t, u, p):
    return _soft_velocity_drift(u[0], u[1], u[2], p)


def _soft_diffusion(t, u, p):
    return _soft_noise(p, u.dtype)


def _positions(theta, v, w, omega):
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([v * c - w * s, v * s + w * c, omega])


def _ideal_rates(q, u, p):
    return _positions(q[2], u[0], jnp.zeros_like(u[0]), u[1])


def _soft_rates(q, u, p):
    return _positions(q[2], u[0], u[1], u[2])


def _ideal_energy(t, u, p):
    """``H = ½(m v² + J ω²)``."""
    return 0.5 * (p.mass * u[0] ** 2 + _j(p) * u[1] ** 2)


def _soft_energy(t, u, p):
    """``H = ½ m (v² + (w + aω)²) + ½ I ω²``."""
    v, w, omega = u[0], u[1], u[2]
    return 0.5 * (p.mass * (v**2 + (w + p.offset * omega) ** 2) + p.inertia * omega**2)


_POSITIONS = (("x", "y", "theta"), ("dependent_coordinate", "dependent_coordinate", "independent_coordinate"))
_REDUCED = {
    # model: (velocity names, drift, diffusion, linear drift, noise channels, q̇, energy)
    "ideal": (("v", "omega"), _ideal_drift, _ideal_diffusion, _ideal_linear, 2, _ideal_rates, _ideal_energy),
    "naive": (("v", "omega"), _ideal_drift, _naive_diffusion, _ideal_linear, 2, _ideal_rates, _ideal_energy),
    "soft": (("v", "slip", "omega"), _soft_drift, _soft_diffusion, _soft_linear, 3, _soft_rates, _soft_energy),
}
_FIELDS = {
    # (model, drift): (velocity names, drift, diffusion, linear drift, noise channels, observables)
    **{(model, False): (*f[:5], (("energy", f[6]),)) for model, f in _REDUCED.items()},
    **{
        (model, True): (f[0], *with_positions(3, f[5], *f[1:4]), f[4], (("energy", on_velocities(3, f[6])),))
        for model, f in _REDUCED.items()
    },
}


class ChaplyginSleighInBath(AbstractBathScene):
    """The Chaplygin sleigh in a heat bath of temperature kT: ideal, naive thermal or soft (viscous) knife.

    ``model`` picks how the knife is realised (module docstring): ``"soft"`` (default), a viscous contact of
    viscosity ``γ`` with its fluctuation–dissipation noise, whose stationary law is Gibbs; ``"naive"``, the ideal
    constraint with noise on the friction only (S0's model, :class:`~nhsde.scenes.ChaplyginSleigh` at
    ``ν = 4εkT``), which drifts forward at finite temperature; ``"ideal"``, no noise.  The state is
    ``(x, y, θ)`` (with ``drift=True``) then ``(v, ω)``, or ``(v, slip, ω)`` for the soft knife.

    Arguments:
        model: ``"soft"``, ``"naive"`` or ``"ideal"``.
        drift: keep the knife point ``(x, y)`` and heading ``θ`` in the state.
        **params: the :class:`BathSleighParameters` (``eps``, ``kT``, ``gamma``, ``mass``, ``inertia``, ``offset``,
            ``load``).

    Examples:
        >>> import nhsde
        >>> nhsde.scenes.ChaplyginSleighInBath(gamma=10.0).build().layout.names
        ('x', 'y', 'theta', 'v', 'slip', 'omega')
        >>> nhsde.scenes.ChaplyginSleighInBath(model="naive", drift=False).observable_names()
        ('v', 'omega', 'energy')
    """

    name: ClassVar[str] = "chaplygin-sleigh-in-bath"
    Parameters: ClassVar[type[BathSleighParameters]] = BathSleighParameters
    fields: ClassVar[dict] = _FIELDS
    positions: ClassVar[tuple[tuple[str, ...], tuple[str, ...]]] = _POSITIONS
    angles: ClassVar[tuple[str, ...]] = ("theta",)

    params: BathSleighParameters
    model: str = eqx.field(static=True)
    drift: bool = eqx.field(static=True)

    def initial_state(self):
        """Moving straight ahead at unit speed from the origin, without slip."""
        velocities = 3 if self.model == "soft" else 2
        y = jnp.zeros(velocities + (3 if self.drift else 0))
        return y.at[3 if self.drift else 0].set(1.0)
