"""Homogeneous ball rolling without slipping on a translationally vibrating plane (S0 §3).

In the frame of the plane, with ``u`` the velocity of the centre relative to the
plane, rolling ``u_x = r ω_y``, ``u_y = −r ω_x``, the plane's acceleration ``−a``
acting as an inertial force ``m a`` at the centre and viscous rolling resistance
``−c u``, the contact force eliminates to

    (m + J/r²) u̇ = m a − c u   ⇒   u̇ + 2ε u = δ V,   ẋ = u          S0 (3.1)

with ``δ = m/(m + J/r²) = 1/(1 + κ)`` (``J = κ m r²``; ``κ = 2/5`` for a
homogeneous ball, so ``δ = 5/7``), ``2ε = c/(m + J/r²)`` and ``V = a`` white noise
of intensity ``ν`` per axis.  In S0's Rayleigh form ``R = m ε₁ u²`` (§5, ``Φ1``)
this is ``ε = δ ε₁``.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._params import AbstractParameters, parameter, sqrt_intensity
from .._system import StateLayout, StochasticSystem
from ._base import AbstractScene

__all__ = ["BallOnVibratingPlane", "BallParameters", "ball_covariances", "ball_two_time_covariances"]


class BallParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="friction ε of (3.1), 1/s")
    nu: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="intensity ν of the vibration acceleration, per axis")
    radius: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="ball radius r")
    inertia_ratio: jnp.ndarray = parameter(default=0.4, lower=0.0, doc="κ = J/(m r²); 2/5 for a homogeneous ball")

    @property
    def delta(self):
        """δ = 1/(1 + κ) of S0 (3.1)."""
        return 1.0 / (1.0 + self.inertia_ratio)


def _drift_with_position(t, y, p):
    u = y[2:]
    return jnp.concatenate([u, -2.0 * p.eps * u])


def _diffusion_with_position(t, y, p):
    g = sqrt_intensity(p.nu) * p.delta
    return jnp.concatenate([jnp.zeros((2, 2), y.dtype), g * jnp.eye(2, dtype=y.dtype)])


def _drift_velocity(t, y, p):
    return -2.0 * p.eps * y


def _diffusion_velocity(t, y, p):
    return sqrt_intensity(p.nu) * p.delta * jnp.eye(2, dtype=y.dtype)


def _linear_with_position(p):
    """A of the drift A Z: ẋ = u, u̇ = −2ε u."""
    z, i = jnp.zeros((2, 2), p.eps.dtype), jnp.eye(2, dtype=p.eps.dtype)
    return jnp.block([[z, i], [z, -2.0 * p.eps * i]])


def _linear_velocity(p):
    return -2.0 * p.eps * jnp.eye(2, dtype=p.eps.dtype)


def _omega(ux_index, uy_index):
    def omega_x(t, y, p):
        return -y[uy_index] / p.radius

    def omega_y(t, y, p):
        return y[ux_index] / p.radius

    return omega_x, omega_y


_OMEGA_WITH_POSITION = _omega(2, 3)
_OMEGA_VELOCITY = _omega(0, 1)


class BallOnVibratingPlane(AbstractScene):
    """A ball rolling on a randomly vibrating rough plane, slowed by viscous friction.

    The ball of S0 §3, built into a :class:`StochasticSystem` by :meth:`build`.

    Keyword arguments are the :class:`BallParameters` (``eps``, ``nu``, ``radius``,
    ``inertia_ratio``) and what the user wants to observe:
    ``drift=True`` keeps the centre's position ``(x, y)`` in the state (needed for
    the systematic and fluctuation drift), otherwise the state is ``(u_x, u_y)``;
    ``angular_velocity=True`` offers ``omega_x``, ``omega_y`` as observables from
    the rolling constraint (no extra state).

    Arguments:
        drift: keep the centre's position ``(x, y)`` in the state (role ``dependent_coordinate``).
        angular_velocity: offer ``omega_x = −u_y/r``, ``omega_y = u_x/r`` as observables.
        **params: the :class:`BallParameters` ``eps``, ``nu``, ``radius``, ``inertia_ratio``.

    Examples:
        From scene to drift statistics: build, simulate from rest, read the fluctuation drift ``K_{q''}``
        of S0 (6.7), whose growth ``νδ²t/(4ε²)`` at large ``t`` is the ball's diffusion.

        >>> import jax
        >>> import nhsde
        >>> scene = nhsde.scenes.BallOnVibratingPlane(eps=0.5, nu=1.0)
        >>> system = scene.build()
        >>> system.layout.names, system.layout.roles
        (('x', 'y', 'u_x', 'u_y'), ('dependent_coordinate', 'dependent_coordinate', 'velocity', 'velocity'))
        >>> nhsde.scenes.BallOnVibratingPlane(drift=False, angular_velocity=True).observable_names()
        ('u_x', 'u_y', 'omega_x', 'omega_y')
        >>> ens = nhsde.simulate(system, scene.initial_state(), jax.random.key(0), n_paths=64, t1=1.0, dt=0.1)
        >>> drift = nhsde.statistics.drift_statistics(ens)
        >>> drift.names, drift.fluctuation.shape
        (('x', 'y'), (11, 2, 2))
    """

    name: ClassVar[str] = "ball-on-vibrating-plane"
    Parameters: ClassVar[type[BallParameters]] = BallParameters

    params: BallParameters
    drift: bool = eqx.field(static=True)
    angular_velocity: bool = eqx.field(static=True)

    def __init__(self, *, drift: bool = True, angular_velocity: bool = False, **params):
        self.params = BallParameters(**params)
        self.drift = bool(drift)
        self.angular_velocity = bool(angular_velocity)

    def build(self) -> StochasticSystem:
        if self.drift:
            layout = StateLayout(
                ("x", "y", "u_x", "u_y"),
                ("dependent_coordinate", "dependent_coordinate", "velocity", "velocity"),
            )
            drift, diffusion, omega = _drift_with_position, _diffusion_with_position, _OMEGA_WITH_POSITION
            linear = _linear_with_position
        else:
            layout = StateLayout(("u_x", "u_y"), ("velocity", "velocity"))
            drift, diffusion, omega = _drift_velocity, _diffusion_velocity, _OMEGA_VELOCITY
            linear = _linear_velocity
        observables = (("omega_x", omega[0]), ("omega_y", omega[1])) if self.angular_velocity else ()
        return StochasticSystem(
            drift_fn=drift,
            diffusion_fn=diffusion,
            params=self.params,
            layout=layout,
            noise_dim=2,
            additive_noise=True,
            observables=observables,
            linear_drift=linear,
        )

    def initial_state(self):
        """The ball at rest at the origin of the plane: zeros of shape ``(4,)`` (``(2,)`` without ``drift``)."""
        return jnp.zeros(4 if self.drift else 2)


def _phi(x):
    """(1 − e^{−x})/x, exact at x = 0."""
    small = jnp.abs(x) < 1e-3
    xs = jnp.where(small, 1.0, x)
    return jnp.where(small, 1.0 - x / 2 + x**2 / 6 - x**3 / 24, -jnp.expm1(-xs) / xs)


def _psi(s):
    """[s − (1 − e^{−2s}) + (1 − e^{−4s})/4]/(4s³), exact at s = 0 (series below s = 0.1)."""
    small = jnp.abs(s) < 0.1
    ss = jnp.where(small, 1.0, s)
    exact = (ss + jnp.expm1(-2 * ss) - jnp.expm1(-4 * ss) / 4) / (4 * ss**3)
    # Σ_n c_n s^{n−3}/4 with c_n = ((−2)^n − (−4)^n/4)/n!, n ≥ 3
    series = sum(((-2.0) ** n - (-4.0) ** n / 4) / math.factorial(n) / 4 * s ** (n - 3) for n in range(3, 16))
    return jnp.where(small, series, exact)


@jax.jit  # one program, not one per operation
def ball_covariances(t, eps, nu, delta):
    """Exact ``(k_xx, k_xu, k_uu)`` of (3.1) from a deterministic initial state.

    ``k_uu = νδ²(1 − e^{−4εt})/(4ε)``, ``k_xu = νδ²(1 − e^{−2εt})²/(8ε²)``,
    ``k_xx = νδ²/(4ε²) [t − 2(1 − e^{−2εt})/(2ε) + (1 − e^{−4εt})/(4ε)]``;
    limits ``t → ∞`` are S0's ``νδ²/(4ε)``, ``νδ²/(8ε²)``, ``νδ²t/(4ε²)``.
    At ``ε → 0`` they tend to ``νδ²t``, ``νδ²t²/2``, ``νδ²t³/3`` (Brownian velocity).

    Arguments:
        t: time since the deterministic start (scalar or array).
        eps: friction ``ε``.
        nu: noise intensity ``ν`` per axis.
        delta: ``δ = 1/(1 + κ)`` (``5/7`` for a homogeneous ball; :attr:`BallParameters.delta`).

    Returns:
        ``(k_xx, k_xu, k_uu)`` per axis, shaped like ``t``; differentiable in every argument.

    Examples:
        Long after the start ``k_uu → νδ²/(4ε)`` and ``k_xx − νδ²t/(4ε²) → −3νδ²/(16ε³)``:

        >>> from nhsde.scenes import ball_covariances
        >>> k_xx, k_xu, k_uu = ball_covariances(50.0, 1.0, 1.0, 1.0)
        >>> print(round(float(k_xx), 4), round(float(k_xu), 4), round(float(k_uu), 4))
        12.3125 0.125 0.25
    """
    g = nu * delta**2
    s = eps * t
    k_uu = g * t * _phi(4 * s)
    k_xu = g * t**2 * _phi(2 * s) ** 2 / 2
    k_xx = g * t**3 * _psi(s)
    return k_xx, k_xu, k_uu


def ball_two_time_covariances(s, t, eps, nu, delta):
    """Exact covariances of (3.1) per axis between times ``s ≤ t`` from a deterministic initial state.

    For ``t ≥ s`` the state ``Z = (x, u)`` evolves as ``Z(t) = Φ(t − s) Z(s) + (noise after s)`` with
    ``Φ(τ) = [[1, b], [0, e]]``, ``e = e^{−2ετ}``, ``b = (1 − e)/(2ε)``, and the noise after ``s`` is
    independent of ``Z(s)``, so ``Cov(Z(t), Z(s)) = Φ(t − s) K(s)`` with ``K`` of :func:`ball_covariances`:

        Cov(x(t), x(s)) = k_xx(s) + b k_xu(s),     Cov(x(t), u(s)) = k_xu(s) + b k_uu(s),
        Cov(u(t), x(s)) = e k_xu(s),               Cov(u(t), u(s)) = e k_uu(s).

    Arguments:
        s, t: the earlier and the later time (broadcast; ``t ≥ s``).
        eps, nu, delta: as for :func:`ball_covariances`.

    Returns:
        ``(c_xx, c_xu, c_ux, c_uu)``: ``Cov(x(t), x(s))``, ``Cov(x(t), u(s))``, ``Cov(u(t), x(s))``,
        ``Cov(u(t), u(s))``; at ``s = t`` the covariances of :func:`ball_covariances`.

    Examples:
        >>> from nhsde.scenes import ball_covariances, ball_two_time_covariances
        >>> c = ball_two_time_covariances(2.0, 2.0, 0.7, 1.3, 5 / 7)
        >>> k = ball_covariances(2.0, 0.7, 1.3, 5 / 7)
        >>> bool(abs(c[0] - k[0]) < 1e-15 and abs(c[1] - c[2]) < 1e-15 and abs(c[3] - k[2]) < 1e-15)
        True
    """
    k_xx, k_xu, k_uu = ball_covariances(s, eps, nu, delta)
    tau = t - s
    e = jnp.exp(-2 * eps * tau)
    b = tau * _phi(2 * eps * tau)
    return k_xx + b * k_xu, k_xu + b * k_uu, e * k_xu, e * k_uu
