"""The one scene contract, the registry derived from it, and the deterministic rolling kind."""

# No `from __future__ import annotations`: equinox reads AbstractVar/AbstractClassVar from live annotations.
import abc
import re
import types
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import equinox as eqx

from .._params import AbstractParameters
from .._system import StateLayout, StochasticSystem

if TYPE_CHECKING:
    from typing import ClassVar as AbstractClassVar

    from equinox import AbstractVar
else:
    from equinox import AbstractClassVar, AbstractVar

__all__ = ["AbstractRollingBodyScene", "AbstractScene", "scene_registry"]


def is_abstract(cls: type) -> bool:
    """Equinox's notion: an abstract method, ``AbstractVar`` or ``AbstractClassVar`` is left unimplemented."""
    return any(getattr(cls, a, ()) for a in ("__abstractmethods__", "__abstractvars__", "__abstractclassvars__"))


def _refuse_concrete_bases(cls: type, kind: type) -> None:
    for base in cls.__mro__[1:]:
        if issubclass(base, kind) and not is_abstract(base):
            raise TypeError(
                f"{cls.__name__} subclasses the concrete scene {base.__name__}; concrete scenes are final: "
                f"subclass an abstract base ({kind.__name__}, …) and hold or build a {base.__name__} instead."
            )


class AbstractScene(eqx.Module):
    """A stochastic scene: one mechanical system, described declaratively, that builds its SDE.

    The contract, kept by every concrete scene (concrete scenes are final: subclassing one raises):

    - ``name`` (class variable): the CLI and run-file name, e.g. ``"ball-on-vibrating-plane"``;
      :meth:`description` (the docstring's first line) is what ``nhsde scenes`` prints.
    - ``Parameters`` (class variable): its :class:`~nhsde.AbstractParameters` class, and ``params``
      an instance.  Every physical constant is a pytree leaf of ``params``: never a static field,
      never closed over (the system's functions receive ``params``), so ``jax.grad`` reaches it.
    - ``intensities`` (class variable, default ``("nu",)``): the parameters that are white-noise
      intensities ``ν``; every noise amplitude is :func:`~nhsde.sqrt_intensity` ``(ν) = √ν``, whose
      ``ν``-derivative at ``ν = 0`` raises instead of returning ``inf``/``nan``.
    - Construction is keyword-only, ``Scene(**options, **parameters)``: the options (``drift``,
      ``route``, …) are static fields with defaults, the rest are passed to ``Parameters``.
    - ``build() -> StochasticSystem`` with ``params`` as its parameters and a state holding only
      what the options ask for; ``initial_state()`` a ``(d,)`` state of that system;
      ``observable_names()`` what it can observe (state components and derived observables).

    Scenes defined in :mod:`nhsde.scenes` are registered under ``name`` in ``nhsde.scenes.SCENES``.
    """

    params: AbstractVar[AbstractParameters]
    name: AbstractClassVar[str]
    Parameters: AbstractClassVar[type[AbstractParameters]]
    intensities: ClassVar[tuple[str, ...]] = ("nu",)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        _refuse_concrete_bases(cls, AbstractScene)

    @abc.abstractmethod
    def build(self) -> StochasticSystem:
        """The stochastic system of this scene.

        Returns:
            a :class:`~nhsde.StochasticSystem` whose ``params`` are this scene's ``params`` and whose state
            holds what the scene's options ask for.
        """

    @abc.abstractmethod
    def initial_state(self) -> Any:
        """A ``(d,)`` state of :meth:`build`'s system.

        Returns:
            a ``(d,)`` array, the scene's documented starting state (``simulate``'s ``y0``).
        """

    def observable_names(self) -> tuple[str, ...]:
        """The names :meth:`build`'s system can observe (``system.observe(names)``)."""
        return self.build().observable_names()

    @classmethod
    def description(cls) -> str:
        """One line of plain text: the first line of the class docstring, reST roles and literals unwrapped
        (``:class:`~a.B``` → ``B``, ````x```` → ``x``)."""
        line = ((cls.__doc__ or "").strip().splitlines() or [""])[0]
        line = re.sub(r":[\w:]+:`~?(?:[^`<]*<)?([^`>]*)>?`", lambda m: m.group(1).rsplit(".", 1)[-1], line)
        return line.replace("``", "")


def scene_registry(package: str) -> Mapping[str, type[AbstractScene]]:
    """``name → class`` of the concrete :class:`AbstractScene` subclasses defined under ``package``
    (read-only; in the order their classes were made); two scenes with one name raise."""
    found: dict[str, type[AbstractScene]] = {}

    def walk(kls: type[AbstractScene]) -> None:
        for sub in kls.__subclasses__():
            if not is_abstract(sub) and sub.__module__.startswith(package + "."):
                other = found.setdefault(sub.name, sub)
                if other is not sub:
                    raise TypeError(f"scenes {other.__name__} and {sub.__name__} are both called {sub.name!r}.")
            walk(sub)

    walk(AbstractScene)
    return types.MappingProxyType(found)


class RollingVectorField(Protocol):
    """What a rolling scene integrates: ``v(t, y, params)``, and the ``layout`` of its state ``y``."""

    @property
    def layout(self) -> StateLayout: ...

    def __call__(self, t: Any, y: Any, params: Any, /) -> Any: ...


class AbstractRollingBodyScene(eqx.Module):
    """A deterministic rolling scene: the ordinary differential equation ``ẏ = v(t, y, params)``.

    Not an :class:`AbstractScene` and not in ``SCENES``: it has no noise and no
    ``build()``, and its initial state is chosen by the caller (``(ω, γ)`` with
    checks), so it cannot keep the stochastic contract.  It holds ``params``
    (leaves), the ``vector_field`` with its state ``layout``, and ``energy(y)``;
    integrate it with :func:`nhsde.analysis.solve_flow`, check it with
    :mod:`nhsde.analysis`.  Concrete ones are final.
    """

    params: AbstractVar[AbstractParameters]
    vector_field: AbstractVar[RollingVectorField]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        _refuse_concrete_bases(cls, AbstractRollingBodyScene)

    @property
    def layout(self) -> StateLayout:
        return self.vector_field.layout

    @abc.abstractmethod
    def energy(self, y) -> Any:
        """The energy, a first integral of the flow."""
