"""Checks and small helpers shared by every layer (one copy each)."""

from __future__ import annotations

import math
from typing import Literal, overload

import jax
import jax.core
import jax.numpy as jnp
import jax.random as jr
import numpy as np

__all__ = ["FAST_COMPILE", "cast_floats", "check_key", "check_number", "check_span", "check_steps", "is_concrete"]

FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
"""XLA options for programs that run once (surveys, Newton solves): compile time dominates their run time."""


def is_concrete(*trees) -> bool:
    """True when no leaf of ``trees`` is a JAX tracer (values can be checked now)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(trees))


def real_state(name: str, y):
    """``y`` as a floating-point array (integers and booleans in the default float); complex values are refused
    naming ``name`` (a cast would drop their imaginary parts silently)."""
    if not isinstance(y, jax.Array):
        y = np.asarray(y) if is_concrete(y) else jnp.asarray(y)  # (a list may hold tracers)
    if jnp.issubdtype(y.dtype, jnp.complexfloating):
        raise TypeError(f"{name} has dtype {y.dtype}; expected real values (float32 or float64).")
    y = y if isinstance(y, jax.Array) else jax.device_put(y)  # (jnp.asarray compiles a program)
    return y if jnp.issubdtype(y.dtype, jnp.floating) else y.astype(jnp.result_type(float))


def under_trace() -> bool:
    """True while a JAX transformation traces the caller: a compiled helper called now would return tracers."""
    return isinstance(jnp.asarray(0.0), jax.core.Tracer)


def cast_floats(tree, dtype):
    """``tree`` with its floating-point array leaves cast to ``dtype`` (other leaves unchanged)."""
    return jax.tree_util.tree_map(
        lambda p: p.astype(dtype) if isinstance(p, jax.Array) and jnp.issubdtype(p.dtype, jnp.floating) else p, tree
    )


@overload
def check_number(name: str, value, *, positive: bool = ..., integer: Literal[True]) -> int: ...
@overload
def check_number(name: str, value, *, positive: bool = ..., integer: Literal[False] = ...) -> float: ...
@overload
def check_number(name: str, value, *, positive: bool = ..., integer: bool = ...) -> int | float: ...


def check_number(name: str, value, *, positive: bool = False, integer: bool = False) -> int | float:
    """``value`` as a finite Python number; a ``TypeError``/``ValueError`` names ``name`` otherwise."""
    if isinstance(value, jax.core.Tracer):
        raise TypeError(f"{name} must be a concrete Python number (it fixes array shapes), not a traced value.")
    scalar_array = isinstance(value, (np.ndarray, jax.Array)) and np.ndim(value) == 0
    if isinstance(value, (bool, np.bool_)) or not (
        isinstance(value, (int, float, np.integer, np.floating)) or scalar_array
    ):
        raise TypeError(f"{name}={value!r}; expected a number.")
    if scalar_array and jnp.issubdtype(jnp.asarray(value).dtype, jnp.bool_):
        raise TypeError(f"{name}={value!r}; expected a number.")
    if integer and isinstance(value, (int, np.integer)):
        if positive and value <= 0:
            raise ValueError(f"{name}={value}; must be > 0.")
        return int(value)
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name}={v}; must be finite.")
    if integer and v != int(v):
        raise ValueError(f"{name}={value}; must be a whole number.")
    if positive and v <= 0:
        raise ValueError(f"{name}={value}; must be > 0.")
    return int(v) if integer else v


def check_span(t0, t1) -> tuple[float, float]:
    """``(t0, t1)`` as finite Python numbers with ``t1 > t0``; a ``ValueError`` names the one at fault otherwise."""
    t0, t1 = check_number("t0", t0), check_number("t1", t1)
    if not t1 > t0:
        raise ValueError(f"t1={t1}; must be > t0={t0}.")
    return t0, t1


def check_steps(name: str, span: float, step: float) -> int:
    """The whole number of steps ``step`` makes of ``span``; a ``ValueError`` names ``name`` otherwise."""
    n = round(span / step)
    if n < 1 or abs(n * step - span) > 1e-9 * span:
        raise ValueError(f"{name}={step} must divide t1 − t0 = {span} into a whole number of steps.")
    return n


def check_key(key):
    """A single typed JAX random key (raw ``uint32[2]`` keys are wrapped)."""
    if isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if key.shape != ():
            raise ValueError(f"key has shape {key.shape}; pass a single key, e.g. jax.random.key(0).")
        return key
    if isinstance(key, (jax.Array, np.ndarray)) and key.shape == (2,) and key.dtype == jnp.uint32:
        return jr.wrap_key_data(jnp.asarray(key))
    raise TypeError(f"key={key!r}; expected a JAX random key, e.g. jax.random.key(0).")


def over_substeps(body, k0, substeps, init):
    """``body(k, carry)`` over the base steps ``k = k0·substeps … (k0 + 1)·substeps − 1`` of fixed step ``k0``, from
    ``init``: a loop whose trip count may be data (one compiled program for every ratio of step to base step)."""
    first = k0 * substeps
    return jax.lax.fori_loop(0, substeps, lambda s, carry: body(first + s, carry), init)


def substeps_span(substeps, dt):
    """``substeps · dt``, the length of a step of ``substeps`` base steps (a Python int or int32 data)."""
    return jnp.asarray(substeps, dt.dtype) * dt


@jax.jit
def fold_key(key, data):
    """``jax.random.fold_in(key, data)`` as one compiled program (called eagerly it compiles two)."""
    return jr.fold_in(key, data)
