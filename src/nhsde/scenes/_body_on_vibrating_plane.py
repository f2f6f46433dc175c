"""Heavy convex body rolling on a translationally vibrating, absolutely rough plane, S0 §5.

In the frame of the plane the body rolls without slipping (classic rolling, S2
(1.4)); the plane's acceleration ``a`` acts as the inertial force ``−m a`` at the
centre of mass ``C`` (S0: ``Q = −m b Ö₁O``), gravity as ``−m g γ``.  In the body
axes, with ``v_C = r × ω`` the velocity of ``C`` relative to the plane:

    Ĩω̇ = (Ĩω + S) × ω − m r × (ω × ṙ) + F × r,   γ̇ = γ × ω,        S0 (5.3)–(5.5)

    Φ₁ = mε U_e²:  F = −m g γ − 2mε v_C − m√ν V,
    Φ₂ = mε U²:    F = −m g γ − 2mε (v_C + π) − m π̇,   π̇ + 2επ = √ν V (shaping filter),

``V`` white noise of unit intensity per axis (S0's ``V`` of intensity ``ν``, with
``√ν`` folded in).  ``Φ₂`` keeps the plane's velocity ``π`` in the state (body
axes: ``π̇ = −2επ − ω × π + √ν V``); its ``π`` terms cancel in ``F`` and the body
obeys the same equations as under ``Φ₁`` — S0 writes (5.5) once for both.
The vibration is isotropic and independent of the orientation, so its body-axes
components are again a standard white noise: no orientation matrix is needed.

Stationary density (S0 Statement 2).  The friction is ``−2εm b bᵀ ∂H/∂p`` and
the noise ``−m√ν b V`` in canonical variables (S0 (5.5)); in ``ω`` they are
``−2εm Ĩ⁻¹ KᵀK ω`` and ``m√ν Ĩ⁻¹ K V`` with ``K = [r]×``.  For
``f = N e^{−αH}`` the dissipative probability flux vanishes iff

    −2εm Ĩ⁻¹KᵀKω f + ½ m²ν Ĩ⁻¹KᵀK Ĩ⁻¹ (αĨω) f = 0   ⇔   α = 4ε/(mν),

and the conservative flux is divergence-free because ``N`` is an invariant
density and ``H`` an integral of the frictionless system.  For a dynamically
symmetric body of revolution ``N(θ) = 1/δ(θ)``, ``δ = (1 + mμ²/C + mκ²/A)^{1/2}``
(S0 §5), and the nutation angle has the marginal density
``c N(θ) ∫ e^{−αH} dp ∝ N(θ) sin θ det Ĩ(θ)^{1/2} e^{−αU(θ)}``.

Ergodicity caveat.  All forces act at ``C``, so their moments about ``P`` are
orthogonal to ``r``: the noise and friction never change ``J = (Ĩω, r)``.  For a
ball with its centre of mass on the symmetry axis (Routh's sphere) ``J`` is
Jellett's integral of the frictionless motion, so it is conserved by the whole
stochastic system: the stationary law is reached only within each level of ``J``,
and from a state at rest (``J = 0``) the ensemble does not tend to
``N e^{−αH}``.  For other bodies of revolution (e.g. a spheroid) ``J`` is not
an integral, but it relaxes slowly (time scale ~40 for the default body).
"""

from __future__ import annotations

from functools import partial
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._misc import FAST_COMPILE, is_concrete
from .._params import AbstractParameters, parameter, sqrt_intensity
from .._system import StateLayout, StochasticSystem
from ..bodies import (
    Ellipsoid,
    RigidBody,
    angular_acceleration,
    contact_inertia,
    contact_kinematics,
    fibonacci_directions,
    position_rates,
    rolling_energy,
)
from ..bodies._rolling import solve3
from ._base import AbstractScene

__all__ = [
    "BodyOnVibratingPlane",
    "VibratingPlaneParameters",
    "revolution_measure_s0",
    "sample_stationary",
    "stationary_nutation_density",
]


class VibratingPlaneParameters(AbstractParameters):
    body: RigidBody
    eps: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="specific friction ε of Φ")
    nu: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="intensity ν of the vibration acceleration, per axis")
    gravity: jnp.ndarray = parameter(default=1.0, lower=0.0, doc="gravitational acceleration g")

    def __init__(self, *, body: RigidBody, eps=0.5, nu=1.0, gravity=1.0):
        if not isinstance(body, RigidBody):
            raise TypeError(f"VibratingPlaneParameters: body={body!r}; expected nhsde.bodies.RigidBody.")
        self.body = body
        self.eps, self.nu, self.gravity = jnp.asarray(eps), jnp.asarray(nu), jnp.asarray(gravity)

    @property
    def alpha(self):
        """``α = 4ε/(mν)`` of the stationary density ``N e^{−αH}``."""
        return 4 * self.eps / (self.body.mass * self.nu)


