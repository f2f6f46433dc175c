"""From a :class:`MechanicalSpec` to a :class:`~nhsde.StochasticSystem`: four routes.

==============  ============================  ===========================================
route           state ``Z``                   equations
==============  ============================  ===========================================
reduced (a)     ``[π, q, q̇']``                Voronets, S0 (1.8), (1.12)
hamiltonian (b) ``[π, q, p']``                S0 (1.13)–(1.15)
multipliers (c) ``[π, q, q̇]``                 Lagrange with multipliers, S1 (2.3)
gauss (d)       ``[π, q, q̇]``                 least compulsion, S1 (2.10)
==============  ============================  ===========================================

Each is an Itô SDE ``dZ = a dt + b dW`` (S0 (1.15)); ``π`` follows (1.2).  Routes
(c) and (d) carry all velocities, so the constraint ``(A; C) q̇ + (A0; C0) = 0`` is
kept only by the equations: Baumgarte stabilisation at ``stabilization`` κ (1/s)
pulls it back, and :func:`project_velocity` projects a state onto it.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._misc import is_concrete
from .._system import StateLayout, StochasticSystem
from . import _small as small
from ._dependence import depends_on
from ._elimination import Elimination, make_elimination
from ._multipliers import (
    compulsion_terms,
    gauss,
    gauss_noise,
    multiplier_noise,
    multipliers,
)
from ._reduced import (
    hamilton,
    hamilton_velocity,
    maggi,
    momentum,
    reduced_noise,
    voronets,
)
from ._spec import MechanicalSpec

__all__ = [
    "ROUTES",
    "AbstractForm",
    "GaussForm",
    "HamiltonianForm",
    "MultiplierForm",
    "ReducedForm",
    "build",
    "formulate",
    "project_velocity",
]


def _inputs(spec, q, qdot, pi=None, t: ArrayLike = 0.0):
    q = jnp.asarray(q)
    if q.shape != (spec.n,):
        raise ValueError(f"q has shape {q.shape}; expected ({spec.n},) for coordinates {spec.coordinates}.")
    qdot = jnp.asarray(qdot, q.dtype)
    if qdot.shape != (spec.n,):
        raise ValueError(f"qdot has shape {qdot.shape}; expected ({spec.n},).")
    pi = jnp.zeros(spec.k, q.dtype) if pi is None else jnp.asarray(pi, q.dtype)
    if pi.shape != (spec.k,):
        raise ValueError(f"pi has shape {pi.shape}; expected ({spec.k},) for {spec.random_parameters}.")
    return q, qdot, pi, jnp.asarray(t, q.dtype)


def _checked_state(spec, elim, q, pi, t):
    """``q`` with run-time checks of the mass matrix and the elimination at this state."""
    p = spec.params
    pivots = jnp.diagonal(small.cholesky(spec.inertia(q, pi, t, p)))
    q = eqx.error_if(q, ~jnp.all(pivots > 0), "the mass matrix is singular or indefinite at this state.")
    rows, _ = spec.velocity_constraints(q, pi, t, p)
    if rows.shape[0]:
        q = eqx.error_if(
            q, small.rank_deficient(rows), "the constraint rows are dependent (rank-deficient) at this state."
        )
    if elim is not None and elim.dependent:
        q = eqx.error_if(
            q,
            small.rank_deficient(rows[:, elim.dep]),
            "the dependent-velocity choice makes B' singular at this state (a_D singular).",
        )
    return q


class AbstractForm(eqx.Module):
    """Equations of motion of a spec by one route; :meth:`system` gives the Itô SDE."""

    spec: eqx.AbstractVar[MechanicalSpec]
    elimination: eqx.AbstractVar[Elimination | None]
    route: eqx.AbstractClassVar[str]

    # ---------------------------------------------------------------- route-specific

    @abc.abstractmethod
    def _motion(self, t, q, x, pi, p) -> tuple[Array, Array]:
        """``(q̇, ẋ)``: all velocities and the drift of the route's velocity part ``x``."""

    @abc.abstractmethod
    def _noise(self, t, q, x, pi, p) -> Array:
        """``ẋ_V``, shape ``(len(x), l)``: the noise of ``x``."""

    @abc.abstractmethod
    def _velocity(self, t, q, x, pi, p) -> Array:
        """All velocities ``q̇`` from the route's velocity part ``x``."""

    @abc.abstractmethod
    def _pack(self, q, v, pi, t, p) -> Array:
        """The route's velocity part ``x`` from all velocities ``q̇``."""

    @abc.abstractmethod
    def _velocity_layout(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """Names and roles of ``x``."""

    def _extra_observables(self) -> tuple:
        return ()

    # ---------------------------------------------------------------- shared

    def _split(self, t, y):
        k, n = self.spec.k, self.spec.n
        return jnp.asarray(t, y.dtype), y[:k], y[k : k + n], y[k + n :]

    def velocities(self, t, y, p):
        """``(q, q̇, π)`` of the state ``y``."""
        t, pi, q, x = self._split(t, y)
        return q, self._velocity(t, q, x, pi, p), pi

    def drift(self, t, y, p):
        t, pi, q, x = self._split(t, y)
        parts = list(self._motion(t, q, x, pi, p))
        return jnp.concatenate([self.spec.pi_drift(pi, t, p), *parts] if self.spec.k else parts)

    def diffusion(self, t, y, p):
        t, pi, q, x = self._split(t, y)
        x_v = self._noise(t, q, x, pi, p)
        parts = [jnp.zeros((self.spec.n, self.spec.noise_dim), y.dtype), x_v]
        if self.spec.k:
            parts.insert(0, self.spec.pi_diffusion(pi, t, p))
        return jnp.concatenate(parts)

    def layout(self) -> StateLayout:
        spec, elim = self.spec, self.elimination
        dependent = () if elim is None else elim.dependent
        roles = tuple("dependent_coordinate" if i in dependent else "independent_coordinate" for i in range(spec.n))
        names, x_roles = self._velocity_layout()
        return StateLayout(
            spec.random_parameters + spec.coordinates + names,
            ("random_parameter",) * spec.k + roles + x_roles,
            spec.angles,
        )

    def state(self, q, qdot, pi=None, t: ArrayLike = 0.0):
        """The state ``Z`` of this route for coordinates ``q``, velocities ``q̇`` on the constraints."""
        spec = self.spec
        q, qdot, pi, t = _inputs(spec, q, qdot, pi, t)
        residual = jnp.max(jnp.abs(spec.constraint_residual(q, qdot, pi, t, spec.params)), initial=0.0)
        tol = jnp.sqrt(jnp.finfo(q.dtype).eps) * (1 + jnp.max(jnp.abs(qdot)))
        if is_concrete(residual) and residual > tol:
            raise ValueError(
                f"qdot={np.asarray(qdot).tolist()} violates the constraints (residual {float(residual):.3g}); "
                "make it consistent, e.g. with mechanics.project_velocity."
            )
        qdot = eqx.error_if(qdot, residual > tol, "qdot violates the constraints.")
        parts = [q, self._pack(q, qdot, pi, t, spec.params)]
        return jnp.concatenate([pi, *parts] if spec.k else parts)

    def accelerations(self, q, qdot, pi=None, t: ArrayLike = 0.0):
        """``q̈ = d q̇(Z)/dt`` (drift part) of all coordinates at ``(q, q̇)`` on the constraints.

        ``q̇`` is linear in the route's velocities (or momenta) at given ``q``, so
        Itô's formula adds nothing: ``q̈ = ∂q̇/∂Z a + ∂q̇/∂t``.
        """
        spec = self.spec
        q, qdot, pi, t = _inputs(spec, q, qdot, pi, t)
        q = _checked_state(spec, self.elimination, q, pi, t)
        y, p = self.state(q, qdot, pi, t), spec.params
        return jax.jvp(lambda t, y: self.velocities(t, y, p)[1], (t, y), (jnp.ones((), t.dtype), self.drift(t, y, p)))[
            1
        ]

    def acceleration_noise(self, q, qdot, pi=None, t: ArrayLike = 0.0):
        """``∂q̇/∂Z b``, shape ``(n, l)``: the accelerations' response to the white noise ``V``."""
        spec = self.spec
        q, qdot, pi, t = _inputs(spec, q, qdot, pi, t)
        y, p = self.state(q, qdot, pi, t), spec.params
        return jax.jacfwd(lambda y: self.velocities(t, y, p)[1])(y) @ self.diffusion(t, y, p)

    def system(self) -> StochasticSystem:
        """The Itô system ``dZ = a dt + b dW`` for :func:`nhsde.simulate`.

        Observables: ``energy`` (``T + Π``), ``constraint_residual``
        (``max |(A; C) q̇ + (A0; C0)|``) and the route's own (velocities not in the
        state, multipliers).  The noise is declared additive when ``b`` does not
        depend on the state.
        """
        form = eqx.tree_at(lambda f: f.spec.params, self, None)  # static and hashable; params come as args
        drift, diffusion = _Field(form, "drift"), _Field(form, "diffusion")
        layout = self.layout()
        y = jnp.zeros(layout.size)
        additive = not depends_on(diffusion, (jnp.zeros(()), y, self.spec.params), 1)
        observables = (("energy", _Field(form, "energy")), ("constraint_residual", _Field(form, "residual")))
        return StochasticSystem(
            drift_fn=drift,
            diffusion_fn=diffusion,
            params=self.spec.params,
            layout=layout,
            noise_dim=self.spec.noise_dim,
            additive_noise=additive,
            observables=observables
            + tuple((name, _Field(form, kind, i)) for name, kind, i in self._extra_observables()),
        )


class _Field(eqx.Module):
    """A vector field or observable ``f(t, y, params)`` of a form (hashable: no parameters inside)."""

    form: AbstractForm = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    index: int = eqx.field(static=True, default=0)

    def __call__(self, t, y, p):
        form = self.form
        if self.kind == "drift":
            return form.drift(t, y, p)
        if self.kind == "diffusion":
            return form.diffusion(t, y, p)
        q, v, pi = form.velocities(t, y, p)
        if self.kind == "energy":
            return form.spec.energy(q, v, pi, t, p)
        if self.kind == "residual":
            return jnp.max(jnp.abs(form.spec.constraint_residual(q, v, pi, t, p)), initial=0.0)
        if self.kind == "velocity":
            return v[self.index]
        if not isinstance(form, MultiplierForm):  # "multiplier": only the multipliers route offers them
            raise ValueError(f"{type(form).__name__} has no observable of kind {self.kind!r}.")
        return multipliers(form.spec, q, v, pi, t, p, form.stabilization)[1][self.index]


def _velocity_names(spec, indices):
    return tuple(f"{spec.coordinates[i]}_dot" for i in indices)


class ReducedForm(AbstractForm):
    """Route (a): Voronets equations in ``(q, q̇')``, S0 (1.8), (1.12).

    With servo-constraints the displacements obey Beghin's conditions S1 (3.2)
    instead of the velocity constraints (:func:`~._reduced.maggi`).
    """

    spec: MechanicalSpec
    elimination: Elimination
    route: ClassVar[str] = "reduced"

    def _motion(self, t, q, x, pi, p):
        equations = voronets if self.spec.servo is None else maggi
        g, rhs, v = equations(self.spec, self.elimination, q, x, pi, t, p)
        return v, small.spd_solve(g, rhs)  # g: the reduced kinetic metric, symmetric positive definite

    def _noise(self, t, q, x, pi, p):
        g, noise = reduced_noise(self.spec, self.elimination, q, self._velocity(t, q, x, pi, p), pi, t, p)
        return small.spd_solve(g, noise)

    def _velocity(self, t, q, x, pi, p):
        psi, b, _, _ = self.elimination.velocity_basis(self.spec, q, pi, t, p)
        return psi @ x + b

    def _pack(self, q, v, pi, t, p):
        return v[self.elimination.ind]

    def _velocity_layout(self):
        ind = self.elimination.independent
        return _velocity_names(self.spec, ind), ("velocity",) * len(ind)

    def _extra_observables(self):
        dep = self.elimination.dependent
        return tuple((name, "velocity", i) for name, i in zip(_velocity_names(self.spec, dep), dep))


class HamiltonianForm(AbstractForm):
    """Route (b): ``q̇' = ∂H/∂p'``, ``ṗ' = U + U'' V``, ``q̇'' = Λ``; state ``[π, q, p']`` (S0 (1.13)–(1.15))."""

    spec: MechanicalSpec
    elimination: Elimination
    route: ClassVar[str] = "hamiltonian"

    def _motion(self, t, q, x, pi, p):
        u, v = hamilton(self.spec, self.elimination, q, x, pi, t, p)
        return v, u

    def _noise(self, t, q, x, pi, p):
        """``U'' = Ψᵀ Q²``."""
        spec, elim = self.spec, self.elimination
        psi = elim.velocity_basis(spec, q, pi, t, p)[0]
        return psi.T @ spec.random_force(q, self._velocity(t, q, x, pi, p), pi, t, p)

    def _velocity(self, t, q, x, pi, p):
        return hamilton_velocity(self.spec, self.elimination, q, x, pi, t, p)

    def _pack(self, q, v, pi, t, p):
        """``p' = ∂T*/∂q̇'``."""
        return momentum(self.spec, self.elimination, q, v[self.elimination.ind], pi, t, p)

    def _velocity_layout(self):
        ind = self.elimination.independent
        return tuple(f"p_{self.spec.coordinates[i]}" for i in ind), ("momentum",) * len(ind)

    def _extra_observables(self):
        return tuple((name, "velocity", i) for i, name in enumerate(_velocity_names(self.spec, range(self.spec.n))))


class _AbstractAllVelocitiesForm(AbstractForm):
    """A route whose velocity part is all of ``q̇`` (multipliers, Gauss): state ``[π, q, q̇]``."""

    def _velocity(self, t, q, x, pi, p):
        return x

    def _pack(self, q, v, pi, t, p):
        return v

    def _velocity_layout(self):
        return _velocity_names(self.spec, range(self.spec.n)), ("velocity",) * self.spec.n


class MultiplierForm(_AbstractAllVelocitiesForm):
    """Route (c): Lagrange's equations with multipliers, S1 (2.3); state ``[π, q, q̇]``.

    Observables ``lambda_j``: the multipliers of the constraint rows (ideal, then
    servo), so that the reactions are ``Dᵀ λ`` (:meth:`reactions`).
    """

    spec: MechanicalSpec
    elimination: Elimination | None
    stabilization: float = eqx.field(static=True)
    route: ClassVar[str] = "multipliers"

    def _motion(self, t, q, x, pi, p):
        return x, multipliers(self.spec, q, x, pi, t, p, self.stabilization)[0]

    def _noise(self, t, q, x, pi, p):
        return multiplier_noise(self.spec, q, x, pi, t, p)[0]

    def _extra_observables(self):
        return tuple((f"lambda_{j}", "multiplier", j) for j in range(self.spec.n_ideal + self.spec.n_servo))

    def multipliers(self, q, qdot, pi=None, t: ArrayLike = 0.0):
        """``λ`` (drift part) at ``(q, q̇)``."""
        spec = self.spec
        q, qdot, pi, t = _inputs(spec, q, qdot, pi, t)
        q = _checked_state(spec, self.elimination, q, pi, t)
        return multipliers(spec, q, qdot, pi, t, spec.params, self.stabilization)[1]

    def reactions(self, q, qdot, pi=None, t: ArrayLike = 0.0):
        """Generalised reaction forces ``Dᵀ λ`` (ideal and servo), drift part."""
        spec = self.spec
        q, qdot, pi, t = _inputs(spec, q, qdot, pi, t)
        return spec.displacement_constraints(q, pi, t, spec.params).T @ self.multipliers(q, qdot, pi, t)


class GaussForm(_AbstractAllVelocitiesForm):
    """Route (d): accelerations of least compulsion, S1 (2.10); state ``[π, q, q̇]``."""

    spec: MechanicalSpec
    elimination: Elimination | None
    stabilization: float = eqx.field(static=True)
    route: ClassVar[str] = "gauss"

    def _motion(self, t, q, x, pi, p):
        return x, gauss(self.spec, q, x, pi, t, p, self.stabilization)

    def _noise(self, t, q, x, pi, p):
        return gauss_noise(self.spec, q, x, pi, t, p)

    def compulsion(self, q, qdot, qddot, pi=None, t: ArrayLike = 0.0):
        """Gauss's compulsion ``Z = ½ (q̈ − M⁻¹F)ᵀ M (q̈ − M⁻¹F)`` of accelerations ``q̈`` (S1 (2.10))."""
        spec = self.spec
        q, qdot, pi, t = _inputs(spec, q, qdot, pi, t)
        mass, force = compulsion_terms(spec, q, qdot, pi, t, spec.params)
        dev = jnp.asarray(qddot, q.dtype) - small.spd_solve(mass, force)
        return 0.5 * dev @ mass @ dev


ROUTES = {"reduced": ReducedForm, "hamiltonian": HamiltonianForm, "multipliers": MultiplierForm, "gauss": GaussForm}
"""Route names → form classes: (a) reduced, (b) hamiltonian, (c) multipliers, (d) gauss."""


def formulate(
    spec: MechanicalSpec,
    route: str = "reduced",
    *,
    dependent=None,
    reference=None,
    pi=None,
    t: float = 0.0,
    stabilization: float = 0.0,
) -> AbstractForm:
    """The equations of motion of ``spec`` by ``route`` (one of :data:`ROUTES`).

    - ``dependent``: names of the dependent velocities ``q̇''`` (S0 (1.7)); with
      ``None`` they are chosen by pivoting at ``reference``.  Needed by the reduced
      routes; for the others they only set the coordinates' roles.
    Arguments:
        spec: the :class:`MechanicalSpec`.
        route: ``"reduced"`` (Voronets), ``"hamiltonian"``, ``"multipliers"`` (Lagrange) or ``"gauss"``.
        dependent: names of the dependent velocities ``q̇''`` (S0 (1.7)); with
            ``None`` they are chosen by pivoting at ``reference``.  Needed by the reduced
            routes; for the others they only set the coordinates' roles.
        reference: a configuration at which :meth:`MechanicalSpec.check` and the
            elimination are checked.
        pi, t: the random parameters and time that complete ``reference``.
        stabilization: Baumgarte rate κ ≥ 0 (1/s) of routes (c), (d).

    Returns:
        the route's :class:`AbstractForm`: ``system()`` gives the Itô system, ``state(q, q̇)`` a state of it.
    """
    if not isinstance(spec, MechanicalSpec):
        raise TypeError(f"spec={type(spec).__name__}; expected a MechanicalSpec.")
    if route not in ROUTES:
        raise ValueError(f"route={route!r}; allowed: {', '.join(ROUTES)}.")
    stabilization = float(stabilization)
    if not np.isfinite(stabilization) or stabilization < 0:
        raise ValueError(f"stabilization={stabilization}; must be finite and ≥ 0 (a rate in 1/s).")
    reduced = route in ("reduced", "hamiltonian")
    if reduced and stabilization:
        raise ValueError(f"stabilization={stabilization} applies to routes 'multipliers' and 'gauss' only.")
    if route == "hamiltonian" and spec.servo is not None:
        raise ValueError(
            "route='hamiltonian' needs ideal constraints: servo-constraint reactions work on the allowed "
            "displacements (S1 (3.1)), so p' = ∂T*/∂q̇' obeys no Hamiltonian equation; use 'reduced', "
            "'multipliers' or 'gauss'."
        )
    if reference is not None:
        spec.check(reference, pi, t)
    elim = None
    if reduced or dependent is not None or reference is not None:
        elim = make_elimination(spec, dependent, reference, pi, t)
    cls = ROUTES[route]
    return cls(spec, elim) if reduced else cls(spec, elim, stabilization)


def build(spec: MechanicalSpec, route: str = "reduced", **options) -> StochasticSystem:
    """``formulate(spec, route, **options).system()``: the Itô system of ``spec``, S0 (1.15).

    Arguments:
        spec: the :class:`MechanicalSpec`.
        route: one of :data:`ROUTES`.
        **options: ``dependent``, ``reference``, ``pi``, ``t``, ``stabilization`` of :func:`formulate`.

    Returns:
        the :class:`~nhsde.StochasticSystem` of the route.

    Examples:
        A knife edge (Chaplygin sleigh with the centre of mass on the blade): ``T = ½|q̇|²``,
        Rayleigh ``R = ε|q̇|²``, random forces along ``x`` and ``y``, no sideways slip
        ``−sin θ ẋ + cos θ ẏ = 0``:

        >>> import jax.numpy as jnp
        >>> import nhsde
        >>> from nhsde import mechanics
        >>> class KnifeParameters(nhsde.AbstractParameters):
        ...     eps: jnp.ndarray = nhsde.parameter(default=0.5, lower=0.0, doc="friction ε")
        ...     nu: jnp.ndarray = nhsde.parameter(default=1.0, lower=0.0, doc="noise intensity ν")
        >>> def kinetic(q, v, pi, t, p):
        ...     return 0.5 * (v @ v)
        >>> def rayleigh(q, v, pi, t, p):
        ...     return p.eps * (v @ v)
        >>> def noise(q, v, pi, t, p):
        ...     return nhsde.sqrt_intensity(p.nu) * jnp.eye(3, 2, dtype=v.dtype)
        >>> def knife(q, pi, t, p):
        ...     return jnp.stack([jnp.array([-jnp.sin(q[2]), jnp.cos(q[2]), 0.0])])
        >>> spec = mechanics.MechanicalSpec(
        ...     coordinates=("x", "y", "theta"),
        ...     params=KnifeParameters(),
        ...     kinetic_energy=kinetic,
        ...     dissipation=rayleigh,
        ...     noise_force=noise,
        ...     constraints=knife,
        ... )
        >>> system = mechanics.build(spec, "reduced", dependent=("y",), reference=jnp.zeros(3))
        >>> system.layout.names
        ('x', 'y', 'theta', 'x_dot', 'theta_dot')
        >>> system.layout.roles[1]
        'dependent_coordinate'
    """
    return formulate(spec, route, **options).system()


def project_velocity(spec: MechanicalSpec, q, qdot, pi=None, t: ArrayLike = 0.0):
    """The velocity on the constraints nearest to ``q̇`` in the kinetic metric.

    ``q̇* = q̇ − M⁻¹Bᵀ (B M⁻¹ Bᵀ)⁻¹ (B q̇ + b)`` with ``B q̇ + b = 0`` all velocity rows.
    """
    q, qdot, pi, t = _inputs(spec, q, qdot, pi, t)
    p = spec.params
    rows, bias = spec.velocity_constraints(q, pi, t, p)
    if rows.shape[0] == 0:
        return qdot
    m_inv_rows = small.spd_solve(spec.inertia(q, pi, t, p), rows.T)
    return qdot - m_inv_rows @ small.spd_solve(rows @ m_inv_rows, rows @ qdot + bias)
