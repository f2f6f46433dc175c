"""Structural dependence of a JAX function's output on one of its arguments.

Used to refuse specs whose kinematics involve the random parameters (S0 (1.8)
would need the Itô correction Δσ) and to recognise additive noise.  The test is
conservative: any operation touching the argument counts, so ``0 * x`` depends
on ``x``.
"""

from __future__ import annotations

import jax
from jax.extend.core import Var

__all__ = ["depends_on"]


def depends_on(fn, args: tuple, argnum: int) -> bool:
    """Whether ``fn(*args)`` can depend on ``args[argnum]`` (traced once, no values used)."""
    closed = jax.make_jaxpr(fn)(*args)
    sizes = [len(jax.tree_util.tree_leaves(a)) for a in args]
    start = sum(sizes[:argnum])
    tainted = set(closed.jaxpr.invars[start : start + sizes[argnum]])
    for eqn in closed.jaxpr.eqns:
        if any(isinstance(v, Var) and v in tainted for v in eqn.invars):
            tainted.update(eqn.outvars)
    return any(isinstance(v, Var) and v in tainted for v in closed.jaxpr.outvars)
