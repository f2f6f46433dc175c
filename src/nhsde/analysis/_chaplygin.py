"""Recognising a conservative Chaplygin system in a mechanical spec, and its equations (4.5), S4 §4.1–4.2.

A Chaplygin system (S4 (4.4)–(4.5)): the constraints solved for the dependent
velocities read ``ẏ = M(x) ẋ`` with the kinetic energy ``T``, the potential ``V`` and
``M`` independent of ``y``; then ``x`` obeys

    d/dt ∂T*/∂ẋ = ∂T*/∂x − ∂V/∂x + (Ωẋ)ẋ,   ω_ijh = (∂m_κi/∂x_j − ∂m_κj/∂x_i) θ_κh,   (4.5)

with ``T* = ½ ẋᵀΘẋ`` and ``θ_κh = ∂(∂T/∂ẏ_κ)/∂ẋ_h`` on the constraints.  Coordinates
``s`` on which ``Θ``, ``V`` and ``Ω`` do not depend are pseudo-cyclic, the others
``r`` positional (4.7); with ``Ω_sss = 0`` (4.8) the motions ``r = r0``, ``ṡ = ṡ0``
solving (4.9) form families of steady motions (:func:`~nhsde.analysis.steady_motions`).

:class:`ChaplyginSystem` writes (4.5) from ``Θ``, ``Ω``, ``V`` and linearises it
about a steady motion; it also gives the reduced (Voronets) drift of
:mod:`nhsde.mechanics` on ``(r, ṙ, ṡ)``, the second, independent route to the roots.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._misc import FAST_COMPILE
from ..mechanics import MechanicalSpec, ReducedForm, formulate
from ._inputs import require_float64
from ._routh import routh_pencil

__all__ = ["ChaplyginSystem", "chaplygin_system"]

_TOL = 1e-8  # relative size below which an autodiff derivative counts as zero (rounding: ~1e-16)


class ChaplyginSystem(eqx.Module):
    """A spec recognised as a conservative Chaplygin system (S4 (4.4)–(4.8)).

    ``positional`` (``r``) and ``pseudo_cyclic`` (``s``) index the coordinates;
    ``form`` is the library's reduced route with the dependent velocities ``y``;
    ``reference`` fills the coordinates nothing depends on (``s``, ``y``).
    """

    spec: MechanicalSpec
    form: ReducedForm
    reference: Float[Array, " n"]
    positional: tuple[int, ...] = eqx.field(static=True)
    pseudo_cyclic: tuple[int, ...] = eqx.field(static=True)

    @property
    def k(self) -> int:
        return len(self.positional)

    @property
    def m(self) -> int:
        return len(self.pseudo_cyclic)

    @property
    def unknowns(self) -> tuple[str, ...]:
        """Names of the ``k + m`` constants of a steady motion: ``r`` then ``ṡ`` (``"<s>_dot"``)."""
        c = self.spec.coordinates
        return tuple(c[i] for i in self.positional) + tuple(f"{c[i]}_dot" for i in self.pseudo_cyclic)

    def _slots(self):
        """Positions of ``r`` and ``s`` within the independent coordinates ``x``."""
        ind = self.form.elimination.independent
        return np.array([ind.index(i) for i in self.positional], int), np.array(
            [ind.index(i) for i in self.pseudo_cyclic], int
        )

    def _q(self, x):
        return self.reference.astype(x.dtype).at[self.form.elimination.ind].set(x)

    def _x(self, r):
        """Independent coordinates with ``r`` set and ``s`` from the reference."""
        r_slot, _ = self._slots()
        return self.reference.astype(r.dtype)[self.form.elimination.ind].at[r_slot].set(r)

    # ------------------------------------------------------------ S4 (4.5) from the spec

    def _kinematics(self, x, p):
        """``(Θ, θ, M)``: ``T* = ½ẋᵀΘẋ``, ``θ_κh = ∂(∂T/∂ẏ_κ)/∂ẋ_h`` on the constraints, ``ẏ = M ẋ``."""
        spec, elim, q = self.spec, self.form.elimination, self._q(x)
        pi, t = jnp.zeros(0, x.dtype), jnp.zeros((), x.dtype)
        psi, _, b_prime, _ = elim.velocity_basis(spec, q, pi, t, p)
        mass_psi = spec.inertia(q, pi, t, p) @ psi
        return psi.T @ mass_psi, mass_psi[elim.dep], b_prime

    def theta(self, x, p):
        """``Θ(x)``: the kinetic metric after eliminating ``ẏ`` (S4 (4.5))."""
        return self._kinematics(x, p)[0]

    def omega(self, x, p):
        """The nonholonomic tensor ``ω_ijh = (∂m_κi/∂x_j − ∂m_κj/∂x_i) θ_κh`` (S4 (4.5))."""
        _, th, _ = self._kinematics(x, p)
        dm = jax.jacfwd(lambda z: self._kinematics(z, p)[2])(x)  # [κ, i, j] = ∂m_κi/∂x_j
        return jnp.einsum("kij,kh->ijh", dm - jnp.swapaxes(dm, 1, 2), th)

    def potential(self, x, p):
        zero = jnp.zeros((), x.dtype)
        return self.spec.potential_energy(self._q(x), jnp.zeros(0, x.dtype), zero, p)

    def _chaplygin_terms(self, x, xdot, xddot, p):
        """The terms of S4 (4.5) as rows: ``Θẍ``, ``Θ̇ẋ``, ``−∂T*/∂x``, ``∂V/∂x``, ``−(Ωẋ)ẋ``."""
        theta, theta_dot = jax.jvp(lambda z: self.theta(z, p), (x,), (xdot,))
        grad_t = jax.grad(lambda z: 0.5 * xdot @ self.theta(z, p) @ xdot)(x)
        gyro = jnp.einsum("ijh,j,h->i", self.omega(x, p), xdot, xdot)
        return jnp.stack([theta @ xddot, theta_dot @ xdot, -grad_t, jax.grad(self.potential)(x, p), -gyro])

    def chaplygin_residual(self, x, xdot, xddot, p):
        """``Θẍ + Θ̇ẋ − ∂T*/∂x + ∂V/∂x − (Ωẋ)ẋ``, zero on motions (S4 (4.5); ``(Ωẋ)ẋ_i = ω_ijh ẋ_j ẋ_h``)."""
        return jnp.sum(self._chaplygin_terms(x, xdot, xddot, p), axis=0)

    def _about_point(self, r, sdot):
        """``(x, ẋ, ẍ)`` of the steady motion: ``r``, ``ṙ = 0``, ``ṡ``, ``ẍ = 0``."""
        x0 = self._x(r)
        return x0, jnp.zeros_like(x0).at[self._slots()[1]].set(sdot), jnp.zeros_like(x0)

    def expansion(self, r, sdot, p) -> tuple[Array, tuple[Array, Array, Array]]:
        """The terms of (4.5) and their derivatives at the steady motion ``r``, ``ṙ = 0``, ``ṡ``, ``ẍ = 0``.

        Returns ``(terms, (∂/∂x, ∂/∂ẋ, ∂/∂ẍ))``, each with a leading axis over the
        five terms ``Θẍ``, ``Θ̇ẋ``, ``−∂T*/∂x``, ``∂V/∂x``, ``−(Ωẋ)ẋ``; rows/columns ordered ``(r, s)``.
        """
        order = np.concatenate(self._slots())

        def terms(x, xdot, xddot):
            out = self._chaplygin_terms(x, xdot, xddot, p)
            return out, out

        jacs, out = jax.jacfwd(terms, argnums=(0, 1, 2), has_aux=True)(*self._about_point(r, sdot))
        du, dv, dw = (j[:, order][:, :, order] for j in jacs)
        return out[:, order], (du, dv, dw)

    def linearisation(self, r, sdot, p):
        """``(W, V, U)`` of (4.5) linearised about ``r = r0, ṡ = ṡ0``: ``W δẍ + V δẋ + U δx = 0``.

        Rows and columns ordered ``(r, s)``; ``W = Θ0`` and these are the blocks of
        ``Δ(μ)`` in S4 (4.22)–(4.23).
        """
        _, (u, v, w) = self.expansion(r, sdot, p)
        return jnp.sum(w, axis=0), jnp.sum(v, axis=0), jnp.sum(u, axis=0)

    def routh(self, r, sdot, p):
        """``(A0, G0 + D0, C0 + E0)`` of S4 (4.17)–(4.19): see :func:`routh_pencil`."""
        return routh_pencil(*self.linearisation(r, sdot, p), self.k)

    # ------------------------------------------------------------ the library's reduced drift

    def reduced_field(self, t, z, p):
        """The reduced drift on ``z = (r, ṙ, ṡ)`` from :mod:`nhsde.mechanics` (``s``, ``y`` dropped)."""
        k, n = self.k, self.spec.n
        r_slot, s_slot = self._slots()
        q = self.reference.astype(z.dtype).at[np.asarray(self.positional, int)].set(z[:k])
        w = (
            jnp.zeros(len(self.form.elimination.independent), z.dtype)
            .at[r_slot]
            .set(z[k : 2 * k])
            .at[s_slot]
            .set(z[2 * k :])
        )
        dy = self.form.drift(t, jnp.concatenate([q, w]), p)
        return jnp.concatenate([dy[np.asarray(self.positional, int)], dy[n:][r_slot], dy[n:][s_slot]])

    def steady_state(self, r, sdot):
        """``z = (r0, 0, ṡ0)`` for :meth:`reduced_field`."""
        r, sdot = jnp.asarray(r), jnp.asarray(sdot)
        return jnp.concatenate([r, jnp.zeros_like(r), sdot])


def _samples(spec, reference, count, seed):
    key_q, key_v = jax.random.split(jax.random.key(seed))
    q = reference + jax.random.uniform(key_q, (count, spec.n), reference.dtype, -0.5, 0.5)
    return q, jax.random.normal(key_v, (count, spec.n), reference.dtype)


def _negligible(derivative, scale) -> bool:
    return float(np.max(np.abs(derivative), initial=0.0)) <= _TOL * max(float(scale), np.finfo(float).tiny)


def _names(spec, indices):
    return tuple(spec.coordinates[i] for i in indices)


def _with_jacobian(fn, x):
    value = fn(x)
    return value, jax.jacfwd(fn)(x), jnp.max(jnp.abs(value), initial=0.0)


@eqx.filter_jit(compiler_options=FAST_COMPILE)  # pyright: ignore[reportCallIssue]  (jit options untyped)
def _survey_spec(spec, elim, q, v):
    """Values and derivatives for the conservative and Chaplygin checks at one configuration."""
    p, pi, t = spec.params, jnp.zeros(0, q.dtype), jnp.zeros((), q.dtype)
    rows, bias = spec.velocity_constraints(q, pi, t, p)
    out = {
        "bias": (bias, 1.0 + jnp.max(jnp.abs(rows))),
        "forces": (
            spec.disturbing_force(q, v, pi, t, p) - jax.grad(spec.rayleigh, argnums=1)(q, v, pi, t, p),
            jnp.max(jnp.abs(spec.inertia(q, pi, t, p) @ v)),
        ),
    }
    parts = {
        "mass matrix": lambda q, t: spec.inertia(q, pi, t, p),
        "potential": lambda q, t: spec.potential_energy(q, pi, t, p),
        "constraints": lambda q, t: spec.velocity_constraints(q, pi, t, p)[0],
    }
    for name, fn in parts.items():
        value, rate = jax.jvp(lambda t, fn=fn: fn(q, t), (t,), (jnp.ones_like(t),))
        out["time " + name] = (rate, 1.0 + jnp.max(jnp.abs(value)))
    parts = {
        "the constraint matrix M (ẏ = M ẋ)": lambda z: elim.velocity_basis(spec, z, pi, t, p)[2],
        "the kinetic energy T": lambda z: spec.inertia(z, pi, t, p),
        "the potential V": lambda z: spec.potential_energy(z, pi, t, p),
    }
    for name, fn in parts.items():
        _, jac, size = _with_jacobian(fn, q)
        out["y " + name] = (jac, size + jnp.max(jnp.abs(jac)))
    return out


@eqx.filter_jit(compiler_options=FAST_COMPILE)  # pyright: ignore[reportCallIssue]  (jit options untyped)
def _survey_reduced(system, x):
    """``(∂F/∂x, scale)`` for ``F = Θ, Ω, V`` (S4 (4.7)) and ``Ω`` itself."""
    p = system.spec.params
    out = []
    for fn in (system.theta, system.omega, system.potential):
        _, jac, size = _with_jacobian(lambda z, fn=fn: fn(z, p), x)
        out.append((jac, size + jnp.max(jnp.abs(jac))))
    return out, system.omega(x, p)


def _check_structure(spec):
    if spec.k:
        raise ValueError(
            f"random_parameters={spec.random_parameters}: steady motions (S4 §4.2) are for deterministic "
            "systems; give a spec without random parameters."
        )
    if spec.holonomic is not None or spec.servo is not None:
        raise ValueError(
            "holonomic or servo-constraints given: S4 (4.1) has only linear homogeneous constraints N(z)ż = 0."
        )


def _check_conservative(survey, qs, vs):
    """S4 treats ``N(z)ż = 0`` with time-independent ``T``, ``V`` and no other forces."""
    for out, q, v in zip(survey, qs, vs):
        where = f"q={np.round(np.asarray(q), 4).tolist()}"
        if not _negligible(*out["bias"]):
            raise ValueError(f"constraint_bias = {np.asarray(out['bias'][0])} at {where}: S4 (4.1) needs N(z)ż = 0.")
        if not _negligible(*out["forces"]):
            raise ValueError(
                f"the spec's forces and dissipation give Q = {np.asarray(out['forces'][0])} at {where}, "
                f"q̇={np.round(np.asarray(v), 4).tolist()}: S4 treats conservative systems (set "
                "friction and forces to zero)."
            )
        for name in ("mass matrix", "potential", "constraints"):
            if not _negligible(*out["time " + name]):
                raise ValueError(f"the {name} depends on time t: S4 (4.1)–(4.2) treat scleronomic systems.")


def _check_chaplygin(spec, elim, survey, qs):
    """``∂T/∂y = ∂V/∂y = ∂M/∂y = 0`` (S4 §4.1, before (4.5)), at the sample configurations."""
    dep = elim.dep
    for out, q in zip(survey, qs):
        for label in ("the constraint matrix M (ẏ = M ẋ)", "the kinetic energy T", "the potential V"):
            jac, scale = (np.asarray(a) for a in out["y " + label])
            offending = [int(i) for i in dep if not _negligible(jac[..., i], scale)]
            if offending:
                raise ValueError(
                    f"not a Chaplygin system: {label} depends on the dependent coordinate(s) "
                    f"{_names(spec, offending)} (max |∂/∂y| = {float(np.max(np.abs(jac[..., offending]))):.3g} at "
                    f"q={np.round(np.asarray(q), 4).tolist()}); S4 (4.4)–(4.5) need T, V and M independent of "
                    f"y = {_names(spec, dep)}. Choose other dependent velocities if possible."
                )


def chaplygin_system(spec: MechanicalSpec, dependent, reference, *, samples: int = 3, seed: int = 0) -> ChaplyginSystem:
    """Recognise ``spec`` as a conservative Chaplygin system; find ``s`` and ``r`` (S4 (4.7)–(4.8)).

    ``dependent`` names the velocities ``ẏ`` (S4 (4.4); ``None``: chosen by pivoting at
    ``reference``, :func:`nhsde.mechanics.choose_dependent`); the tests run by autodiff
    at ``samples`` configurations within ±0.5 of ``reference``.  ``ValueError`` if
    the spec is not conservative, not Chaplygin (``T``, ``V`` or ``M`` depend on
    ``y``), has no pseudo-cyclic or no positional coordinate, or violates (4.8).
    """
    if not isinstance(spec, MechanicalSpec):
        raise TypeError(f"spec={type(spec).__name__}; expected a MechanicalSpec.")
    reference = jnp.asarray(reference, jnp.result_type(float))
    require_float64("reference", reference)
    if reference.shape != (spec.n,):
        raise ValueError(f"reference has shape {reference.shape}; expected ({spec.n},) for {spec.coordinates}.")
    _check_structure(spec)
    form = formulate(spec, "reduced", dependent=dependent, reference=reference)
    assert isinstance(form, ReducedForm)  # the "reduced" route
    elim = form.elimination
    qs, vs = _samples(spec, reference, samples, seed)
    survey = [_survey_spec(spec, elim, q, v) for q, v in zip(qs, vs)]
    _check_conservative(survey, qs, vs)
    _check_chaplygin(spec, elim, survey, qs)
    probe = ChaplyginSystem(spec, form, reference, tuple(elim.independent), ())
    ind = elim.ind
    cyclic = np.ones(len(ind), bool)
    for q in qs:
        for jac, scale in _survey_reduced(probe, q[ind])[0]:
            jac = np.asarray(jac)
            cyclic &= np.array([_negligible(jac[..., i], scale) for i in range(len(ind))])
    positional = tuple(int(i) for i, c in zip(ind, cyclic) if not c)
    pseudo_cyclic = tuple(int(i) for i, c in zip(ind, cyclic) if c)
    if not pseudo_cyclic or not positional:
        raise ValueError(
            f"independent coordinates {_names(spec, ind)}: pseudo-cyclic {_names(spec, pseudo_cyclic)}, positional "
            f"{_names(spec, positional)}; S4 §4.2 needs at least one of each (Θ, V, Ω independent of s, (4.7))."
        )
    system = ChaplyginSystem(spec, form, reference, positional, pseudo_cyclic)
    slot = [list(elim.independent).index(i) for i in pseudo_cyclic]
    for q in qs:
        omega = np.asarray(_survey_reduced(probe, q[ind])[1])
        if not _negligible(omega[np.ix_(slot, slot, slot)], np.max(np.abs(omega))):
            raise ValueError(
                f"Ω_sss ≠ 0 for s = {_names(spec, pseudo_cyclic)} "
                f"at q={np.round(np.asarray(q), 4).tolist()}: condition "
                "(4.8) fails, and steady motions other than equilibria need (4.12) as well (S4 Remark 4.1)."
            )
    return system
