"""Counter-based Brownian increments on a fixed step grid, and the driver interface.

The increment over base step ``k`` of path ``p`` is a function of ``(key, p, k)``
alone: paths are grouped in blocks of ``BLOCK`` lanes, the block key is
``fold_in(key, block)``, and step ``k`` draws ``normal(fold_in(block_key, k),
(BLOCK, m))``, one row per lane.  Hence

- the same key gives bitwise the same paths, whatever the chunking of paths;
- nothing is stored, and the increments are plain functions of ``(key, k)``,
  so the solve is reverse-differentiable;
- one draw per block and step serves ``BLOCK`` paths, and each lane receives
  its row through ``vmap`` (no per-lane gather), which keeps the loop as cheap as
  a hand-fused one;
- a step of ``substeps`` base steps sums the base increments, so coarse and
  fine solves share one path (strong-error studies); the sum is a loop
  (``over_substeps``), so ``substeps`` may be data of the compiled run.
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array, PRNGKeyArray, PyTree

from ._misc import over_substeps, substeps_span
from ._weak import WeakIncrement

__all__ = ["BLOCK", "AbstractDriver", "StepIncrement", "Wiener", "block_keys"]

BLOCK = 64
"""Paths per random block; chunk sizes are multiples of it."""


def block_keys(key: PRNGKeyArray, first_block, n_blocks: int) -> PRNGKeyArray:
    """Keys of blocks ``first_block, …, first_block + n_blocks − 1``."""
    return jax.vmap(lambda b: jr.fold_in(key, b))(first_block + jnp.arange(n_blocks))


class AbstractDriver(eqx.Module):
    """The driving process ``W`` of ``dZ = a dt + b dW`` (S0 (1.3)), per noise channel.

    A driver draws, for one block of ``BLOCK`` paths, the increments of ``W`` over
    fixed step ``k0`` (``substeps`` base steps of length ``dt``) from the block
    key and the step counter.  Its parameters (jump intensities, …) are pytree
    leaves.  ``continuous`` is False for drivers with jumps, for which only
    Euler–Maruyama applies (S0 §2, Remark: the Stratonovich shortcut fails);
    Wiener is the one continuous driver.  ``variance_rate`` is ``ν`` of S0 (1.4)
    per channel, ``E[dW dWᵀ] = diag(ν) dt``.
    """

    continuous: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def variance_rate(self) -> Array:
        """``ν`` of S0 (1.4): a scalar or one value per channel."""

    def noise_intensity(self, noise_dim: int, dtype) -> Array:
        """``ν`` per channel, shape ``(noise_dim,)``, in ``dtype``."""
        return jnp.broadcast_to(jnp.asarray(self.variance_rate()).astype(dtype), (noise_dim,))

    @abc.abstractmethod
    def block_increment(self, key, block, k0, dt, shape, substeps, levy_area) -> PyTree:
        """Increments of the block's ``BLOCK`` lanes over fixed step ``k0``, leading axis ``BLOCK``.

        ``key`` is the block key ``fold_in(ensemble key, block)``; ``block`` (an ``int32``
        scalar) is the global block index, so lane ``l`` is path ``block·BLOCK + l``.

        A ``(BLOCK, *shape)`` array, or a ``diffrax.SpaceTimeLevyArea`` of such
        arrays when ``levy_area`` asks for it.
        """


class Wiener(AbstractDriver):
    """Standard Wiener process: S0's normal stochastic systems."""

    continuous: ClassVar[bool] = True

    def variance_rate(self):
        return jnp.ones(())

    def block_increment(self, key, block, k0, dt, shape, substeps, levy_area):
        del block  # the block key alone defines the draws
        # PlatenWeak2's three-point or Gaussian increments:
        if isinstance(levy_area, type) and issubclass(levy_area, WeakIncrement):
            return levy_area.block_draw(key, k0, dt, (BLOCK,) + shape, substeps)
        levy = levy_area is dfx.SpaceTimeLevyArea
        sqrt_dt = jnp.sqrt(dt)
        h_scale = sqrt_dt / math.sqrt(12.0)

        def base_step(k, carry):
            # H = (1/h) ∫_0^h W ds − W_h/2, with ∫ over base step i = δ (W(t_i) + ΔW_i/2 + H_i).
            w, integral = carry
            draws = jr.normal(jr.fold_in(key, k), (2 if levy else 1, BLOCK) + shape, dtype=dt.dtype)
            dw = sqrt_dt * draws[0]
            if levy:
                integral = integral + (w + 0.5 * dw + h_scale * draws[1])
            return w + dw, integral

        zeros = jnp.zeros((BLOCK,) + shape, dt.dtype)
        w, integral = over_substeps(base_step, k0, substeps, (zeros, zeros))
        if not levy:
            return w
        h = substeps_span(substeps, dt)
        return dfx.SpaceTimeLevyArea(dt=jnp.broadcast_to(h, (BLOCK,)), W=w, H=dt * integral / h - 0.5 * w)


class StepIncrement(dfx.AbstractBrownianPath):
    """The driver's increment over one step, handed to a diffrax solver as its control.

    ``evaluate(t0, t1)`` returns the stored increment (with its Lévy area when the
    solver asks for it); the fixed-step loop builds one per lane and step.
    """

    increment: PyTree
    levy_area: type[dfx.AbstractBrownianIncrement] = eqx.field(static=True)

    @property
    def t0(self):
        return -jnp.inf

    @property
    def t1(self):
        return jnp.inf

    def evaluate(self, t0, t1=None, left: bool = True, use_levy: bool = False):
        del t0, t1, left
        if isinstance(self.increment, dfx.AbstractBrownianIncrement):
            return self.increment if use_levy else self.increment.W
        if use_levy:
            raise ValueError("this solver needs space-time Lévy area, which the driver was not asked for.")
        return self.increment
