"""Steady motions of conservative Chaplygin systems and their stability, S4 §4.1–4.4.

A Chaplygin system (S4 (4.4)–(4.5)): the constraints solved for the dependent
velocities read ``ẏ = M(x) ẋ`` with the kinetic energy ``T``, the potential ``V`` and
``M`` independent of ``y``; then ``x`` obeys

    d/dt ∂T*/∂ẋ = ∂T*/∂x − ∂V/∂x + (Ωẋ)ẋ,   ω_ijh = (∂m_κi/∂x_j − ∂m_κj/∂x_i) θ_κh,   (4.5)

with ``T* = ½ ẋᵀΘẋ`` and ``θ_κh = ∂(∂T/∂ẏ_κ)/∂ẋ_h`` on the constraints.  Coordinates
``s`` on which ``Θ``, ``V`` and ``Ω`` do not depend are pseudo-cyclic, the others
``r`` positional (4.7); with ``Ω_sss = 0`` (4.8) the motions ``r = r0``, ``ṡ = ṡ0``
solving (4.9) form families of steady motions.  Their stability in ``r, ṙ, ṡ``
is decided by the ``2k`` roots of ``det(A0 μ² + (G0 + D0) μ + (C0 + E0)) = 0``
(4.19), Theorem 4.1; the ``m`` further zero roots belong to the family.

Two independent routes give the roots: the linearisation of (4.5) written here
from ``Θ``, ``Ω``, ``V`` (the matrix ``Δ(μ)`` of (4.22)–(4.23), whose Schur
complement is the Routh pencil of (4.19)), and the eigenvalues of the Jacobian
of :mod:`nhsde.mechanics`' reduced (Voronets) drift on ``(r, ṙ, ṡ)``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

from ..mechanics import MechanicalSpec, formulate
from ..mechanics._forms import ReducedForm
from ._liouville import FAST_COMPILE
from ._stability import Stability, classify, linear_stability, require_float64

__all__ = [
    "ChaplyginSystem",
    "StabilityBoundary",
    "SteadyMotions",
    "SteadyStability",
    "chaplygin_system",
    "delta_matrix",
    "routh_pencil",
    "stability_boundary",
    "steady_motions",
    "steady_stability",
]

_TOL = 1e-8  # relative size below which an autodiff derivative counts as zero (rounding: ~1e-16)
_NEWTON_STEPS = 50
_CHUNK = 8  # family values solved per compiled, vmapped Newton call


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

    def _about(self, r, sdot, p):
        """(4.5)'s terms and their derivatives at ``r``, ``ṙ = 0``, ``ṡ``, ``ẍ = 0``; rows/columns ``(r, s)``.

        Returns ``(terms, (∂/∂x, ∂/∂ẋ, ∂/∂ẍ))``, each with a leading axis over the terms.
        """
        order = np.concatenate(self._slots())

        def terms(*args):
            out = self._chaplygin_terms(*args, p)
            return out, out

        jacs, out = jax.jacfwd(terms, argnums=(0, 1, 2), has_aux=True)(*self._about_point(r, sdot))
        return out[:, order], tuple(j[:, order][:, :, order] for j in jacs)

    def linearisation(self, r, sdot, p):
        """``(W, V, U)`` of (4.5) linearised about ``r = r0, ṡ = ṡ0``: ``W δẍ + V δẋ + U δx = 0``.

        Rows and columns ordered ``(r, s)``; ``W = Θ0`` and these are the blocks of
        ``Δ(μ)`` in S4 (4.22)–(4.23).
        """
        _, (u, v, w) = self._about(r, sdot, p)
        return tuple(jnp.sum(a, axis=0) for a in (w, v, u))

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


def routh_pencil(w, v, u, k: int):
    """``(A0, G0 + D0, C0 + E0)`` of S4 (4.17)–(4.19): the Schur complement of ``Δ(μ)`` (4.23) on ``r``.

    From the linearisation ``(W, V, U)`` (rows/columns ``r`` then ``s``, the first ``k``
    positional): ``A0 = W_rr − W_rs W_ss⁻¹ W_sr``,
    ``G0 + D0 = V_rr − W_rs W_ss⁻¹ V_sr − V_rs W_ss⁻¹ W_sr``, ``C0 + E0 = U_rr − V_rs W_ss⁻¹ V_sr``
    (eliminate ``δṡ = −W_ss⁻¹(W_sr μ + V_sr) δr`` from the ``s`` rows, which carry a factor ``μ``).
    """
    wrs, wsr, vrs, vsr = w[:k, k:], w[k:, :k], v[:k, k:], v[k:, :k]
    solve = lambda b: jnp.linalg.solve(w[k:, k:], b)
    a0 = w[:k, :k] - wrs @ solve(wsr)
    b0 = v[:k, :k] - wrs @ solve(vsr) - vrs @ solve(wsr)
    k0 = u[:k, :k] - vrs @ solve(vsr)
    return a0, b0, k0


def delta_matrix(mu, w, v, u, k: int):
    """``Δ(μ) = [[W_rr μ² + V_rr μ + U_rr, W_rs μ + V_rs], [W_sr μ + V_sr, W_ss]]`` of S4 (4.23).

    ``det Δ(μ) = det W_ss · det(A0μ² + (G0 + D0)μ + (C0 + E0))``: its roots are those of (4.19).
    """
    w, v, u = (jnp.asarray(a) for a in (w, v, u))
    dtype = jax.lax.complex(w[0, 0], w[0, 0]).dtype
    mu, w, v, u = jnp.asarray(mu, dtype), w.astype(dtype), v.astype(dtype), u.astype(dtype)
    top = jnp.concatenate([w[:k, :k] * mu**2 + v[:k, :k] * mu + u[:k, :k], w[:k, k:] * mu + v[:k, k:]], axis=1)
    bottom = jnp.concatenate([w[k:, :k] * mu + v[k:, :k], w[k:, k:]], axis=1)
    return jnp.concatenate([top, bottom])


# ---------------------------------------------------------------------------- recognition


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


@eqx.filter_jit(compiler_options=FAST_COMPILE)
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


@eqx.filter_jit(compiler_options=FAST_COMPILE)
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


# ---------------------------------------------------------------------------- families (4.9)


class SteadyMotions(eqx.Module):
    """Steady motions ``r = r0, ṙ = 0, ṡ = ṡ0`` solving S4 (4.9), one row per family parameter value.

    ``family_dimension`` is ``k + m − rank ∂(4.9)/∂(r, ṡ)``: the dimension of the
    family through each motion (``m`` in general position, S4 (4.10));
    ``linearisation``: ``(W, V, U)`` of (4.5) about each motion (rows/columns ``r``
    then ``s``), the blocks of ``Δ(μ)`` (4.23).
    """

    positions: Float[Array, "batch k"]
    velocities: Float[Array, "batch m"]
    residual: Float[Array, " batch"]
    linearisation: tuple[Array, Array, Array]
    family_dimension: tuple[int, ...] = eqx.field(static=True)

    def __getitem__(self, i) -> tuple:
        return self.positions[i], self.velocities[i]


def _evaluate(system, p, fixed_slots, free_slots, fixed, free):
    """At the unknowns ``free``: (4.9), the size of its terms, ``∂(4.9)/∂(r, ṡ) = −[U_rr, V_rs]``,
    the size of the terms' derivatives, the linearisation ``(W, V, U)`` and ``(r, ṡ)``.

    (4.9) ``∂/∂r ½ Θ_ss ṡ·ṡ + (Ω_rss ṡ)ṡ − ∂V/∂r = 0`` is minus the ``r`` rows of (4.5)
    at ``ṙ = 0``, ``ẍ = 0`` (``Θ̇ẋ = 0`` there since ``Θ`` does not depend on ``s``).
    """
    k = system.k
    u = jnp.zeros(k + system.m, free.dtype).at[fixed_slots].set(fixed).at[free_slots].set(free)
    terms, (du, dv, dw) = system._about(u[:k], u[k:], p)
    parts_jac = -jnp.concatenate([du[:, :k, :k], dv[:, :k, k:]], axis=2)
    linear = tuple(jnp.sum(a, axis=0) for a in (dw, dv, du))
    return (
        -jnp.sum(terms[:, :k], axis=0),
        jnp.sum(jnp.abs(terms[:, :k]), axis=0),
        jnp.sum(parts_jac, axis=0),
        jnp.sum(jnp.abs(parts_jac), axis=0),
        linear,
        u,
    )


def _rank_cut(jac_size):
    """Singular values below this are cancellation noise: the terms of (4.9) cancel identically there."""
    return 1e3 * jnp.finfo(jac_size.dtype).eps * jnp.max(jac_size, initial=0.0)


def _converged(res, size):
    return jnp.max(jnp.abs(res), initial=0.0) <= 1e3 * jnp.finfo(res.dtype).eps * jnp.max(size, initial=0.0)


@eqx.filter_jit(compiler_options=FAST_COMPILE)
def _solve(system, p, fixed_slots, free_slots, fixed, free):
    """Newton's method with minimum-norm steps (the family may be wider than ``m``), vmapped over rows.

    Each step evaluates (4.9) and the linearisation once and stops when (4.9)
    vanishes to rounding; the result reported is the last point evaluated.
    """

    def one(fixed, free):
        def step(carry):
            free, i = carry[0], carry[-1]
            res, size, jac, jac_size, linear, u = _evaluate(system, p, fixed_slots, free_slots, fixed, free)
            left, sv, right = jnp.linalg.svd(jac[:, free_slots], full_matrices=False)
            inverse = jnp.where(sv > _rank_cut(jac_size), 1.0 / jnp.where(sv > 0, sv, 1.0), 0.0)
            done = _converged(res, size)
            free = jnp.where(done, free, free - right.T @ (inverse * (left.T @ res)))
            return free, res, size, jac, jac_size, linear, u, i + 1

        def more(carry):
            return (carry[-1] == 0) | ((carry[-1] < _NEWTON_STEPS) & ~_converged(carry[1], carry[2]))

        init = jax.eval_shape(lambda z: _evaluate(system, p, fixed_slots, free_slots, fixed, z), free)
        init = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), init)
        _, res, size, jac, jac_size, linear, u, _ = jax.lax.while_loop(more, step, (free, *init, jnp.zeros((), int)))
        return u, jnp.max(jnp.abs(res), initial=0.0), jnp.max(size, initial=0.0), jac, _rank_cut(jac_size), linear

    return jax.vmap(one)(fixed, free)


def _values(system, family: dict, what: str):
    names = system.unknowns
    unknown = [n for n in family if n not in names]
    if unknown:
        raise ValueError(f"{what} names {unknown}; allowed: {names} (positions r, velocities ṡ as '<s>_dot').")
    values = {n: np.atleast_1d(np.asarray(v, float)) for n, v in family.items()}
    return values


def steady_motions(system: ChaplyginSystem, family: dict, guess: dict | None = None) -> SteadyMotions:
    """Solve S4 (4.9) for steady motions by Newton's method, vmapped over the family parameter.

    ``family`` fixes ``m`` of the ``k + m`` constants :attr:`ChaplyginSystem.unknowns`
    (default choice in S4 (4.11): the velocities ``ṡ``), each a scalar or a 1-d
    array of values; the other ``k`` are found from ``guess`` (default: the
    reference ``r``, ``ṡ = 1``).  ``ValueError`` names a parameter value at which
    (4.9) has no solution near the guess (outside the family's domain).
    """
    names, p = system.unknowns, system.spec.params
    fixed = _values(system, family, "family")
    if len(fixed) != system.m:
        raise ValueError(f"family fixes {sorted(fixed)}; give exactly m = {system.m} of {names} (S4 (4.10)).")
    start = _values(system, guess or {}, "guess")
    batch = np.broadcast_shapes(*(v.shape for v in fixed.values()))
    if len(batch) != 1:
        raise ValueError(
            f"family values have shapes {[v.shape for v in fixed.values()]}; expected scalars or 1-d arrays."
        )
    fixed_slots = np.array([names.index(n) for n in fixed], int)
    free_slots = np.array([i for i in range(len(names)) if i not in fixed_slots], int)
    default = np.concatenate([np.asarray(system.reference)[list(system.positional)], np.ones(system.m)])
    free0 = np.stack([np.broadcast_to(start.get(names[i], default[i]), batch) for i in free_slots], axis=-1)
    values = np.stack([np.broadcast_to(v, batch) for v in fixed.values()], axis=-1)
    # fixed-size chunks: one compilation serves every batch size
    pad = -batch[0] % _CHUNK
    values_p, free_p = (np.concatenate([a, np.repeat(a[-1:], pad, axis=0)]) for a in (values, free0))
    chunks = [
        _solve(
            system,
            p,
            fixed_slots,
            free_slots,
            jnp.asarray(values_p[i : i + _CHUNK]),
            jnp.asarray(free_p[i : i + _CHUNK]),
        )
        for i in range(0, len(values_p), _CHUNK)
    ]
    u, res, scale, full, cut, linear = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[: batch[0]], *chunks)
    u, res, scale, full, cut = (np.asarray(a) for a in (u, res, scale, full, cut))
    for i in range(batch[0]):
        if not (np.all(np.isfinite(u[i])) and res[i] <= 1e3 * np.finfo(res.dtype).eps * scale[i]):
            given = ", ".join(f"{n}={v[i]:.6g}" for n, v in zip(fixed, values.T))
            raise ValueError(
                f"no steady motion with {given}: Newton's method on S4 (4.9) from "
                f"{dict(zip([names[j] for j in free_slots], free0[i].tolist()))} ended at residual {res[i]:.3g} "
                f"(terms of size {scale[i]:.3g}); this value lies outside the family's domain (no real solution "
                "nearby)."
            )
    dims = []
    for i in range(batch[0]):
        dims.append(len(names) - int(np.sum(np.linalg.svd(full[i], compute_uv=False) > cut[i])))
    k = system.k
    return SteadyMotions(jnp.asarray(u[:, :k]), jnp.asarray(u[:, k:]), jnp.asarray(res), linear, tuple(dims))


# ---------------------------------------------------------------------------- stability (4.19)


class SteadyStability(eqx.Module):
    """Linear stability of one steady motion (S4 Theorem 4.1).

    ``A0, G0, D0, C0, E0``: the Routh pencil (4.17)–(4.19) (``G0`` skew, ``D0``
    symmetric in ``μ``; ``C0`` symmetric, ``E0`` skew); ``routh``: its ``2k`` roots,
    classified (zero roots beyond the ``m`` separated ones belong to a larger
    family); ``drift``: the eigenvalues of the library's reduced drift, the
    independent route (``None`` if not asked for); ``verdict`` from ``routh``; ``linearisation``: ``(W, V, U)``
    of (4.5) about the motion, the blocks of ``Δ(μ)`` (4.23) (:func:`delta_matrix`).
    """

    A0: Float[Array, "k k"]
    G0: Float[Array, "k k"]
    D0: Float[Array, "k k"]
    C0: Float[Array, "k k"]
    E0: Float[Array, "k k"]
    routh: Stability
    drift: Stability | None
    linearisation: tuple[Array, Array, Array]

    @property
    def verdict(self) -> str:
        return self.routh.verdict

    @property
    def roots(self) -> Complex[Array, " n"]:
        return self.routh.roots


def steady_stability(
    system: ChaplyginSystem, motions: SteadyMotions, index: int = 0, *, drift: bool = True, rtol: float = 1e-8
) -> SteadyStability:
    """Stability of ``motions[index]`` by the roots of S4 (4.19) and (``drift=True``) the reduced drift's Jacobian."""
    r, sdot = motions[index]
    linear = tuple(a[index] for a in motions.linearisation)
    a0, b0, k0 = (np.asarray(a) for a in routh_pencil(*linear, system.k))
    kk = system.k
    companion = np.block([[np.zeros((kk, kk)), np.eye(kk)], [-np.linalg.solve(a0, k0), -np.linalg.solve(a0, b0)]])
    scale = float(np.linalg.norm(companion, 2)) or 1.0
    routh = classify(np.linalg.eigvals(companion), motions.family_dimension[index] - system.m, rtol, scale)
    check = None
    if drift:
        state = system.steady_state(r, sdot)
        check = linear_stability(
            system.reduced_field, state, system.spec.params, n_family=motions.family_dimension[index], rtol=rtol
        )
    sym = lambda a: jnp.asarray(0.5 * (a + a.T))
    skew = lambda a: jnp.asarray(0.5 * (a - a.T))
    return SteadyStability(jnp.asarray(a0), skew(b0), sym(b0), sym(k0), skew(k0), routh, check, linear)


# ---------------------------------------------------------------------------- boundaries (Remark 4.6)


class StabilityBoundary(eqx.Module):
    """Where the verdict changes along a path in the family parameter.

    ``kind``: ``"Andronov–Hopf"`` when the critical roots are a complex pair
    crossing the imaginary axis (S4 Remark 4.6), ``"real root through zero"``
    otherwise; ``critical_roots``: the roots nearest the imaginary axis there;
    ``verdicts``: on the two sides.
    """

    parameter: dict = eqx.field(static=True)
    critical_roots: Complex[Array, " c"]
    kind: str = eqx.field(static=True)
    verdicts: tuple[str, str] = eqx.field(static=True)


def stability_boundary(
    system: ChaplyginSystem,
    start: dict,
    stop: dict,
    guess: dict | None = None,
    *,
    xtol: float = 1e-14,
    rtol: float = 1e-8,
) -> StabilityBoundary:
    """Bisect the segment ``start → stop`` of family parameters for the change of verdict.

    Between "asymptotically stable" and "unstable" the sign of the largest real
    part of the roots of (4.19) is bisected (it crosses zero transversally at an
    Andronov–Hopf point); otherwise the verdict itself.  ``xtol`` is relative to
    the segment.  ``ValueError`` if both ends have the same verdict.
    """
    if set(start) != set(stop):
        raise ValueError(f"start fixes {sorted(start)} but stop fixes {sorted(stop)}; fix the same names.")
    a = {n: float(v) for n, v in start.items()}
    b = {n: float(stop[n]) for n in a}
    guess = dict(guess or {})

    def at(lam):
        family = {n: a[n] + lam * (b[n] - a[n]) for n in a}
        motions = steady_motions(system, family, guess)
        u = np.concatenate([motions.positions[0], motions.velocities[0]])
        guess.update((n, u[i]) for i, n in enumerate(system.unknowns) if n not in family)  # continuation
        return family, steady_stability(system, motions, drift=False, rtol=rtol)

    first, last = at(0.0)[1], at(1.0)[1]
    ends = (first.verdict, last.verdict)
    scale = max(float(np.max(np.abs(np.asarray(s.routh.eigenvalues)))) for s in (first, last)) or 1.0
    if ends[0] == ends[1]:
        raise ValueError(f"the verdict is {ends[0]!r} at both start={start} and stop={stop}; no boundary to bisect.")
    signed = set(ends) == {"asymptotically stable", "unstable"}

    def on_stop_side(stability):
        if signed:
            return (float(stability.routh.growth_rate) > 0.0) == (ends[1] == "unstable")
        return stability.verdict == ends[1]

    lo, hi = 0.0, 1.0
    while hi - lo > xtol:
        mid = 0.5 * (lo + hi)
        if on_stop_side(at(mid)[1]):
            hi = mid
        else:
            lo = mid
    family, stability = at(0.5 * (lo + hi))
    roots = np.asarray(stability.routh.roots)
    order = np.argsort(np.abs(roots.real), kind="stable")
    critical = roots[order[:2]] if roots.size > 1 else roots
    hopf = bool(np.min(np.abs(critical.imag)) > np.sqrt(rtol) * scale)
    return StabilityBoundary(family, jnp.asarray(critical), "Andronov–Hopf" if hopf else "real root through zero", ends)
