"""Scenes written as a :class:`~nhsde.mechanics.MechanicalSpec`: the equations come from the library."""

# No `from __future__ import annotations`: equinox reads AbstractVar/AbstractClassVar from live annotations.
import abc
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

from .._system import StochasticSystem
from ..mechanics import ROUTES, AbstractForm, MechanicalSpec, formulate
from ._base import AbstractScene

if TYPE_CHECKING:
    from typing import ClassVar as AbstractClassVar

    from equinox import AbstractVar
else:
    from equinox import AbstractClassVar, AbstractVar

__all__ = ["AbstractSpecScene"]


class AbstractSpecScene(AbstractScene):
    """A scene given by its energies and constraints; ``route`` picks the equations (see
    :data:`~nhsde.mechanics.ROUTES`).

    A concrete spec scene declares, besides ``name``, ``Parameters`` and ``params``:

    - ``coordinates`` (class variable): the names of ``q``; ``angles`` (class variable, default none): those the
      terms read through ``sin``/``cos`` (a path fails where one passes the precision's resolution,
      :class:`~nhsde.StateLayout`);
    - ``terms``: the :class:`~nhsde.mechanics.MechanicalSpec` functions by keyword
      (``kinetic_energy`` or ``mass_matrix``, ``potential``, ``constraints``,
      ``holonomic``, ``servo``, ``dissipation``, ``noise_force``, …), a class variable or a property;
    - ``dependent`` (class variable): the Voronets choice of dependent velocities
      of the reduced routes, and in every route the coordinates with the role
      ``dependent_coordinate`` (the drift) (``None``: chosen by pivoting at the initial configuration);
    - ``stabilization`` (class variable, default 10/s): the Baumgarte rate of the
      routes with all velocities;
    - a static field ``route``, a keyword-only ``__init__(self, *, route=..., **params)``
      setting ``params`` and the options, and ``configuration() -> (q, q̇)``.

    ``spec()``, ``form()``, ``build()`` and ``initial_state()`` follow from these: do not implement them.
    The guide's page "Your own scene" writes one, a knife edge on an inclined plane.
    """

    route: AbstractVar[str]
    coordinates: AbstractClassVar[tuple[str, ...]]
    terms: AbstractVar[Mapping[str, Any]]
    dependent: ClassVar[tuple[str, ...] | None] = None
    angles: ClassVar[tuple[str, ...]] = ()
    stabilization: ClassVar[float] = 10.0

    def __check_init__(self):
        if self.route not in ROUTES:
            raise ValueError(f"route={self.route!r}; allowed: {', '.join(ROUTES)}.")

    @abc.abstractmethod
    def configuration(self) -> tuple[Any, Any]:
        """``(q, q̇)`` of the initial state (velocities on the constraints)."""

    def spec(self) -> MechanicalSpec:
        """The mechanical specification: ``coordinates``, ``angles``, ``params`` and the ``terms``."""
        return MechanicalSpec(coordinates=self.coordinates, angles=self.angles, params=self.params, **self.terms)

    def form(self) -> AbstractForm:
        q, _ = self.configuration()
        rate = self.stabilization if self.route in ("multipliers", "gauss") else 0.0
        return formulate(self.spec(), self.route, dependent=self.dependent, reference=q, stabilization=rate)

    def build(self) -> StochasticSystem:
        """The stochastic system of :meth:`spec` by the scene's ``route``.

        Returns:
            the :class:`~nhsde.StochasticSystem` of :meth:`form`.
        """
        return self.form().system()

    def initial_state(self):
        """The state of :meth:`configuration` ``(q, q̇)`` in the route's variables.

        Returns:
            a ``(d,)`` state of :meth:`build`'s system.
        """
        return self.form().state(*self.configuration())