def _default_body() -> RigidBody:
    """A homogeneous oblate spheroid, semi-axes ``(1, 1, 0.6)``, mass 1: a body of revolution."""
    return RigidBody(mass=1.0, inertia=(0.272, 0.272, 0.4), surface=Ellipsoid(semi_axes=jnp.array([1.0, 1.0, 0.6])))


class _Layout(eqx.Module):
    position: bool = eqx.field(static=True)
    filter: bool = eqx.field(static=True)

    def slices(self):
        """Index of ``α`` (or None) and of ``π`` (or None) in the state."""
        alpha = 6 if self.position else None
        pi = (11 if self.position else 6) if self.filter else None
        return alpha, pi


class _Drift(eqx.Module):
    layout: _Layout

    def __call__(self, t, y, p: VibratingPlaneParameters):
        body = p.body
        omega, gamma = y[:3], y[3:6]
        n, n_dot, r, r_dot = contact_kinematics(body.surface, omega, gamma)
        m = body.mass
        v_c = jnp.cross(r, omega)
        alpha_at, pi_at = self.layout.slices()
        pi_dot = None  # Φ₂'s plane velocity's rate, where the state has it
        if pi_at is None:  # Φ₁: friction on the velocity relative to the plane
            force = -m * p.gravity * n - 2 * m * p.eps * v_c
        else:  # Φ₂: friction on the absolute velocity v_C + π; inertial force −m π̇, drift part 2mεπ
            pi = y[pi_at : pi_at + 3]
            pi_dot = -2 * p.eps * pi - jnp.cross(omega, pi)
            force = -m * p.gravity * n - 2 * m * p.eps * (v_c + pi) + 2 * m * p.eps * pi
        omega_dot = angular_acceleration(
            body.inertia, m, body.gyrostat, omega, n, n_dot, r, r_dot, jnp.cross(force, r), rubber=False
        )
        parts = [omega_dot, jnp.linalg.norm(gamma) * n_dot]
        if alpha_at is not None:
            parts.append(position_rates(y[alpha_at : alpha_at + 3], omega, n, r_dot))
        if pi_dot is not None:
            parts.append(pi_dot)
        return jnp.concatenate(parts)


class _Diffusion(eqx.Module):
    layout: _Layout

    def __call__(self, t, y, p: VibratingPlaneParameters):
        body = p.body
        n = y[3:6] / jnp.linalg.norm(y[3:6])
        r = body.surface.contact_point(n)
        cross_r = jax.vmap(lambda e: jnp.cross(r, e), out_axes=1)(jnp.eye(3, dtype=y.dtype))  # [r]×
        it = contact_inertia(body.inertia, body.mass, r)
        root = sqrt_intensity(p.nu)
        b_omega = body.mass * root * solve3(it, cross_r)  # torque (−m√ν V) × r = m√ν r × V
        rows = [b_omega, jnp.zeros((y.shape[0] - 3, 3), y.dtype)]
        _, pi_at = self.layout.slices()
        if pi_at is not None:
            rows = [b_omega, jnp.zeros((pi_at - 3, 3), y.dtype), root * jnp.eye(3, dtype=y.dtype)]
        return jnp.concatenate(rows)


def _theta(t, y, p):
    return jnp.arccos(jnp.clip(y[5] / jnp.linalg.norm(y[3:6]), -1.0, 1.0))


def _energy(t, y, p):
    return rolling_energy(y, p)


