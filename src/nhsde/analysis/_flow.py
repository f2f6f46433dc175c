"""Accurate deterministic integrations of a vector field, vmapped over initial states, with the phase volume."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from .._misc import FAST_COMPILE, cast_floats
from ._inputs import state_batch
from ._liouville import divergence

__all__ = ["Flow", "solve_flow"]


class Flow(eqx.Module):
    """Solutions ``ys[i, j]`` from initial state ``i`` at times ``ts[j]``.

    ``log_volume[i, j] = ∫₀^{t_j} div v dt`` along the solution (when asked for):
    the logarithm of the Jacobian of the flow map, by which phase volume grows.
    An invariant density ``ρ`` must satisfy ``ρ(y(t)) = ρ(y(0)) e^{−log_volume}``.
    """

    ts: jax.Array
    ys: jax.Array
    log_volume: jax.Array | None = None


SOLVERS = {"dopri8": dfx.Dopri8, "tsit5": dfx.Tsit5, "dopri5": dfx.Dopri5}


@partial(jax.jit, static_argnums=(0, 4, 5, 6, 7, 8, 9), compiler_options=FAST_COMPILE)
def _solve(vector_field, y0, params, t1, n_save, rtol, atol, solver, max_steps, log_volume):
    ts = jnp.linspace(0.0, t1, n_save, dtype=y0.dtype)
    field = vector_field
    if log_volume:  # augment with ℓ̇ = div v

        def field(t, z, p):
            return jnp.concatenate([vector_field(t, z[:-1], p), divergence(vector_field, z[:-1], p, t)[None]])

        y0 = jnp.concatenate([y0, jnp.zeros((y0.shape[0], 1), y0.dtype)], axis=1)

    def one(y):
        sol = dfx.diffeqsolve(
            dfx.ODETerm(field),
            SOLVERS[solver](),
            0.0,
            t1,
            None,
            y,
            params,
            saveat=dfx.SaveAt(ts=ts),
            stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
            max_steps=max_steps,
        )
        assert sol.ys is not None  # saveat=SaveAt(ts=…) saves the solution
        return sol.ys

    ys = jax.vmap(one)(y0)
    if log_volume:
        return Flow(ts=ts, ys=ys[..., :-1], log_volume=ys[..., -1])
    return Flow(ts=ts, ys=ys)


def solve_flow(
    vector_field: Callable,
    y0,
    params,
    *,
    t1: float,
    n_save: int = 101,
    rtol: float = 1e-11,
    atol: float = 1e-12,
    solver: str = "dopri8",
    max_steps: int = 1_000_000,
    log_volume: bool = False,
) -> Flow:
    """Integrate ``ẏ = v(t, y, params)`` from each row of ``y0`` ``(n, d)`` with an adaptive high-order solver.

    Negative ``t1`` integrates backwards in time.  All initial states run
    together under ``vmap``, compiled for compile speed (checks run once).
    ``log_volume=True`` also integrates ``∫ div v dt``.

    Arguments:
        vector_field: ``v(t, y, params)``.
        y0: ``(n, d)`` initial states (float64).
        params: the field's parameters.
        t1: the end time (negative: backwards).
        n_save: equally spaced save times from 0 to ``t1``.
        rtol, atol: the step-size controller's tolerances.
        solver: ``"dopri8"``, ``"tsit5"`` or ``"dopri5"``.
        max_steps: step budget per state.
        log_volume: also integrate ``∫ div v dt``.

    Returns:
        a :class:`Flow` with ``ts`` ``(n_save,)``, ``ys`` ``(n, n_save, d)`` and, if asked, ``log_volume``.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver={solver!r}; allowed: {', '.join(SOLVERS)}.")
    if t1 == 0:
        raise ValueError("t1=0; integrate over a non-empty interval.")
    y0 = state_batch(y0, "y0")
    params = cast_floats(params, y0.dtype)
    return _solve(
        vector_field,
        y0,
        params,
        jnp.asarray(t1, y0.dtype),
        int(n_save),
        float(rtol),
        float(atol),
        solver,
        int(max_steps),
        bool(log_volume),
    )
