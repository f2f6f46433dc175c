"""A rigid body: mass, central inertia tensor, surface, gyrostatic momentum."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._misc import is_concrete
from .._params import AbstractParameters, parameter
from ._surfaces import AbstractSurface

__all__ = ["RigidBody"]


class RigidBody(AbstractParameters):
    """Mass ``m``, inertia tensor ``I`` about the centre of mass, surface ``r(γ)``, rotor ``S``.

    All vectors in the body axes (principal axes when ``I`` is diagonal).
    ``inertia`` is a symmetric positive-definite ``(3, 3)`` matrix or the ``(3,)``
    principal moments; ``gyrostat`` is the constant angular momentum ``S`` of a
    balanced rotor spinning uniformly inside the body, S2 (1.7).

    Arguments:
        mass: ``m > 0``.
        inertia: ``I`` about the centre of mass, ``(3, 3)`` or principal moments ``(3,)``.
        surface: the body's surface (:class:`Sphere`, :class:`Ellipsoid`, …).
        gyrostat: the rotor's angular momentum ``S``.
    """

    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True, doc="mass m")
    inertia: jnp.ndarray = parameter(default=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), doc="I")
    surface: AbstractSurface  # pyright: ignore[reportGeneralTypeIssues]  (__init__ is custom: no field order)
    gyrostat: jnp.ndarray = parameter(default=(0.0, 0.0, 0.0), doc="gyrostatic momentum S")

    def __init__(self, *, mass=1.0, inertia=(1.0, 1.0, 1.0), surface: AbstractSurface, gyrostat=(0.0, 0.0, 0.0)):
        if not isinstance(surface, AbstractSurface):
            raise TypeError(
                f"RigidBody: surface={surface!r}; expected a surface, e.g. nhsde.bodies.Sphere(radius=1.0)."
            )
        inertia = jnp.asarray(inertia)
        if inertia.shape == (3,):
            inertia = jnp.diag(inertia)
        self.mass = jnp.asarray(mass)
        self.inertia = inertia
        self.surface = surface
        self.gyrostat = jnp.asarray(gyrostat)

    def __check_init__(self):
        if np.shape(self.inertia) != (3, 3):
            raise ValueError(f"RigidBody: inertia has shape {np.shape(self.inertia)}; expected (3,) or (3, 3).")
        if np.shape(self.gyrostat) != (3,):
            raise ValueError(f"RigidBody: gyrostat has shape {np.shape(self.gyrostat)}; expected (3,).")
        if not is_concrete(self.inertia):
            return
        i = np.asarray(self.inertia, np.float64)
        eig = np.linalg.eigvalsh(0.5 * (i + i.T))
        if not np.allclose(i, i.T, rtol=1e-12, atol=1e-12 * np.max(np.abs(i))) or np.min(eig) <= 0:
            raise ValueError(
                f"RigidBody: inertia={i.tolist()} is not symmetric positive definite "
                f"(eigenvalues {eig.tolist()}); an inertia tensor must be."
            )
