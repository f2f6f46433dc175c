"""Antithetic variates: the same paths driven by ``−W``.

The law of a Wiener process is symmetric, so ``X(W)`` and ``X(−W)`` have the same
law and ``½(f(X(W)) + f(X(−W)))`` is an unbiased sample of ``E f(X)`` whose
variance is smaller whenever ``f ∘ X`` has a part odd in ``W`` (Glasserman,
*Monte Carlo Methods in Financial Engineering*, 2004, §4.2).  Nothing is gained
for a part even in ``W``: for the ball from rest ``x(−W) = −x(W)``, so its
covariances gain nothing while its means become exact.  :func:`antithetic` gives
the reflected system; ``extrapolate`` and ``multilevel_monte_carlo`` pair every
path with it (``antithetic=True``), which composes with their own coupling
because the reflection acts on the shared counter-based increments.
"""

from __future__ import annotations

from typing import Any, ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._brownian import AbstractDriver
from .._misc import is_concrete
from .._system import StochasticSystem
from .._weak import WeakIncrement

__all__ = ["Antithetic", "antithetic", "check_reflectable"]


def check_reflectable(driver: AbstractDriver, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` where ``driver`` has jumps: its law is not symmetric under ``W → −W``."""
    if not driver.continuous:
        raise ValueError(
            f"{name}: the driver {type(driver).__name__} has jumps, whose law is not symmetric under W → −W; "
            "antithetic paths need a Wiener driver."
        )


def _sign(value):
    return value if isinstance(value, jax.Array) else np.asarray(value, np.float64)


class Antithetic(AbstractDriver):
    """``driver`` with its increments multiplied by ``sign``: ``W → −W`` (the default), or ``+1``.

    Space-time Lévy area ``H`` is linear in the path and changes sign; the
    two-point ``V`` of :class:`~nhsde.PlatenWeak2`'s increments stands for the
    Lévy area, which is even in the path, and is kept.  ``sign`` is data, so a
    path and its reflection run in one compiled program (the estimators solve
    both through ``Antithetic``).
    """

    driver: AbstractDriver
    sign: Any = eqx.field(default=-1.0, converter=_sign)
    continuous: ClassVar[bool] = True

    def __check_init__(self):
        check_reflectable(self.driver, "antithetic")

    def variance_rate(self):
        return self.driver.variance_rate()

    def block_increment(self, key, block, k0, dt, shape, substeps, levy_area):
        inc = self.driver.block_increment(key, block, k0, dt, shape, substeps, levy_area)
        sign = jnp.asarray(self.sign, dt.dtype)
        if isinstance(inc, dfx.SpaceTimeLevyArea):
            return dfx.SpaceTimeLevyArea(dt=inc.dt, W=sign * inc.W, H=sign * inc.H)
        if isinstance(inc, WeakIncrement):
            return eqx.tree_at(lambda i: i.W, inc, sign * inc.W)
        return sign * inc


def antithetic(system: StochasticSystem) -> StochasticSystem:
    """``system`` driven by ``−W``: with the same key, the antithetic partner of every path."""
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem.")
    noise = system.noise
    if isinstance(noise, Antithetic):
        flipped = -noise.sign
        if is_concrete(flipped) and np.all(flipped == 1):  # the reflection of a reflection: the driver itself
            return eqx.tree_at(lambda s: s.noise, system, noise.driver)
        return eqx.tree_at(lambda s: s.noise.sign, system, flipped)
    return eqx.tree_at(lambda s: s.noise, system, Antithetic(noise))


def signed(system: StochasticSystem) -> StochasticSystem:
    """``system`` as it is, its Wiener driver wrapped in ``Antithetic(sign=+1)``: the same paths, in the compiled
    program that also solves their reflections (:func:`antithetic` of it flips the sign)."""
    if not system.noise.continuous or isinstance(system.noise, Antithetic):
        return system
    return eqx.tree_at(lambda s: s.noise, system, Antithetic(system.noise, 1.0))
