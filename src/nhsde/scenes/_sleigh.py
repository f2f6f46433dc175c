"""Chaplygin sleigh with viscous friction and random force and torque.

A body of mass ``m`` and central inertia ``I`` slides on a knife edge at ``P``, a
distance ``a`` behind the centre of mass along the body axis ``e1``; ``P`` has no
velocity across ``e1``.  With ``v`` the speed of ``P`` along ``e1``, ``ω`` the
angular velocity and ``J = I + m a²`` (eliminating the constraint reaction from
the momentum balance of the centre of mass and the moment balance about it):

    v̇ = a ω² − 2ε v + V₁/√m,     ω̇ = −(m a/J) v ω − 2ε ω + V₂/√J,
    ẋ = v cos θ,   ẏ = v sin θ,   θ̇ = ω,

with ``V`` white noise of intensity ``ν`` (random force along the knife and
random torque, scaled so that friction is proportional to ``bbᵀ``, the form of
S0 Statement 1).  Energy ``H = ½(m v² + J ω²)`` is conserved at ``ε = ν = 0``, but
the flow compresses phase volume (``div = −(m a/J) v``): no invariant measure,
and a nonlinear scene for the drift statistics of the contact point ``(x, y)``.

This is the *naive thermal* model (S0's): read as a bath of temperature ``kT = ν/(4ε)``, the noise reaches the
friction but not the knife's reaction.  At stationarity ``⟨v⟩ = a⟨ω²⟩/(2ε) > 0``: the sleigh drifts forward in a
bath at one temperature, which Jagla, Bloch & Rojo (arXiv 2603.14424) show violates the second law.  The consistent
model, a viscous knife with its own fluctuation–dissipation noise, is :class:`~nhsde.scenes.ChaplyginSleighInBath`.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from .._system import StateLayout, StochasticSystem
from ._base import AbstractScene

__all__ = ["ChaplyginSleigh", "SleighParameters"]


class SleighParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.1, lower=0.0, doc="friction ε, 1/s")
    nu: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="intensity ν of the random force and torque")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    inertia: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="central moment of inertia I")
    offset: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="distance a from the centre of mass to the knife")


def _velocity_drift(v, w, p):
    j = p.inertia + p.mass * p.offset**2
    return jnp.stack([p.offset * w**2 - 2 * p.eps * v, -(p.mass * p.offset / j) * v * w - 2 * p.eps * w])


def _velocity_noise(p, dtype):
    j = p.inertia + p.mass * p.offset**2
    return sqrt_intensity(p.nu) * jnp.diag(jnp.stack([1 / jnp.sqrt(p.mass), 1 / jnp.sqrt(j)]).astype(dtype))


def _drift_full(t, y, p):
    theta, v, w = y[2], y[3], y[4]
    return jnp.concatenate([jnp.stack([v * jnp.cos(theta), v * jnp.sin(theta), w]), _velocity_drift(v, w, p)])


def _diffusion_full(t, y, p):
    return jnp.concatenate([jnp.zeros((3, 2), y.dtype), _velocity_noise(p, y.dtype)])


def _drift_reduced(t, y, p):
    return _velocity_drift(y[0], y[1], p)


def _diffusion_reduced(t, y, p):
    return _velocity_noise(p, y.dtype)


def _linear_full(p):
    """Friction part of the drift: −2ε on (v, ω)."""
    return jnp.diag(jnp.array([0.0, 0.0, 0.0, 1.0, 1.0], p.eps.dtype)) * (-2.0 * p.eps)


def _linear_reduced(p):
    return -2.0 * p.eps * jnp.eye(2, dtype=p.eps.dtype)


def _energy(v_index, w_index):
    def energy(t, y, p):
        """H = ½(m v² + J ω²), J = I + m a²."""
        return 0.5 * (p.mass * y[v_index] ** 2 + (p.inertia + p.mass * p.offset**2) * y[w_index] ** 2)

    return energy


_ENERGY_FULL, _ENERGY_REDUCED = _energy(3, 4), _energy(0, 1)


class ChaplyginSleigh(AbstractScene):
    """The noisy Chaplygin sleigh: a knife edge with friction, a random force along it and a random torque.

    The naive thermal model (module docstring): at ``kT = ν/(4ε)`` it drifts forward, ``⟨v⟩ = a⟨ω²⟩/(2ε)``.

    ``drift=True`` keeps the contact point ``(x, y)`` and heading ``θ`` in the
    state; otherwise the state is ``(v, ω)`` alone (their dynamics do not involve
    the position).  The observable ``energy`` is ``H``; in Itô calculus
    ``dE[H]/dt = −4ε E[H] + ν``.

    Arguments:
        drift: keep the contact point ``(x, y)`` and heading ``θ`` in the state.
        **params: the :class:`SleighParameters`.

    Examples:
        >>> import nhsde
        >>> scene = nhsde.scenes.ChaplyginSleigh(eps=0.1, nu=0.5)
        >>> scene.build().layout.names
        ('x', 'y', 'theta', 'v', 'omega')
        >>> print(scene.initial_state())
        [0. 0. 0. 1. 0.]
        >>> nhsde.scenes.ChaplyginSleigh(drift=False).observable_names()
        ('v', 'omega', 'energy')
    """

    name: ClassVar[str] = "chaplygin-sleigh"
    Parameters: ClassVar[type[SleighParameters]] = SleighParameters

    params: SleighParameters
    drift: bool = eqx.field(static=True)

    def __init__(self, *, drift: bool = True, **params):
        self.params = SleighParameters(**params)
        self.drift = bool(drift)

    def build(self) -> StochasticSystem:
        if self.drift:
            layout = StateLayout(
                ("x", "y", "theta", "v", "omega"),
                ("dependent_coordinate", "dependent_coordinate", "independent_coordinate", "velocity", "velocity"),
                angles=("theta",),
            )
            drift, diffusion, linear, energy = _drift_full, _diffusion_full, _linear_full, _ENERGY_FULL
        else:
            layout = StateLayout(("v", "omega"), ("velocity", "velocity"))
            drift, diffusion, linear, energy = _drift_reduced, _diffusion_reduced, _linear_reduced, _ENERGY_REDUCED
        return StochasticSystem(
            drift_fn=drift,
            diffusion_fn=diffusion,
            params=self.params,
            layout=layout,
            noise_dim=2,
            additive_noise=True,
            linear_drift=linear,
            observables=(("energy", energy),),
        )

    def initial_state(self):
        """Moving straight ahead at unit speed from the origin."""
        y = jnp.zeros(5 if self.drift else 2)
        return y.at[3 if self.drift else 0].set(1.0)