class BodyOnVibratingPlane(AbstractScene):
    """A heavy convex body rolling on a randomly vibrating rough plane, with friction phi1 or phi2.

    S0 §5, friction ``Φ₁`` or ``Φ₂``.

    Keyword arguments: ``eps``, ``nu``, ``gravity`` and ``body`` (a
    :class:`~nhsde.bodies.RigidBody`; default: a homogeneous oblate spheroid with
    semi-axes ``(1, 1, 0.6)``, a body of revolution); ``friction='phi1'``
    (relative velocity, white vibration acceleration) or ``'phi2'`` (absolute
    velocity, coloured plane velocity ``π`` in the state); ``drift=True`` keeps
    the horizontal axis ``α`` and the contact point ``(x, y)``.  State
    ``(ω, γ)`` (body axes).  Observables ``theta`` (nutation angle) and ``energy``.

    Arguments:
        body: the rolling :class:`~nhsde.bodies.RigidBody` (default: the oblate spheroid above).
        friction: ``'phi1'`` or ``'phi2'``, S0 §5.
        drift: keep ``α`` and the contact point ``(x, y)`` in the state.
        **params: the :class:`VibratingPlaneParameters` ``eps``, ``nu``, ``gravity``.
    """

    name: ClassVar[str] = "body-on-vibrating-plane"
    Parameters: ClassVar[type[VibratingPlaneParameters]] = VibratingPlaneParameters

    params: VibratingPlaneParameters
    friction: str = eqx.field(static=True)
    drift: bool = eqx.field(static=True)

    def __init__(
        self,
        *,
        body: RigidBody | None = None,
        friction: Literal["phi1", "phi2"] = "phi1",
        drift: bool = False,
        **params,
    ):
        if friction not in ("phi1", "phi2"):
            raise ValueError(
                f"friction={friction!r}; allowed: 'phi1' (relative velocity) or 'phi2' (absolute velocity)."
            )
        self.params = VibratingPlaneParameters(body=_default_body() if body is None else body, **params)
        self.friction = friction
        self.drift = bool(drift)

    def build(self) -> StochasticSystem:
        layout = _Layout(position=self.drift, filter=self.friction == "phi2")
        names = ("omega_1", "omega_2", "omega_3", "gamma_1", "gamma_2", "gamma_3")
        roles = ("velocity",) * 3 + ("independent_coordinate",) * 3
        if self.drift:
            names += ("alpha_1", "alpha_2", "alpha_3", "x", "y")
            roles += ("independent_coordinate",) * 3 + ("dependent_coordinate",) * 2
        if layout.filter:
            names += ("pi_1", "pi_2", "pi_3")
            roles += ("random_parameter",) * 3
        # b depends on γ only and γ carries no noise, so Σⱼ(∂bⱼ/∂Z)bⱼ = 0 and the Itô and Stratonovich
        # forms coincide; tagged Stratonovich so that Euler–Heun (first order in the drift) needs no conversion.
        return StochasticSystem(
            drift_fn=_Drift(layout),
            diffusion_fn=_Diffusion(layout),
            params=self.params,
            layout=StateLayout(names, roles),
            noise_dim=3,
            interpretation="stratonovich",
            observables=(("theta", _theta), ("energy", _energy)),
        )

    def initial_state(self):
        """At rest, ``e₃`` up, ``e₁`` along ``OX``, contact point at the origin, plane at rest."""
        parts = [jnp.zeros(3), jnp.array([0.0, 0.0, 1.0])]
        if self.drift:
            parts += [jnp.array([1.0, 0.0, 0.0]), jnp.zeros(2)]
        if self.friction == "phi2":
            parts.append(jnp.zeros(3))
        return jnp.concatenate(parts)


def _symmetric(body: RigidBody):
    if is_concrete(body.inertia):
        i = np.asarray(body.inertia)
        if not (np.allclose(i, np.diag(np.diag(i))) and np.isclose(i[0, 0], i[1, 1])):
            raise ValueError(
                f"S0's N(θ) is for a dynamically symmetric body of revolution, I = diag(A, A, C); got {i.tolist()}."
            )
    return body.inertia[0, 0], body.inertia[2, 2]


def _delta(body: RigidBody, theta):
    """``δ(θ) = (1 + mμ²/C + mκ²/A)^{1/2}``, ``μ = z sin θ + z_θ cos θ``, ``κ = −z cos θ + z_θ sin θ`` (S0 §5)."""
    a, c = _symmetric(body)

    def height(th):
        gamma = jnp.stack([jnp.sin(th), jnp.zeros_like(th), jnp.cos(th)])
        return -jnp.dot(gamma, body.surface.contact_point(gamma))

    z, z_theta = jax.value_and_grad(height)(theta)
    mu = z * jnp.sin(theta) + z_theta * jnp.cos(theta)
    kappa = -z * jnp.cos(theta) + z_theta * jnp.sin(theta)
    return jnp.sqrt(1 + body.mass * mu**2 / c + body.mass * kappa**2 / a)


def revolution_measure_s0(y, p):
    """Invariant density of classic rolling of a body of revolution in ``(ω, γ)``: ``N(θ) det Ĩ``.

    S0 §5 gives ``N(θ) = 1/δ(θ)`` in the canonical variables ``(ψ, θ, φ, p)``;
    ``dp = sin θ det Ĩ dω`` and ``dθ dφ = dγ/sin θ`` turn it into ``N det Ĩ dω dγ``.
    ``p`` is anything with a ``body``.
    """
    body = p.body
    n = y[3:6] / jnp.linalg.norm(y[3:6])
    theta = jnp.arccos(n[2])
    r = body.surface.contact_point(n)
    return jnp.linalg.det(contact_inertia(body.inertia, body.mass, r)) / _delta(body, theta)


