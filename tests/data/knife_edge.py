"""A scene of the user's, for the tests: a knife edge on an inclined plane (docs/guide/your-own-scene.md).

Exact at ``eps = nu = 0`` from rest at the origin spinning at ``ω`` (Neimark & Fufaev):
``x(t) = g sin α sin²(ωt) / (2ω²)``, ``y(t) = g sin α (ωt − ½ sin 2ωt) / (2ω²)``.
"""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from nhsde import AbstractParameters, parameter, sqrt_intensity
from nhsde.scenes import AbstractSpecScene


class KnifeEdgeParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="friction rate")
    nu: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="noise intensity")
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    inertia: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="moment of inertia J")
    slope: jnp.ndarray = parameter(default=1.0, doc="g sin(alpha), the acceleration down the plane")


def kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * (v[0] ** 2 + v[1] ** 2) + 0.5 * p.inertia * v[2] ** 2


def potential(q, pi, t, p):
    return -p.mass * p.slope * q[0]  # x points down the plane


def blade(q, pi, t, p):  # the contact point moves along the blade: -sin(theta) x' + cos(theta) y' = 0
    return jnp.stack([-jnp.sin(q[2]), jnp.cos(q[2]), jnp.zeros((), q.dtype)])[None, :]


def dissipation(q, v, pi, t, p):
    along = jnp.cos(q[2]) * v[0] + jnp.sin(q[2]) * v[1]
    return p.eps * (p.mass * along**2 + p.inertia * v[2] ** 2)


def noise(q, v, pi, t, p):
    zero = jnp.zeros((), q.dtype)
    f, tau = jnp.sqrt(p.mass), jnp.sqrt(p.inertia)
    return sqrt_intensity(p.nu) * jnp.stack(
        [jnp.stack([f * jnp.cos(q[2]), zero]), jnp.stack([f * jnp.sin(q[2]), zero]), jnp.stack([zero, tau])]
    )


class KnifeEdge(AbstractSpecScene):
    """Knife edge on an inclined plane, spinning at rate omega from rest at the origin."""

    name: ClassVar[str] = "knife-edge"
    Parameters: ClassVar[type[KnifeEdgeParameters]] = KnifeEdgeParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y", "theta")
    terms: ClassVar[dict] = dict(
        kinetic_energy=kinetic, potential=potential, constraints=blade, dissipation=dissipation, noise_force=noise
    )
    dependent: ClassVar[tuple[str, ...]] = ("y",)
    angles: ClassVar[tuple[str, ...]] = ("theta",)

    params: KnifeEdgeParameters
    route: str = eqx.field(static=True)
    omega: float = eqx.field(static=True)

    def __init__(self, *, route: str = "multipliers", omega: float = 1.0, **params):
        self.params, self.route, self.omega = KnifeEdgeParameters(**params), route, omega

    def configuration(self):
        return jnp.zeros(3), jnp.array([0.0, 0.0, self.omega])
