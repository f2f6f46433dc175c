"""The vertical rolling disk in a heat bath: the ideal, the naive thermal and the soft (viscous-contact) model.

Conventions of :mod:`._disk`: contact point ``(x, y)``, rolling angle ``θ``, heading ``φ`` (the rolling direction
``e = (cos φ, sin φ)``), radius ``R``, mass ``m``, moments of inertia ``I`` about the axle and ``J`` about the
vertical, ``T = ½ m (ẋ² + ẏ²) + ½ I θ̇² + ½ J φ̇²``, friction ``R_f = 2εT``.  In the body frame the centre moves
with ``v = e·(ẋ, ẏ)`` along the heading and ``w`` across it; rolling without slipping is ``v = R θ̇``, ``w = 0``.
The bath has temperature ``kT``.

- ``model="ideal"``: the contact rolls without slipping and nothing is random (``kT``, ``γ`` unused).  The
  reactions cancel from ``(I + mR²) θ̈ = −2ε (I + mR²) θ̇``, ``J φ̈ = −2εJ φ̇`` (``θ̈ = φ̈ = 0`` without friction).
- ``model="naive"``: the same ideal contact with the friction's fluctuation–dissipation noise,
  ``+ √(4εkT/(I + mR²)) V₁`` and ``+ √(4εkT/J) V₂``: :class:`~nhsde.scenes.VerticalRollingDisk` at ``ν = 4εkT``.
  Its reaction has no noise.  For the sleigh this model drifts forward against the second law (Jagla, Bloch &
  Rojo, arXiv 2603.14424); for the disk it does not: its constrained flow ``θ̈ = φ̈ = 0`` keeps the volume and
  ``T_c = ½ (I + mR²) θ̇² + ½ J φ̇²``, so S0 Statement 1 gives the stationary law ``exp(−T_c/kT)``, which is
  Gibbs conditioned on no slip.  It still misses the contact's thermal modes: ``(I + mR²)⟨θ̇²⟩ = J⟨φ̇²⟩ = kT``,
  ``⟨T⟩ = kT``, and ``I⟨θ̇²⟩ = kT I/(I + mR²)``.
- ``model="soft"``: the contact is viscous, force ``−γ s`` at ``P`` on the slip ``s = (v − Rθ̇, w)``, with its
  noise ``√(2γkT) V_c`` (two channels).  Newton–Euler in the body frame:

      m (v̇ − φ̇ w) = F₁ − 2εm v + √(4εkTm) V₁,   m (ẇ + φ̇ v) = F₂ − 2εm w + √(4εkTm) V₂,
      I θ̈ = −R F₁ − 2εI θ̇ + √(4εkTI) V₃,         J φ̈ = −2εJ φ̇ + √(4εkTJ) V₄,
      F = −γ s + √(2γkT) V_c.

  A Langevin system with ``T = ½ m (v² + w²) + ½ I θ̇² + ½ J φ̇²`` (THEORY.md §8): its stationary law is Gibbs,
  ``exp(−T/kT)``, so ``m⟨v²⟩ = m⟨w²⟩ = I⟨θ̇²⟩ = J⟨φ̇²⟩ = kT``, ``⟨T⟩ = 2kT`` and ``⟨v⟩ = 0``.  As ``γ → ∞`` at
  ``kT = 0`` the ideal disk returns, on the contact time scale ``m/γ``.

Positions (``drift=True``): ``ẋ = v cos φ − w sin φ``, ``ẏ = v sin φ + w cos φ`` (``v = Rθ̇``, ``w = 0`` in the
ideal and naive models), then ``θ̇`` and ``φ̇``.  The velocity damping is linear with constant coefficients in the
body frame, so it is declared as the system's ``linear_drift``: the contact's slip modes are damped at rates up to
``γ (1/m + R²/I)``, and explicit solvers past their stability limit are refused before the run.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from ._bath import AbstractBathScene, on_velocities, with_positions

__all__ = ["BathDiskParameters", "VerticalRollingDiskInBath"]


class BathDiskParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="friction ε, 1/s")
    kT: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="bath temperature kT (energy)")
    gamma: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="contact viscosity γ of the soft contact")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="radius R")
    roll_inertia: jnp.ndarray = parameter(default=0.5, lower=0.0, strict=True, doc="moment of inertia I about the axle")
    turn_inertia: jnp.ndarray = parameter(
        default=0.25, lower=0.0, strict=True, doc="moment of inertia J about the vertical"
    )


def _rolling_inertia(p):
    """``I + mR²``: the moment of inertia about the contact line."""
    return p.roll_inertia + p.mass * p.radius**2


# ---------------------------------------------------------------- ideal and naive: state (θ̇, φ̇)


def _ideal_linear(p):
    return -2.0 * p.eps * jnp.eye(2, dtype=p.eps.dtype)


def _ideal_velocity_drift(theta_dot, phi_dot, p):
    return -2.0 * p.eps * jnp.stack([theta_dot, phi_dot])


def _naive_noise(p, dtype):
    """``√(4εkT) diag(1/√(I + mR²), 1/√J)``: the friction's fluctuation–dissipation noise."""
    scale = sqrt_intensity(p.kT) * jnp.sqrt(4 * p.eps)
    return (scale * jnp.diag(jnp.stack([1 / jnp.sqrt(_rolling_inertia(p)), 1 / jnp.sqrt(p.turn_inertia)]))).astype(
        dtype
    )


