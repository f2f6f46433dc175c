"""Scenes written as a :class:`~nhsde.mechanics.MechanicalSpec`: the equations come from the library."""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx

from .._params import AbstractParameters
from .._system import StochasticSystem
from ..mechanics import ROUTES, AbstractForm, MechanicalSpec, formulate

__all__ = ["AbstractSpecScene"]


def checked_route(route: str) -> str:
    if route not in ROUTES:
        raise ValueError(f"route={route!r}; allowed: {', '.join(ROUTES)}.")
    return route


class AbstractSpecScene(eqx.Module):
    """A scene given by its energies and constraints; ``route`` picks the equations (see
    :data:`~nhsde.mechanics.ROUTES`).

    ``dependent`` is the Voronets choice of dependent velocities and
    ``stabilization`` the Baumgarte rate used by the routes with all velocities.
    """

    params: eqx.AbstractVar[AbstractParameters]
    route: eqx.AbstractVar[str]
    dependent: ClassVar[tuple[str, ...]]
    stabilization: ClassVar[float] = 0.0

    @abc.abstractmethod
    def spec(self) -> MechanicalSpec:
        """The mechanical specification."""

    @abc.abstractmethod
    def configuration(self):
        """``(q, q̇)`` of the initial state (velocities on the constraints)."""

    def form(self) -> AbstractForm:
        q, _ = self.configuration()
        rate = self.stabilization if self.route in ("multipliers", "gauss") else 0.0
        return formulate(self.spec(), self.route, dependent=self.dependent, reference=q, stabilization=rate)

    def build(self) -> StochasticSystem:
        return self.form().system()

    def initial_state(self):
        return self.form().state(*self.configuration())
