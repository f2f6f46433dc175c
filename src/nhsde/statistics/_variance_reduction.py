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

from typing import ClassVar

import diffrax as dfx
import equinox as eqx

from .._brownian import AbstractDriver
from .._system import StochasticSystem
from .._weak import WeakIncrement

__all__ = ["Antithetic", "antithetic"]


class Antithetic(AbstractDriver):
    """``driver`` with its increments reflected, ``W → −W``.

    Space-time Lévy area ``H`` is linear in the path and changes sign; the
    two-point ``V`` of :class:`~nhsde.PlatenWeak2`'s increments stands for the
    Lévy area, which is even in the path, and is kept.
    """

    driver: AbstractDriver
    continuous: ClassVar[bool] = True

    def __check_init__(self):
        if not self.driver.continuous:
            raise ValueError(
                f"antithetic: the driver {type(self.driver).__name__} has jumps, whose law is not symmetric "
                "under W → −W; antithetic paths need a Wiener driver."
            )

    def variance_rate(self):
        return self.driver.variance_rate()

    def block_increment(self, key, block, k0, dt, shape, substeps, levy_area):
        inc = self.driver.block_increment(key, block, k0, dt, shape, substeps, levy_area)
        if isinstance(inc, dfx.SpaceTimeLevyArea):
            return dfx.SpaceTimeLevyArea(dt=inc.dt, W=-inc.W, H=-inc.H)
        if isinstance(inc, WeakIncrement):
            return eqx.tree_at(lambda i: i.W, inc, -inc.W)
        return -inc


def antithetic(system: StochasticSystem) -> StochasticSystem:
    """``system`` driven by ``−W``: with the same key, the antithetic partner of every path."""
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem.")
    if isinstance(system.noise, Antithetic):
        return eqx.tree_at(lambda s: s.noise, system, system.noise.driver)
    return eqx.tree_at(lambda s: s.noise, system, Antithetic(system.noise))
