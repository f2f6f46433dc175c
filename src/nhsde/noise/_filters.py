"""Shaping filters: random parameters ``π`` of S0 (1.2) as coloured noise.

A filter is the Itô SDE ``dπ = φ(π, t) dt + ψ(π, t) dW`` (1.2).
:func:`with_shaping_filter` drives a system with the filter output instead of
white noise: ``dZ = a dt + b dW`` becomes

    dπ = φ(π, t) dt + ψ(π, t) dW,     Ż = a_S(Z, t) + b(Z, t) π,

with ``a_S`` the system's Stratonovich drift.  Coloured noise is a smooth
input, so the system's equations hold in the ordinary sense (S0 §2, Remark:
they are the Stratonovich ones); hence, as the filter's correlation time goes
to zero with its low-frequency intensity fixed, the result tends to the
original system (Wong–Zakai).  The filter states come first, with role
``random_parameter`` (S0 (1.15): ``Z = [π, q, p']``), and exist only in systems
built this way.
"""

# No ``from __future__ import annotations`` here: equinox reads AbstractVar annotations, which must not be strings.

import abc
import dataclasses
from collections.abc import Callable
from typing import Any, Protocol, cast

import equinox as eqx
import jax.numpy as jnp
from equinox import AbstractVar
from jaxtyping import Array, PyTree

from .._params import AbstractParameters, parameter
from .._system import ItoStratonovichDrift, StateLayout, StochasticSystem

__all__ = ["AbstractShapingFilter", "FilteredParameters", "OrnsteinUhlenbeck", "ShapingFilter", "with_shaping_filter"]


class AbstractShapingFilter(eqx.Module):
    """``dπ = φ(π, t) dt + ψ(π, t) dW`` (S0 (1.2), Itô); the filter is also its own parameters."""

    names: AbstractVar[tuple[str, ...]]
    noise_dim: AbstractVar[int]
    additive_noise: AbstractVar[bool]

    @abc.abstractmethod
    def drift(self, t, pi) -> Array:
        """``φ(π, t)``."""

    @abc.abstractmethod
    def diffusion(self, t, pi) -> Array:
        """``ψ(π, t)``, shape ``(len(names), noise_dim)``."""


class OrnsteinUhlenbeck(AbstractShapingFilter, AbstractParameters):
    """Coloured noise ``π̇ = −γ π + γ √ν V`` of intensity ``ν`` and correlation time ``1/γ``, per name.

    Correlation ``(γν/2) e^{−γ|τ|}`` (stationary variance ``γν/2``), spectral
    density at zero ``ν``: as ``γ → ∞`` it tends to white noise of intensity ``ν``.
    S0 §5's filter ``π̇ + 2επ = V`` is ``rate = 2ε``, ``intensity = 1/(2ε)²``.

    Arguments:
        names: one state name per output channel, e.g. ``("pi_x", "pi_y")``.
        rate: ``γ = 1/correlation time``, ``> 0`` (scalar or per channel).
        intensity: ``ν``, the low-frequency intensity (scalar or per channel).

    Examples:
        >>> import nhsde
        >>> pi = nhsde.noise.OrnsteinUhlenbeck(names=("pi_x", "pi_y"), rate=4.0, intensity=0.5)
        >>> print(pi.stationary_variance())  # γν/2
        [1. 1.]
    """

    names: tuple[str, ...] = eqx.field(static=True)
    rate: Array = parameter(default=1.0, lower=0.0, strict=True, per_channel=True, doc="γ = 1/correlation time")
    intensity: Array = parameter(default=1.0, lower=0.0, per_channel=True, doc="ν: low-frequency intensity")

    def __check_init__(self):
        if isinstance(self.names, str) or not isinstance(self.names, tuple) or not self.names:
            raise ValueError(f"names={self.names!r}; expected a non-empty tuple of state names, e.g. ('pi_x', 'pi_y').")

    @property
    def noise_dim(self) -> int:
        return len(self.names)

    @property
    def additive_noise(self) -> bool:
        return True

    def drift(self, t, pi):
        return -self.rate.astype(pi.dtype) * pi

    def diffusion(self, t, pi):
        scale = self.rate * jnp.sqrt(self.intensity)
        return jnp.diag(jnp.broadcast_to(scale.astype(pi.dtype), pi.shape))

    def stationary_variance(self) -> Array:
        """``γν/2`` per channel."""
        return jnp.broadcast_to(self.rate * self.intensity / 2, (self.noise_dim,))


class ShapingFilter(AbstractShapingFilter):
    """A general filter ``dπ = φ(t, π, params) dt + ψ(t, π, params) dW`` (S0 (1.2)).

    ``drift_fn``/``diffusion_fn`` are pure functions with diffrax's signature;
    ``params`` is a pytree of leaves (e.g. an :class:`~nhsde.AbstractParameters`).

    Arguments:
        drift_fn: ``φ(t, π, params) -> (k,)``.
        diffusion_fn: ``ψ(t, π, params) -> (k, noise_dim)``.
        params: the filter's parameters.
        names: one state name per output ``π``.
        noise_dim: the dimension of the driving noise.
        additive_noise: ``ψ`` does not depend on ``π`` (keyword only).
    """

    drift_fn: Callable = eqx.field(static=True)
    diffusion_fn: Callable = eqx.field(static=True)
    params: PyTree
    names: tuple[str, ...] = eqx.field(static=True)
    noise_dim: int = eqx.field(static=True)
    additive_noise: bool = eqx.field(static=True, default=False, kw_only=True)

    def drift(self, t, pi):
        return self.drift_fn(t, pi, self.params)

    def diffusion(self, t, pi):
        return self.diffusion_fn(t, pi, self.params)

    def replace(self, **changes):
        return dataclasses.replace(self, params=self.params.replace(**changes))


