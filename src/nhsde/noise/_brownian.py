"""Counter-based Brownian path on a fixed step grid.

The increment over base step ``k`` of path ``p`` is a function of ``(key, p, k)``
alone: paths are grouped in blocks of ``BLOCK`` lanes, the block key is
``fold_in(key, block)``, and step ``k`` draws ``normal(fold_in(block_key, k),
(BLOCK, m))`` of which the path reads its lane.  Hence

- the same key gives bitwise the same path, whatever the chunking of paths;
- nothing is stored, and the path is reverse-differentiable (it is a pure
  function of time);
- one random draw per block and step serves ``BLOCK`` paths (under ``vmap`` over
  lanes the draw is not batched), which is what makes it as cheap as a fused
  loop;
- a step of ``substeps`` base steps sums the base increments, so coarse and
  fine solves can share one path (strong-error studies).
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
from jaxtyping import Array, Float, Int, PRNGKeyArray

__all__ = ["BLOCK", "AbstractDriver", "CounterBrownianPath", "Wiener", "block_keys"]

BLOCK = 64
"""Paths per random block; chunk sizes are multiples of it."""


def block_keys(key: PRNGKeyArray, first_block, n_blocks: int) -> PRNGKeyArray:
    """Keys of blocks ``first_block, …, first_block + n_blocks − 1``."""
    return jax.vmap(lambda b: jr.fold_in(key, b))(first_block + jnp.arange(n_blocks))


class CounterBrownianPath(dfx.AbstractBrownianPath):
    """One lane of a block of Brownian paths on the grid ``t_start + k·dt``.

    ``evaluate(t0, t1)`` must be called with ``t0`` on the grid and
    ``t1 − t0 = substeps·dt``; with ``use_levy=True`` it also returns the
    space-time Lévy area ``H`` of the step, aggregated exactly from the base steps.
    """

    key: PRNGKeyArray  # block key
    lane: Int[Array, ""]
    t_start: Float[Array, ""]
    dt: Float[Array, ""]  # base step
    shape: tuple[int, ...] = eqx.field(static=True)
    substeps: int = eqx.field(static=True, default=1)
    levy_area: type[dfx.BrownianIncrement | dfx.SpaceTimeLevyArea] = eqx.field(
        static=True, default=dfx.BrownianIncrement
    )

    @property
    def t0(self):
        return self.t_start

    @property
    def t1(self):
        return jnp.inf

    def _base_draws(self, k):
        n = 2 if self.levy_area is dfx.SpaceTimeLevyArea else 1
        z = jr.normal(jr.fold_in(self.key, k), (n, BLOCK) + self.shape, dtype=self.dt.dtype)
        return z[:, self.lane]

    def evaluate(self, t0, t1=None, left: bool = True, use_levy: bool = False):
        del left
        if t1 is None:
            raise ValueError("CounterBrownianPath gives increments only: call evaluate(t0, t1).")
        t0 = jax.lax.stop_gradient(t0)
        k0 = jnp.round((t0 - self.t_start) / self.dt).astype(jnp.int32)
        draws = jax.vmap(self._base_draws)(k0 + jnp.arange(self.substeps, dtype=jnp.int32))  # (r, n, *shape)
        sqrt_dt = jnp.sqrt(self.dt)
        dw = sqrt_dt * draws[:, 0]
        w = jnp.sum(dw, axis=0)
        if not use_levy:
            return w
        if self.levy_area is not dfx.SpaceTimeLevyArea:
            raise ValueError("this solver needs space-time Lévy area; build the path with levy_area=SpaceTimeLevyArea.")
        # H = (1/h) ∫_0^h W ds − W_h/2, with ∫ over base step i = δ (W(t_i) + ΔW_i/2 + H_i).
        h_base = (sqrt_dt / math.sqrt(12.0)) * draws[:, 1]
        w_before = jnp.cumsum(dw, axis=0) - dw
        integral = self.dt * jnp.sum(w_before + 0.5 * dw + h_base, axis=0)
        h = self.substeps * self.dt
        return dfx.SpaceTimeLevyArea(dt=h, W=w, H=integral / h - 0.5 * w)


class AbstractDriver(eqx.Module):
    """The driving process ``W`` of ``dZ = a dt + b dW`` (S0 (1.3)), per noise channel.

    A driver makes the counter-based path of one lane of one block of paths on
    the fixed step grid; its parameters (jump intensities, …) are pytree leaves.
    ``continuous`` is False for drivers with jumps, for which only Itô solvers
    without Lévy area apply (S0 §2, Remark: the Stratonovich shortcut fails).
    """

    continuous: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def path(self, key, lane, t_start, dt, shape, substeps, levy_area) -> dfx.AbstractPath:
        """The path of lane ``lane`` of the block with key ``key`` (see :class:`CounterBrownianPath`)."""


class Wiener(AbstractDriver):
    """Standard Wiener process: S0's normal stochastic systems."""

    continuous: ClassVar[bool] = True

    def path(self, key, lane, t_start, dt, shape, substeps, levy_area):
        return CounterBrownianPath(key, lane, t_start, dt, shape, substeps, levy_area)
