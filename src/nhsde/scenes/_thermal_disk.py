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
from .._system import StateLayout, StochasticSystem
from ._base import AbstractScene

__all__ = ["BathDiskParameters", "VerticalRollingDiskInBath"]

MODELS = ("ideal", "naive", "soft")


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


def _positions(phi, v, w, theta_dot, phi_dot):
    c, s = jnp.cos(phi), jnp.sin(phi)
    return jnp.stack([v * c - w * s, v * s + w * c, theta_dot, phi_dot])


def _ideal_drift_full(t, y, p):
    theta_dot, phi_dot = y[4], y[5]
    v = p.radius * theta_dot
    return jnp.concatenate(
        [_positions(y[3], v, jnp.zeros_like(v), theta_dot, phi_dot), _ideal_velocity_drift(theta_dot, phi_dot, p)]
    )


def _ideal_drift_reduced(t, y, p):
    return _ideal_velocity_drift(y[0], y[1], p)


def _ideal_diffusion_full(t, y, p):
    return jnp.zeros((6, 2), y.dtype)


def _ideal_diffusion_reduced(t, y, p):
    return jnp.zeros((2, 2), y.dtype)


def _naive_diffusion_full(t, y, p):
    return jnp.concatenate([jnp.zeros((4, 2), y.dtype), _naive_noise(p, y.dtype)])


def _naive_diffusion_reduced(t, y, p):
    return _naive_noise(p, y.dtype)


def _ideal_linear_full(p):
    return jnp.zeros((6, 6), p.eps.dtype).at[4:, 4:].set(_ideal_linear(p))


def _soft_drift_full(t, y, p):
    v, w, theta_dot, phi_dot = y[4], y[5], y[6], y[7]
    return jnp.concatenate(
        [_positions(y[3], v, w, theta_dot, phi_dot), _soft_velocity_drift(v, w, theta_dot, phi_dot, p)]
    )


def _soft_drift_reduced(t, y, p):
    return _soft_velocity_drift(y[0], y[1], y[2], y[3], p)


def _soft_diffusion_full(t, y, p):
    return jnp.concatenate([jnp.zeros((4, 6), y.dtype), _soft_noise(p, y.dtype)])


def _soft_diffusion_reduced(t, y, p):
    return _soft_noise(p, y.dtype)


def _soft_linear_full(p):
    return jnp.zeros((8, 8), p.eps.dtype).at[4:, 4:].set(_soft_linear(p))


def _ideal_energy(offset):
    def energy(t, y, p):
        """``T_c = ½ (I + mR²) θ̇² + ½ J φ̇²``."""
        return 0.5 * (_rolling_inertia(p) * y[offset] ** 2 + p.turn_inertia * y[offset + 1] ** 2)

    return energy


def _soft_energy(offset):
    def energy(t, y, p):
        """``T = ½ m (v² + w²) + ½ I θ̇² + ½ J φ̇²``."""
        v, w, theta_dot, phi_dot = y[offset], y[offset + 1], y[offset + 2], y[offset + 3]
        return 0.5 * (p.mass * (v**2 + w**2) + p.roll_inertia * theta_dot**2 + p.turn_inertia * phi_dot**2)

    return energy


def _soft_slip(offset):
    def slip(t, y, p):
        """``v − R θ̇``: the contact's slip along the heading."""
        return y[offset] - p.radius * y[offset + 2]

    return slip


_OBSERVABLES = {
    ("soft", True): (("energy", _soft_energy(4)), ("slip", _soft_slip(4))),
    ("soft", False): (("energy", _soft_energy(0)), ("slip", _soft_slip(0))),
    ("ideal", True): (("energy", _ideal_energy(4)),),
    ("ideal", False): (("energy", _ideal_energy(0)),),
}
_POSITIONS = (
    ("x", "y", "theta", "phi"),
    ("dependent_coordinate", "dependent_coordinate", "independent_coordinate", "independent_coordinate"),
)
_SOFT_VELOCITIES = ("v", "w", "theta_dot", "phi_dot")
_FIELDS = {
    # (model, drift): (velocity names, drift, diffusion, linear drift, noise channels)
    ("ideal", True): (("theta_dot", "phi_dot"), _ideal_drift_full, _ideal_diffusion_full, _ideal_linear_full, 2),
    ("ideal", False): (("theta_dot", "phi_dot"), _ideal_drift_reduced, _ideal_diffusion_reduced, _ideal_linear, 2),
    ("naive", True): (("theta_dot", "phi_dot"), _ideal_drift_full, _naive_diffusion_full, _ideal_linear_full, 2),
    ("naive", False): (("theta_dot", "phi_dot"), _ideal_drift_reduced, _naive_diffusion_reduced, _ideal_linear, 2),
    ("soft", True): (_SOFT_VELOCITIES, _soft_drift_full, _soft_diffusion_full, _soft_linear_full, 6),
    ("soft", False): (_SOFT_VELOCITIES, _soft_drift_reduced, _soft_diffusion_reduced, _soft_linear, 6),
}


class VerticalRollingDiskInBath(AbstractScene):
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
    intensities: ClassVar[tuple[str, ...]] = ("kT",)

    params: BathDiskParameters
    model: str = eqx.field(static=True)
    drift: bool = eqx.field(static=True)

    def __init__(self, *, model: str = "soft", drift: bool = True, **params):
        if model not in MODELS:
            raise ValueError(f"model={model!r}; allowed: {', '.join(repr(m) for m in MODELS)}.")
        self.params = BathDiskParameters(**params)
        self.model = model
        self.drift = bool(drift)

    def build(self) -> StochasticSystem:
        velocities, drift, diffusion, linear, channels = _FIELDS[self.model, self.drift]
        names, roles = velocities, ("velocity",) * len(velocities)
        if self.drift:
            names, roles = _POSITIONS[0] + names, _POSITIONS[1] + roles
        return StochasticSystem(
            drift_fn=drift,
            diffusion_fn=diffusion,
            params=self.params,
            layout=StateLayout(names, roles),
            noise_dim=channels,
            additive_noise=True,
            linear_drift=linear,
            observables=_OBSERVABLES["soft" if self.model == "soft" else "ideal", self.drift],
        )

    def initial_state(self):
        """Rolling straight ahead from the origin at ``θ̇ = 1`` (``v = R``), without slip."""
        offset = 4 if self.drift else 0
        if self.model != "soft":
            return jnp.zeros(offset + 2).at[offset].set(1.0)
        return jnp.zeros(offset + 4).at[offset].set(self.params.radius).at[offset + 2].set(1.0)