# ---------------------------------------------------------------- soft: state (v, w, θ̇, φ̇)


def _soft_linear(p):
    """``−M⁻¹ D`` on ``(v, w, θ̇, φ̇)``: ``M = diag(m, m, I, J)``, ``D = 2εM + γ BᵀB``, ``B = [[1, 0, −R, 0], [0, 1, 0,
    0]]`` the slip."""
    m, r, i, eps, gamma = p.mass, p.radius, p.roll_inertia, p.eps, p.gamma
    zero = jnp.zeros_like(eps)
    return jnp.stack(
        [
            jnp.stack([-2 * eps - gamma / m, zero, gamma * r / m, zero]),
            jnp.stack([zero, -2 * eps - gamma / m, zero, zero]),
            jnp.stack([gamma * r / i, zero, -2 * eps - gamma * r**2 / i, zero]),
            jnp.stack([zero, zero, zero, -2 * eps]),
        ]
    )


def _soft_velocity_drift(v, w, theta_dot, phi_dot, p):
    linear = _soft_linear(p).astype(v.dtype) @ jnp.stack([v, w, theta_dot, phi_dot])
    zero = jnp.zeros_like(v)
    return linear + jnp.stack([phi_dot * w, -phi_dot * v, zero, zero])


def _soft_noise(p, dtype):
    """``M⁻¹ √(2kT) D^{1/2}`` on channels (friction on ``v``, ``w``, ``θ``, ``φ``; contact along, across)."""
    m, r, i, j = p.mass, p.radius, p.roll_inertia, p.turn_inertia
    friction = jnp.sqrt(4 * p.eps)
    contact = jnp.sqrt(2 * p.gamma)
    zero = jnp.zeros_like(friction)
    b = jnp.stack(
        [
            jnp.stack([friction / jnp.sqrt(m), zero, zero, zero, contact / m, zero]),
            jnp.stack([zero, friction / jnp.sqrt(m), zero, zero, zero, contact / m]),
            jnp.stack([zero, zero, friction / jnp.sqrt(i), zero, -r * contact / i, zero]),
            jnp.stack([zero, zero, zero, friction / jnp.sqrt(j), zero, zero]),
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
    return _soft_velocity_drift(u[0], u[1], u[2], u[3], p)


def _soft_diffusion(t, u, p):
    return _soft_noise(p, u.dtype)


def _positions(phi, v, w, theta_dot, phi_dot):
    c, s = jnp.cos(phi), jnp.sin(phi)
    return jnp.stack([v * c - w * s, v * s + w * c, theta_dot, phi_dot])


def _ideal_rates(q, u, p):
    v = p.radius * u[0]
    return _positions(q[3], v, jnp.zeros_like(v), u[0], u[1])


def _soft_rates(q, u, p):
    return _positions(q[3], u[0], u[1], u[2], u[3])


def _ideal_energy(t, u, p):
    """``T_c = ½ (I + mR²) θ̇² + ½ J φ̇²``."""
    return 0.5 * (_rolling_inertia(p) * u[0] ** 2 + p.turn_inertia * u[1] ** 2)


def _soft_energy(t, u, p):
    """``T = ½ m (v² + w²) + ½ I θ̇² + ½ J φ̇²``."""
    v, w, theta_dot, phi_dot = u[0], u[1], u[2], u[3]
    return 0.5 * (p.mass * (v**2 + w**2) + p.roll_inertia * theta_dot**2 + p.turn_inertia * phi_dot**2)


def _soft_slip(t, u, p):
    """``v − R θ̇``: the contact's slip along the heading."""
    return u[0] - p.radius * u[2]


_POSITIONS = (
    ("x", "y", "theta", "phi"),
    ("dependent_coordinate", "dependent_coordinate", "independent_coordinate", "independent_coordinate"),
)
_IDEAL_VELOCITIES, _SOFT_VELOCITIES = ("theta_dot", "phi_dot"), ("v", "w", "theta_dot", "phi_dot")
_IDEAL_OBSERVABLES, _SOFT_OBSERVABLES = (("energy", _ideal_energy),), (("energy", _soft_energy), ("slip", _soft_slip))
_REDUCED = {
    # model: (velocity names, drift, diffusion, linear drift, noise channels, q̇, observables)
    "ideal": (_IDEAL_VELOCITIES, _ideal_drift, _ideal_diffusion, _ideal_linear, 2, _ideal_rates, _IDEAL_OBSERVABLES),
    "naive": (_IDEAL_VELOCITIES, _ideal_drift, _naive_diffusion, _ideal_linear, 2, _ideal_rates, _IDEAL_OBSERVABLES),
    "soft": (_SOFT_VELOCITIES, _soft_drift, _soft_diffusion, _soft_linear, 6, _soft_rates, _SOFT_OBSERVABLES),
}
_FIELDS = {
    # (model, drift): (velocity names, drift, diffusion, linear drift, noise channels, observables)
    **{(model, False): (*f[:5], f[6]) for model, f in _REDUCED.items()},
    **{
        (model, True): (
            f[0],
            *with_positions(4, f[5], *f[1:4]),
            f[4],
            tuple((name, on_velocities(4, g)) for name, g in f[6]),
        )
        for model, f in _REDUCED.items()
    },
}


class VerticalRollingDiskInBath(AbstractBathScene):
    """The vertical rolling disk in a heat bath of temperature kT: ideal, naive thermal or soft (viscous) contact.

    ``model`` picks how the contact is realised (module docstring): ``"soft"`` (default), a viscous contact of
    viscosity ``γ`` with its fluctuation–dissipation noise, whose stationary law is Gibbs; ``"naive"``, rolling
    without slipping with noise on the friction only (:class:`~nhsde.scenes.VerticalRollingDisk` at ``ν = 4εkT``),
    whose stationary law is Gibbs conditioned on no slip; ``"ideal"``, no noise.  The state is ``(x, y, θ, φ)``
    (with ``drift=True``) then ``(θ̇, φ̇)``, or ``(v, w, θ̇, φ̇)`` for the soft contact (``v``, ``w``: the centre's
    velocity along and across the heading).

    Arguments:
        model: ``"soft"``, ``"naive"`` or ``"ideal"``.
        drift: keep the contact point ``(x, y)`` and the angles ``θ``, ``φ`` in the state.
        **params: the :class:`BathDiskParameters` (``eps``, ``kT``, ``gamma``, ``mass``, ``radius``,
            ``roll_inertia``, ``turn_inertia``).

    Examples:
        >>> import nhsde
        >>> nhsde.scenes.VerticalRollingDiskInBath(gamma=10.0).build().layout.names
        ('x', 'y', 'theta', 'phi', 'v', 'w', 'theta_dot', 'phi_dot')
        >>> nhsde.scenes.VerticalRollingDiskInBath(model="naive", drift=False).observable_names()
        ('theta_dot', 'phi_dot', 'energy')
    """

    name: ClassVar[str] = "vertical-rolling-disk-in-bath"
    Parameters: ClassVar[type[BathDiskParameters]] = BathDiskParameters
    fields: ClassVar[dict] = _FIELDS
    positions: ClassVar[tuple[tuple[str, ...], tuple[str, ...]]] = _POSITIONS
    angles: ClassVar[tuple[str, ...]] = ("phi",)

    params: BathDiskParameters
    model: str = eqx.field(static=True)
    drift: bool = eqx.field(static=True)

    def initial_state(self):
        """Rolling straight ahead from the origin at ``θ̇ = 1`` (``v = R``), without slip."""
        offset = 4 if self.drift else 0
        if self.model != "soft":
            return jnp.zeros(offset + 2).at[offset].set(1.0)
        return jnp.zeros(offset + 4).at[offset].set(self.params.radius).at[offset + 2].set(1.0)
