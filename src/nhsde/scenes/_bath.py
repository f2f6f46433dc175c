"""Bodies in a heat bath written in body-frame velocities ``u``, with the positions ``q`` they drive.

The scenes ``*InBath`` write each model's fields on the velocities alone (the reduced state, ``drift=False``); the
full state ``(q, u)`` adds ``q̇ = rates(q, u, p)``, noiseless and undamped: the noise gains zero rows and the linear
drift is block diagonal, zero on ``q``.
"""

# No `from __future__ import annotations`: equinox reads AbstractVar/AbstractClassVar from live annotations.
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

import jax.numpy as jnp

from .._system import StateLayout, StochasticSystem
from ._base import AbstractScene

if TYPE_CHECKING:
    from typing import ClassVar as AbstractClassVar
else:
    from equinox import AbstractClassVar

__all__ = ["AbstractBathScene", "on_velocities", "with_positions"]

MODELS = ("ideal", "naive", "soft")


def with_positions(n: int, rates: Callable, drift: Callable, diffusion: Callable, linear: Callable):
    """``(drift, diffusion, linear)`` of the state ``(q, u)``, ``q`` its first ``n`` entries, from the velocity
    fields ``drift(t, u, p)``, ``diffusion(t, u, p)``, ``linear(p)`` and ``q̇ = rates(q, u, p)``.  Call it once, at
    module level: the fields are static, and a new function would compile anew."""

    def full_drift(t, y, p):
        return jnp.concatenate([rates(y[:n], y[n:], p), drift(t, y[n:], p)])

    def full_diffusion(t, y, p):
        b = diffusion(t, y[n:], p)
        return jnp.concatenate([jnp.zeros((n, b.shape[1]), b.dtype), b])

    def full_linear(p):
        a = linear(p)
        size = n + a.shape[0]
        return jnp.zeros((size, size), a.dtype).at[n:, n:].set(a)

    return full_drift, full_diffusion, full_linear


def on_velocities(n: int, observable: Callable) -> Callable:
    """``observable(t, u, p)`` of the velocities as an observable of the state ``(q, u)``."""

    def of_state(t, y, p):
        return observable(t, y[n:], p)

    return of_state


class AbstractBathScene(AbstractScene):
    """A body in a heat bath of temperature ``kT``, its contact ``model="ideal" | "naive" | "soft"`` (the ideal
    constraint without noise; with the friction's noise only; a viscous contact with its own noise), with the
    positions in the state when ``drift``.

    A concrete one declares ``fields``: ``(model, drift) -> (velocity names, drift, diffusion, linear drift, noise
    channels, observables)`` (from :func:`with_positions` for ``drift=True``), ``positions``: the names and roles
    of ``q``, and ``angles``: those the fields read through ``sin``/``cos`` (:class:`~nhsde.StateLayout`).
    """

    fields: AbstractClassVar[dict]
    positions: AbstractClassVar[tuple[tuple[str, ...], tuple[str, ...]]]
    intensities: ClassVar[tuple[str, ...]] = ("kT",)
    angles: ClassVar[tuple[str, ...]] = ()

    def __init__(self, *, model: str = "soft", drift: bool = True, **params):
        if model not in MODELS:
            raise ValueError(f"model={model!r}; allowed: {', '.join(repr(m) for m in MODELS)}.")
        self.params = self.Parameters(**params)
        self.model = model  # pyright: ignore[reportAttributeAccessIssue]
        self.drift = bool(drift)  # pyright: ignore[reportAttributeAccessIssue]

    def build(self) -> StochasticSystem:
        model, drift = self.model, self.drift  # pyright: ignore[reportAttributeAccessIssue]
        velocities, drift_fn, diffusion_fn, linear, channels, observables = self.fields[model, drift]
        names, roles = velocities, ("velocity",) * len(velocities)
        if drift:
            names, roles = self.positions[0] + names, self.positions[1] + roles
        return StochasticSystem(
            drift_fn=drift_fn,
            diffusion_fn=diffusion_fn,
            params=self.params,
            layout=StateLayout(names, roles, self.angles if drift else ()),
            noise_dim=channels,
            additive_noise=True,
            linear_drift=linear,
            observables=observables,
        )
