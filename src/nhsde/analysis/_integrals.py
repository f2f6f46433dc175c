"""First integrals: their rates by autodiff, and their drift along accurate long integrations (:func:`solve_flow`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import partial

import jax
import jax.numpy as jnp

from .._misc import FAST_COMPILE, cast_floats
from ._flow import Flow
from ._inputs import state_batch

__all__ = ["integral_drift", "integral_rates"]


@partial(jax.jit, static_argnums=(0, 1), compiler_options=FAST_COMPILE)
def _rates(vector_field, integrals, states, params, t):
    def one(y):
        v = vector_field(t, y, params)
        return {name: jax.jvp(lambda z, f=f: f(z, params), (y,), (v,))[1] for name, f in integrals}

    return jax.vmap(one)(states)


def integral_rates(vector_field: Callable, integrals: Mapping[str, Callable], states, params, t=0.0) -> dict:
    """``dF/dt = (∇F, v)`` at each state for each ``F = integrals[name](y, params)``: zero for a first integral.

    Arguments:
        vector_field: the flow ``v(t, y, params)``.
        integrals: ``name → F(y, params)``, the candidate first integrals.
        states: ``(n, d)`` states.
        params: the parameters passed to both.
        t: the time at which ``v`` is evaluated.

    Returns:
        ``name → (n,)`` rates ``dF/dt``.

    Examples:
        >>> import jax.numpy as jnp
        >>> from nhsde import analysis
        >>> def rotation(t, y, p):
        ...     return jnp.array([y[1], -y[0]])
        >>> integrals = {"radius": lambda y, p: y @ y, "x": lambda y, p: y[0]}
        >>> rates = analysis.integral_rates(rotation, integrals, jnp.array([[1.0, 2.0]]), None)
        >>> print(rates["radius"], rates["x"])
        [0.] [2.]
    """
    states = state_batch(states)
    params = cast_floats(params, states.dtype)
    return _rates(vector_field, tuple(integrals.items()), states, params, jnp.asarray(t, states.dtype))


def integral_drift(integrals: Mapping[str, Callable], flow: Flow, params) -> dict:
    """``max_t |F(y(t)) − F(y(0))|`` per trajectory for each integral: how well the integration keeps it."""
    return _drift(tuple(integrals.items()), flow.ys, cast_floats(params, flow.ys.dtype))


@partial(jax.jit, static_argnums=0, compiler_options=FAST_COMPILE)
def _drift(integrals, ys, params):
    out = {}
    for name, f in integrals:
        values = jax.vmap(jax.vmap(lambda y, f=f: f(y, params)))(ys)
        out[name] = jnp.max(jnp.abs(values - values[:, :1]), axis=1)
    return out
