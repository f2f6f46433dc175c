"""Voronets elimination of the dependent velocities, S0 (1.7): ``q̇'' = B' q̇' + B''``.

With the constraint rows split into the columns of the dependent velocities
(``a_D``, square) and the independent ones (``a_I``),
``B' = −a_D⁻¹ a_I`` and ``B'' = −a_D⁻¹ a0``; equivalently ``q̇ = Ψ q̇' + b`` with
``Ψ`` holding ``B'`` in the dependent rows and the identity in the independent ones.
The choice is fixed for a whole run; it must keep ``a_D`` invertible where the
motion goes (e.g. the sleigh's ``ẏ = tan θ ẋ`` fails at ``cos θ = 0``).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._misc import is_concrete
from . import _small as small
from ._spec import MechanicalSpec

__all__ = ["Elimination", "choose_dependent", "make_elimination"]

_COND_LIMIT = 1e10


class Elimination(eqx.Module):
    """Indices of the dependent (``q''``) and independent (``q'``) coordinates."""

    dependent: tuple[int, ...] = eqx.field(static=True)
    independent: tuple[int, ...] = eqx.field(static=True)

    @property
    def dep(self) -> np.ndarray:
        """Indices of the dependent coordinates, for array indexing."""
        return np.asarray(self.dependent, dtype=int)

    @property
    def ind(self) -> np.ndarray:
        """Indices of the independent coordinates, for array indexing."""
        return np.asarray(self.independent, dtype=int)

    def basis(self, rows, bias):
        """``(Ψ, b, B', B'')`` with ``q̇ = Ψ q̇' + b`` for the constraint ``rows q̇ + bias = 0``."""
        dep, ind = self.dep, self.ind
        n, dtype = rows.shape[1], rows.dtype
        eye = jnp.eye(len(ind), dtype=dtype)
        if not self.dependent:
            return eye, jnp.zeros(n, dtype), jnp.zeros((0, len(ind)), dtype), jnp.zeros(0, dtype)
        sol = small.solve(rows[:, dep], jnp.concatenate([rows[:, ind], bias[:, None]], axis=1))
        b_prime, b_second = -sol[:, :-1], -sol[:, -1]
        psi = jnp.zeros((n, len(ind)), dtype).at[dep].set(b_prime).at[ind].set(eye)
        return psi, jnp.zeros(n, dtype).at[dep].set(b_second), b_prime, b_second

    def velocity_basis(self, spec: MechanicalSpec, q, pi, t, p):
        """``(Ψ, b, B', B'')`` for the velocities (ideal and servo constraints)."""
        return self.basis(*spec.velocity_constraints(q, pi, t, p))

    def displacement_basis(self, spec: MechanicalSpec, q, pi, t, p):
        """``Ψ_δ``: the virtual displacements ``δq = Ψ_δ δq'`` (ideal rows and servo realisation, S1 (3.2))."""
        rows = spec.displacement_constraints(q, pi, t, p)
        return self.basis(rows, jnp.zeros(rows.shape[0], rows.dtype))[0]


def _configuration(spec, q, pi, t):
    q = jnp.asarray(q)
    if q.shape != (spec.n,):
        raise ValueError(f"reference q has shape {q.shape}; expected ({spec.n},) for coordinates {spec.coordinates}.")
    pi = jnp.zeros(spec.k, q.dtype) if pi is None else jnp.asarray(pi, q.dtype)
    return q, pi, jnp.asarray(t, q.dtype)


def choose_dependent(spec: MechanicalSpec, q, pi=None, t=0.0) -> tuple[str, ...]:
    """Dependent velocities by complete pivoting on the constraint rows at ``q``.

    Gaussian elimination takes, row by row, the largest remaining entry; its
    column is a dependent velocity.  This keeps ``a_D`` well conditioned near ``q``.
    """
    q, pi, t = _configuration(spec, q, pi, t)
    rows = spec.velocity_constraints(q, pi, t, spec.params)[0]
    if not is_concrete(rows):
        raise TypeError(
            "dependent=None chooses the dependent velocities from the constraint rows' values at the reference "
            "configuration, and they are traced here (the system is built inside jax.jit, jax.grad or jax.vmap): "
            f"pass dependent= ({rows.shape[0]} of {spec.coordinates}), or build the system outside the transform."
        )
    rows = np.array(rows, dtype=float)
    chosen = []
    for _ in range(rows.shape[0]):
        i, j = np.unravel_index(np.argmax(np.abs(rows)), rows.shape)
        if rows[i, j] == 0.0:
            raise ValueError(f"the constraint rows at q={np.asarray(q).tolist()} are dependent; cannot pivot.")
        chosen.append(int(j))
        rows = rows - np.outer(rows[:, j] / rows[i, j], rows[i])
        rows[i] = 0.0
    return tuple(spec.coordinates[j] for j in sorted(chosen))


def make_elimination(spec: MechanicalSpec, dependent=None, reference=None, pi=None, t=0.0) -> Elimination:
    """The elimination for ``dependent`` velocity names, or by pivoting at ``reference``.

    At ``reference`` the blocks ``a_D`` of the velocity rows and of the
    displacement rows must be invertible (``ValueError`` otherwise).
    """
    m = spec.n_ideal + spec.n_servo
    if dependent is None:
        if reference is None:
            raise ValueError(
                "dependent=None needs a reference configuration to pivot at; pass dependent=(names…) "
                f"with {m} of {spec.coordinates}, or reference=q."
            )
        dependent = choose_dependent(spec, reference, pi, t)
    if isinstance(dependent, str):
        dependent = (dependent,)
    dependent = tuple(dependent)
    unknown = [d for d in dependent if d not in spec.coordinates]
    if unknown or len(set(dependent)) != len(dependent) or len(dependent) != m:
        raise ValueError(
            f"dependent={dependent!r}; expected {m} distinct names among the coordinates {spec.coordinates} "
            f"(one per constraint)."
        )
    dep = tuple(sorted(spec.coordinates.index(d) for d in dependent))
    elim = Elimination(dep, tuple(i for i in range(spec.n) if i not in dep))
    if reference is not None:
        q, pi, t = _configuration(spec, reference, pi, t)
        p = spec.params
        if not is_concrete(q, pi, t, p):  # built inside a transform: checked where its values are known
            return elim
        for label, rows in (
            ("velocity constraint", spec.velocity_constraints(q, pi, t, p)[0]),
            ("virtual-displacement", spec.displacement_constraints(q, pi, t, p)),
        ):
            block = np.asarray(rows)[:, np.asarray(dep, dtype=int)]
            if block.size and np.linalg.cond(block) > _COND_LIMIT:
                raise ValueError(
                    f"dependent={dependent!r} makes B' singular at q={np.asarray(q).tolist()}: the {label} block "
                    f"a_D on these velocities is {block.tolist()} (condition number {np.linalg.cond(block):.3g}). "
                    "Choose other dependent velocities, or dependent=None to pivot."
                )
    return elim