def stationary_nutation_density(p: VibratingPlaneParameters, theta):
    """Marginal density of the nutation angle ``θ ∈ [0, π]``, S0 Statement 2 with ``N(θ)`` of S0 §5:

        f(θ) = c N(θ) ∫ e^{−αH} dp = c' N(θ) sin θ (det Ĩ(θ))^{1/2} e^{−αU(θ)},   α = 4ε/(mν),

    (the Gaussian ``p``-integral of ``H = ½pᵀG⁻¹p + U``, ``det G = sin²θ det Ĩ``),
    normalised on ``[0, π]`` (Gauss–Legendre, 256 nodes).
    """
    _symmetric(p.body)
    return _nutation_density(p, jnp.atleast_1d(jnp.asarray(theta, jnp.result_type(float))))


@partial(jax.jit, compiler_options=FAST_COMPILE)
def _nutation_density(p: VibratingPlaneParameters, theta):
    body = p.body

    def log_weight(th):
        gamma = jnp.stack([jnp.sin(th), jnp.zeros_like(th), jnp.cos(th)])
        r = body.surface.contact_point(gamma)
        u = -body.mass * p.gravity * jnp.dot(gamma, r)
        det = jnp.linalg.det(contact_inertia(body.inertia, body.mass, r))
        return jnp.log(jnp.sin(th)) + 0.5 * jnp.log(det) - p.alpha * u - jnp.log(_delta(body, th))

    x, w = np.polynomial.legendre.leggauss(256)
    nodes = jnp.asarray(0.5 * np.pi * (x + 1), theta.dtype)
    log_nodes = jax.vmap(log_weight)(nodes)
    shift = jnp.max(log_nodes)
    total = 0.5 * np.pi * jnp.dot(jnp.asarray(w, theta.dtype), jnp.exp(log_nodes - shift))
    return jnp.exp(jax.vmap(log_weight)(theta) - shift) / total


def sample_stationary(p: VibratingPlaneParameters, key, n: int, measure=revolution_measure_s0):
    """``n`` states ``(ω, γ)`` drawn from ``c ρ(γ) e^{−αH(ω, γ)}`` (S0 Statement 2; ``ρ = measure``).

    ``γ`` by rejection from the uniform law on the sphere with the weight
    ``ρ(γ) det Ĩ(γ)^{−1/2} e^{−αU(γ)}`` (the ``ω``-integral done), bounded by its
    maximum over a fine grid and the candidates times ``e^{0.1}``; then ``ω`` given
    ``γ`` is Gaussian with covariance ``(αĨ)⁻¹``.  Use it to start an ensemble in
    the stationary law.
    """
    body = p.body

    def log_weight(gamma):
        r = body.surface.contact_point(gamma)
        it = contact_inertia(body.inertia, body.mass, r)
        y = jnp.concatenate([jnp.zeros(3, gamma.dtype), gamma])
        u = -body.mass * p.gravity * jnp.dot(gamma, r)
        return jnp.log(measure(y, p)) - 0.5 * jnp.log(jnp.linalg.det(it)) - p.alpha * u

    def omega(gamma, z):
        it = contact_inertia(body.inertia, body.mass, body.surface.contact_point(gamma))
        return jnp.linalg.cholesky(jnp.linalg.inv(p.alpha * it)) @ z

    log_weights = jax.jit(jax.vmap(log_weight), compiler_options=FAST_COMPILE)
    bound = float(jnp.max(log_weights(jnp.asarray(fibonacci_directions(8192))))) + 0.1
    accepted, k = [], key
    while sum(len(a) for a in accepted) < n:
        k, k_dir, k_acc = jax.random.split(k, 3)
        g = jax.random.normal(k_dir, (4 * n, 3))
        g = g / jnp.linalg.norm(g, axis=1, keepdims=True)
        lw = log_weights(g)
        if float(jnp.max(lw)) > bound:
            raise RuntimeError("sample_stationary: the rejection bound was exceeded; the weight is not smooth enough.")
        keep = jnp.log(jax.random.uniform(k_acc, (4 * n,))) < lw - bound
        accepted.append(np.asarray(g[keep]))
    gammas = jnp.asarray(np.concatenate(accepted)[:n])
    omegas = jax.jit(jax.vmap(omega), compiler_options=FAST_COMPILE)(
        gammas, jax.random.normal(jax.random.fold_in(k, 1), (n, 3), gammas.dtype)
    )
    return jnp.concatenate([omegas, gammas], axis=1)