class _Replaceable(Protocol):
    def replace(self, **changes) -> Any: ...


class FilteredParameters(eqx.Module):
    """Parameters of a system driven through a shaping filter: the system's and the filter's."""

    system: PyTree
    filter: AbstractShapingFilter

    def replace(self, **changes):
        """Change parameters by name; names of the system's parameters go to the system, the rest to the filter."""
        params = self.system
        system_names = {f.name for f in dataclasses.fields(params)} if dataclasses.is_dataclass(params) else set()
        mine = {k: v for k, v in changes.items() if k in system_names}
        rest = {k: v for k, v in changes.items() if k not in system_names}
        system = self.system.replace(**mine) if mine else self.system
        # a filter is its own parameters: OrnsteinUhlenbeck (AbstractParameters) and ShapingFilter define replace
        filter_ = cast(_Replaceable, self.filter).replace(**rest) if rest else self.filter
        return FilteredParameters(system, filter_)


class _FilteredDrift(eqx.Module):
    """``[φ(π, t), a_S(Z, t) + b(Z, t) π]``."""

    drift: Callable
    diffusion: Callable
    k: int

    def __call__(self, t, y, p):
        pi, z = y[: self.k], y[self.k :]
        return jnp.concatenate(
            [p.filter.drift(t, pi), self.drift(t, z, p.system) + self.diffusion(t, z, p.system) @ pi]
        )


class _FilteredDiffusion(eqx.Module):
    """``[[ψ(π, t)], [0]]``."""

    k: int
    d: int

    def __call__(self, t, y, p):
        psi = p.filter.diffusion(t, y[: self.k])
        return jnp.concatenate([psi, jnp.zeros((self.d, psi.shape[1]), psi.dtype)])


class _OnSystemState(eqx.Module):
    """An observable of the system, read from the filtered state."""

    fn: Callable
    k: int

    def __call__(self, t, y, p):
        return self.fn(t, y[self.k :], p.system)


def with_shaping_filter(system, filter: AbstractShapingFilter):
    """``system`` driven by the output ``π`` of ``filter`` instead of its white noise.

    The filter needs one output per noise channel of ``system``; the new system's
    noise (``system.noise``, Wiener or with jumps) drives the filter.

    Arguments:
        system: the white-noise system ``dZ = a dt + b dW``.
        filter: a shaping filter (:class:`OrnsteinUhlenbeck`, :class:`ShapingFilter`) with one output per
            noise channel of ``system``.

    Returns:
        the :class:`~nhsde.StochasticSystem` ``dπ = φ dt + ψ dW``, ``Ż = a_S + b π`` with state ``[π, Z]``
        (S0 (1.15)) and parameters :class:`FilteredParameters` ``(system, filter)``.

    Examples:
        The ball of S0 (3.1) shaken by coloured noise of correlation time ``0.1``:

        >>> import nhsde
        >>> ball = nhsde.scenes.BallOnVibratingPlane(drift=False).build()
        >>> pi = nhsde.noise.OrnsteinUhlenbeck(names=("pi_x", "pi_y"), rate=10.0)
        >>> coloured = nhsde.noise.with_shaping_filter(ball, pi)
        >>> coloured.layout.names
        ('pi_x', 'pi_y', 'u_x', 'u_y')
        >>> coloured.layout.roles
        ('random_parameter', 'random_parameter', 'velocity', 'velocity')
    """
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem.")
    if not isinstance(filter, AbstractShapingFilter):
        raise TypeError(f"filter={type(filter).__name__}; expected a shaping filter such as OrnsteinUhlenbeck(...).")
    k = len(filter.names)
    if k != system.noise_dim:
        raise ValueError(
            f"filter has {k} outputs {filter.names} but the system has {system.noise_dim} noise channels; "
            "give the filter one name per channel."
        )
    clash = set(filter.names) & set(system.observable_names())
    if clash:
        raise ValueError(f"filter names {sorted(clash)} clash with the system's names.")
    drift = system.drift_fn
    if system.interpretation == "ito" and not system.additive_noise:
        drift = ItoStratonovichDrift(system.drift_fn, system.diffusion_fn, -1.0)
    return StochasticSystem(
        drift_fn=_FilteredDrift(drift, system.diffusion_fn, k),
        diffusion_fn=_FilteredDiffusion(k, system.state_dim),
        params=FilteredParameters(system.params, filter),
        layout=StateLayout(
            tuple(filter.names) + system.layout.names,
            ("random_parameter",) * k + system.layout.roles,
            system.layout.angles,
        ),
        noise_dim=filter.noise_dim,
        interpretation="ito",
        additive_noise=filter.additive_noise,
        observables=tuple((name, _OnSystemState(fn, k)) for name, fn in system.observables),
        noise=system.noise,
    )
