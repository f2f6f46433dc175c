"""Argument checks shared by the analysis functions (one copy each).

The checks of every layer (numbers, steps, keys, concreteness, float casts) are
in :mod:`nhsde._misc`; these are the ones particular to analysing a vector field
or a system about a steady state.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._brownian import Wiener
from .._misc import is_concrete
from .._system import StochasticSystem

__all__ = ["check_radius", "ito_system", "require_float64", "require_wiener", "state_batch"]


def state_batch(states, name: str = "states") -> jax.Array:
    """``states`` as a floating-point ``(n_states, state_dim)`` array; another rank raises naming ``name``."""
    states = jnp.asarray(states)
    if states.ndim != 2:
        raise ValueError(f"{name} has shape {states.shape}; expected (n_states, state_dim).")
    if not jnp.issubdtype(states.dtype, jnp.floating):
        states = states.astype(jnp.result_type(float))
    return states


def require_float64(name: str, x) -> None:
    """Raise unless ``x`` is float64: the tolerances that separate zero, neutral and growing roots need it."""
    if jnp.asarray(x).dtype != jnp.float64:
        raise ValueError(
            f"{name} has dtype {jnp.asarray(x).dtype}; stability analysis needs float64 "
            "(call jax.config.update('jax_enable_x64', True) before creating arrays)."
        )


def ito_system(system) -> StochasticSystem:
    """``system`` in the Itô interpretation; ``TypeError`` unless it is a :class:`~nhsde.StochasticSystem`."""
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    if system.interpretation != "ito":
        system = system.converted("ito")
    return system


def require_wiener(system: StochasticSystem, what: str) -> None:
    """Raise unless ``system`` is driven by Wiener noise: ``what`` assumes continuous paths."""
    if not isinstance(system.noise, Wiener):
        raise TypeError(
            f"{what} assumes continuous paths (a Wiener driver); this system is driven by "
            f"{type(system.noise).__name__}, whose jumps overshoot the boundary."
        )


def check_radius(radius):
    """``radius`` unchanged if traced or a finite number > 0; ``ValueError`` otherwise."""
    if not is_concrete(radius):
        return radius
    r = np.asarray(radius)
    if r.shape != () or not np.isfinite(r) or not r > 0:
        raise ValueError(f"radius={radius!r}; must be a finite number > 0 (the half-width of the region |δ| < radius).")
    return radius
