"""Deterministic rolling scenes: a rigid body on a plane or a sphere (S2 §1), a flat base on a sphere (S2 §4.5).

These are ordinary differential equations, the deterministic kind
:class:`~nhsde.scenes.AbstractRollingBodyScene` (not stochastic scenes, not in
``SCENES``): a scene holds the parameters (``params``), the vector field
``vector_field(t, y, params)`` and the state layout, and checks and builds
initial states.  Integrate them with :func:`nhsde.analysis.solve_flow`, check
them with :mod:`nhsde.analysis`.
"""

from __future__ import annotations

import warnings
from typing import ClassVar, Literal

import jax.numpy as jnp
import numpy as np

from ..bodies import (
    Disk,
    FlatBaseField,
    FlatBaseParameters,
    RigidBody,
    RollingField,
    RollingParameters,
    flat_base_energy,
    rolling_energy,
)
from ..bodies._rolling import check_rolling_configuration
from ._base import AbstractRollingBodyScene

__all__ = ["FlatBaseOnSphere", "RollingBody"]

TOLERANCE = 1e-10


def _fix(name: str, violation: float, project: bool) -> None:
    """Raise for a violated constraint, or (``project=True``) report the correction."""
    if violation <= TOLERANCE:
        return
    if not project:
        raise ValueError(
            f"initial state violates {name}: off by {violation:.3g} (allowed {TOLERANCE:g}); "
            "fix it or pass project=True to project onto the constraints."
        )
    warnings.warn(f"initial state projected onto {name}: correction {violation:.3g}.", stacklevel=3)


class RollingBody(AbstractRollingBodyScene):
    """Scene: a rigid body rolling without slipping (``contact='classic'``) or without slipping and
    spinning (``contact='rubber'``) on a horizontal plane or, with ``curvature=k``, on a fixed sphere.

    ``gravity`` (plane only) adds ``U = −m g (γ, r(γ))``.  ``drift=True`` (plane
    only) keeps the horizontal axis ``α`` and the contact point ``(x, y)`` in the
    state; otherwise the state is ``(ω, γ)`` (S2 (1.6), (1.13)).
    """

    params: RollingParameters
    vector_field: RollingField

    Parameters: ClassVar[type[RollingParameters]] = RollingParameters

    def __init__(
        self,
        *,
        body: RigidBody,
        contact: Literal["classic", "rubber"] = "rubber",
        curvature=None,
        gravity=0.0,
        drift: bool = False,
    ):
        if contact not in ("classic", "rubber"):
            raise ValueError(f"contact={contact!r}; allowed: 'classic' (no slip) or 'rubber' (no slip, no spin).")
        sphere = curvature is not None
        if sphere and drift:
            raise ValueError(
                "drift=True keeps the contact point on a plane; on a sphere (curvature given) use drift=False."
            )
        self.params = RollingParameters(body=body, curvature=curvature if sphere else 0.0, gravity=gravity)
        check_rolling_configuration(self.params, sphere)
        self.vector_field = RollingField(rubber=contact == "rubber", sphere=sphere, position=bool(drift))

    def energy(self, y):
        """``E = ½(ω, Ĩω) + U(γ)``."""
        return rolling_energy(y, self.params)

    def initial_state(self, omega, gamma, alpha=None, *, project: bool = False):
        """The state from ``ω``, ``γ`` (and ``α`` when ``drift``; the contact point starts at the origin).

        Checks ``|γ| = 1``, ``(ω, γ) = 0`` for rubber rolling and ``|α| = 1``, ``(α, γ) = 0``;
        a violation raises ``ValueError``, or with ``project=True`` is projected
        away (``γ`` normalised, ``ω`` and ``α`` made orthogonal to ``γ``) with a
        warning that reports the size of the correction.
        """
        omega = np.asarray(omega, np.float64)
        gamma = np.asarray(gamma, np.float64)
        for name, v in (("omega", omega), ("gamma", gamma)):
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name}={v.tolist()}; expected 3 finite components.")
        norm = float(np.linalg.norm(gamma))
        if norm == 0:
            raise ValueError("gamma=0; γ is the unit normal of the support.")
        if isinstance(self.params.body.surface, Disk) and np.hypot(gamma[0], gamma[1]) < 1e-6 * norm:
            raise ValueError(f"gamma={gamma.tolist()}: the disk lies flat (a face contact, not a rolling point).")
        _fix("|γ| = 1", abs(norm - 1.0), project)
        gamma = gamma / norm
        if self.vector_field.rubber:
            _fix("the no-spin constraint (ω, γ) = 0", abs(float(omega @ gamma)), project)
            omega = omega - (omega @ gamma) * gamma
        parts = [omega, gamma]
        if self.vector_field.position:
            if alpha is None:
                raise ValueError("drift=True: pass alpha, the body-axes components of the fixed horizontal axis OX.")
            alpha = np.asarray(alpha, np.float64)
            _fix("(α, γ) = 0", abs(float(alpha @ gamma)), project)
            alpha = alpha - (alpha @ gamma) * gamma
            _fix("|α| = 1", abs(float(np.linalg.norm(alpha)) - 1.0), project)
            parts += [alpha / np.linalg.norm(alpha), np.zeros(2)]
        elif alpha is not None:
            raise ValueError("alpha is part of the state only with drift=True.")
        return jnp.asarray(np.concatenate(parts))


class FlatBaseOnSphere(AbstractRollingBodyScene):
    """Scene: a body rolling (rubber) on a fixed sphere with a flat base, S2 §4.5, (4.6)–(4.7).

    Keyword arguments are the :class:`~nhsde.bodies.FlatBaseParameters`
    (``mass``, ``inertia`` principal moments, ``z`` = third component of the
    contact vector ``r``, ``curvature`` ``k > 0``).  State ``(ω₁, ω₂, r₁, r₂)``.
    """

    params: FlatBaseParameters
    vector_field: FlatBaseField

    Parameters: ClassVar[type[FlatBaseParameters]] = FlatBaseParameters

    def __init__(self, **params):
        self.params = FlatBaseParameters(**params)
        self.vector_field = FlatBaseField()

    def energy(self, y):
        """``E = ½(ω, Ĩω)``."""
        return flat_base_energy(y, self.params)
