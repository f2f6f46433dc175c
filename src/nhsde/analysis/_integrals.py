"""First integrals: their rates by autodiff, and their drift along accurate long integrations."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import partial

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from ._liouville import FAST_COMPILE, _cast, _states, divergence

__all__ = ["Flow", "integral_drift", "integral_rates", "solve_flow"]


@partial(jax.jit, static_argnums=(0, 1), compiler_options=FAST_COMPILE)
def _rates(vector_field, integrals, states, params, t):
    def one(y):
        v = vector_field(t, y, params)
        return {name: jax.jvp(lambda z, f=f: f(z, params), (y,), (v,))[1] for name, f in integrals}

    return jax.vmap(one)(states)


def integral_rates(vector_field: Callable, integrals: Mapping[str, Callable], states, params, t=0.0) -> dict:
    """``dF/dt = (∇F, v)`` at each state for each ``F = integrals[name](y, params)``: zero for a first integral."""
    states = _states(states)
    params = _cast(params, states.dtype)
    return _rates(vector_field, tuple(integrals.items()), states, params, jnp.asarray(t, states.dtype))


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
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver={solver!r}; allowed: {', '.join(SOLVERS)}.")
    if t1 == 0:
        raise ValueError("t1=0; integrate over a non-empty interval.")
    y0 = _states(y0)
    params = _cast(params, y0.dtype)
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


def integral_drift(integrals: Mapping[str, Callable], flow: Flow, params) -> dict:
    """``max_t |F(y(t)) − F(y(0))|`` per trajectory for each integral: how well the integration keeps it."""
    return _drift(tuple(integrals.items()), flow.ys, _cast(params, flow.ys.dtype))


@partial(jax.jit, static_argnums=0, compiler_options=FAST_COMPILE)
def _drift(integrals, ys, params):
    out = {}
    for name, f in integrals:
        values = jax.vmap(jax.vmap(lambda y, f=f: f(y, params)))(ys)
        out[name] = jnp.max(jnp.abs(values - values[:, :1]), axis=1)
    return out
