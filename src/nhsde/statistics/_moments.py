"""The moment equations of the normal approximation (statistical linearisation), S0 §6.

Gaussian closure of the Itô system ``dZ = a dt + b dW``, ``W`` of intensity
``ν`` per channel (S0 (1.4): Wiener, Poisson or general): with ``E_N`` the
expectation under ``N(m, K)``,

    ṁ = E_N[a],    K̇ = Ā K + K Āᵀ + E_N[b diag(ν) bᵀ],    Ā = E_N[∂a/∂Z]

(``E_N[a Z°ᵀ] = Ā K`` by Stein's lemma).  It is exact for linear systems, with
any driver.  Expectations are tensor Gauss–Hermite cubatures of ``order`` nodes
per component over the components on which ``∂a/∂Z`` or ``b`` depend (``a`` is
affine in the others: no cubature at all for a linear system, never over ``q''``
in a Chaplygin system); the equations are solved with fixed Dopri8 steps in a
``lax.scan``, or, for a linear autonomous system, exactly by matrix exponentials
(:func:`_linear_flow`), so results are differentiable in every parameter, in
forward and in reverse mode.  Their transient solution is
:func:`~nhsde.statistics.normal_approximation`, their stationary regime
:func:`~nhsde.statistics.stationary_drift`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._misc import FAST_COMPILE, check_number, is_concrete, real_state
from .._params import validated
from .._solvers import linear_flow
from .._system import StochasticSystem
from ..noise import driver_intensity

__all__ = ["GaussianClosure", "gaussian_closure", "initial_moments", "integrate_moments"]


def _hermite(order: int, dim: int, dtype):
    """Tensor Gauss–Hermite rule for ``N(0, I_dim)``: nodes ``(P, dim)``, weights ``(P,)``, exactly symmetric."""
    x, w = np.polynomial.hermite_e.hermegauss(order)
    x, w = (x - x[::-1]) / 2, (w + w[::-1]) / 2
    w = w / w.sum()
    grid = np.meshgrid(*([x] * dim), indexing="ij")
    wgrid = np.meshgrid(*([w] * dim), indexing="ij")
    nodes = np.stack([g.reshape(-1) for g in grid], axis=-1) if dim else np.zeros((1, 0))
    weights = np.prod(np.stack([g.reshape(-1) for g in wgrid], axis=-1), axis=-1) if dim else np.ones(1)
    return jnp.asarray(nodes, dtype), jnp.asarray(weights, dtype)


def _dependence(system: StochasticSystem, points: Array, directions: Array, times: Array):
    """``d/dZ (∂a/∂Z, b)`` at each point along each direction (``(point, direction, …)`` arrays, at ``t = 0``), and
    ``d/dt (a, b)`` at each point and time (``(point, time, …)``)."""
    drift: Callable[..., Array] = system.drift_fn
    diffusion: Callable[..., Array] = system.diffusion_fn

    def coefficients(z):
        # called with t = 0.0 (a float: VectorField's annotation asks for an array)
        return jax.jacfwd(lambda y: drift(0.0, y, system.params))(z), diffusion(0.0, z, system.params)

    def tangents(z, direction):
        return jax.jvp(coefficients, (z,), (direction,))[1]

    def rates(z, t):
        fields = lambda t: (drift(t, z, system.params), diffusion(t, z, system.params))  # noqa: E731
        return jax.jvp(fields, (t,), (jnp.ones_like(t),))[1]

    in_z = jax.vmap(jax.vmap(tangents, in_axes=(None, 0)), in_axes=(0, None))(points, directions)
    in_t = jax.vmap(jax.vmap(rates, in_axes=(None, 0)), in_axes=(0, None))(points, times)
    return in_z, in_t


@functools.lru_cache(maxsize=32)
def _dependence_program(static, treedef, shapes):
    """:func:`_dependence` compiled once per system structure (second-order autodiff of the vector fields: its
    tracing and compilation cost seconds on a spec scene)."""

    def run(dynamic):
        return _dependence(*eqx.combine(dynamic, static))

    avals = jax.tree_util.tree_unflatten(treedef, shapes)
    return jax.jit(run, compiler_options=FAST_COMPILE).lower(avals).compile()


def _structure(system: StochasticSystem, dtype) -> tuple[tuple[int, ...], bool]:
    """``(active, autonomous)``: the components on which ``∂a/∂Z`` or ``b`` depend (``a`` is affine in the others
    with constant coefficients, so Gaussian expectations need cubature over these only: none for a linear
    system), and whether ``a`` and ``b`` are free of ``t``.

    Found by differentiating ``(∂a/∂Z, b)`` along each component at random states, and ``(a, b)`` in ``t`` at random
    states and times, with every parameter leaf replaced by a random value in ``[0.5, 1.5]``: the structure, not the
    current (possibly traced) values, decides.  The program is compiled ahead and called on concrete arrays, so this
    holds inside an outer ``jit`` too.
    """
    rng = np.random.default_rng(0)
    d = system.state_dim
    params = jax.tree_util.tree_map(
        lambda p: (
            np.asarray(rng.uniform(0.5, 1.5, np.shape(p)), dtype)
            if jnp.issubdtype(jnp.result_type(p), jnp.floating)
            else p
        ),
        system.params,
    )
    probe = (
        eqx.tree_at(lambda s: s.params, system, params),
        rng.normal(size=(3, d)).astype(dtype),
        np.eye(d, dtype=dtype),
        rng.uniform(0.1, 10.0, size=3).astype(dtype),
    )
    dynamic, static = eqx.partition(probe, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    shapes = tuple(jax.ShapeDtypeStruct(np.shape(x), jnp.result_type(x)) for x in leaves)
    try:
        program = _dependence_program(static, treedef, shapes)
    except TypeError:  # a static part that cannot be hashed: compile for this call alone
        program = _dependence_program.__wrapped__(static, treedef, shapes)
    in_z, in_t = program(dynamic)
    found = np.zeros(d, bool)
    for t in jax.tree_util.tree_leaves(in_z):  # NaN counts as dependence
        found |= np.any(np.asarray(t).reshape(3, d, -1) != 0, axis=(0, 2))
    autonomous = not any(np.any(np.asarray(t) != 0) for t in jax.tree_util.tree_leaves(in_t))
    return tuple(int(i) for i in np.flatnonzero(found)), autonomous


def _cholesky(k, floor):
    """Lower Cholesky factor of a symmetric positive semi-definite ``k``, robust to rounding.

    A pivot at or below ``floor`` (a direction without variance; Runge–Kutta
    stages of a covariance that starts at 0 can even be slightly indefinite)
    gets a zero column below the diagonal and ``√floor`` on it.  Plain
    arithmetic, so differentiable everywhere.
    """
    n = k.shape[0]
    below = jnp.arange(n)
    cols = []
    for j in range(n):
        c = k[:, j] - sum((cols[i] * cols[i][j] for i in range(j)), jnp.zeros_like(k[:, j]))
        ok = c[j] > floor
        pivot = jnp.sqrt(jnp.where(ok, c[j], floor))
        cols.append(jnp.where(ok & (below > j), c / pivot, 0.0).at[j].set(pivot))
    return jnp.stack(cols, axis=1)


class GaussianClosure(eqx.Module):
    """Gaussian expectations of the drift, its Jacobian and the noise covariance of ``system``."""

    system: StochasticSystem
    intensity: Array  # ν per channel
    active: tuple[int, ...] = eqx.field(static=True)  # components ∂a/∂Z and b depend on
    nodes: Array
    weights: Array
    linear: bool = eqx.field(static=True, default=False)  # a affine in Z, b constant, neither depending on t

    def expectations(self, t, m, k):
        """``(E_N[a], E_N[∂a/∂Z], E_N[b diag(ν) bᵀ])`` under ``N(m, K)``."""
        idx = np.asarray(self.active, dtype=int)
        z = jnp.broadcast_to(m, (self.weights.shape[0], m.shape[0]))
        if idx.size:
            k_a = k[np.ix_(idx, idx)]
            tiny = jnp.finfo(m.dtype).eps
            chol = _cholesky(0.5 * (k_a + k_a.T), tiny * jnp.max(jnp.abs(jnp.diagonal(k_a))) + tiny**2)
            z = z.at[:, idx].add(self.nodes @ chol.T)
        params = self.system.params

        def drift_twice(y):
            a = self.system.drift(t, y, params)
            return a, a

        jac, drift = jax.vmap(jax.jacfwd(drift_twice, has_aux=True))(z)
        b = jax.vmap(lambda y: self.system.diffusion(t, y, params))(z)
        w = self.weights
        return (
            jnp.einsum("p,pi->i", w, drift),
            jnp.einsum("p,pij->ij", w, jac),
            jnp.einsum("p,pik,k,pjk->ij", w, b, self.intensity, b),
        )

    def rhs(self, t, state, args):
        m, k = state
        mean_a, jac, q = self.expectations(t, m, k)
        return mean_a, jac @ k + k @ jac.T + q


def gaussian_closure(system: StochasticSystem, dtype, order: int) -> GaussianClosure:
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem (e.g. a scene's .build()).")
    order = int(check_number("order", order, integer=True))
    if order < 1:
        raise ValueError(f"order={order}; must be ≥ 1 (Gauss–Hermite nodes per component).")
    if system.interpretation != "ito":
        system = system.converted("ito")
    params = validated(system.params)
    params = jax.tree_util.tree_map(
        lambda p: p.astype(dtype) if jnp.issubdtype(jnp.result_type(p), jnp.floating) else p, params
    )
    system = eqx.tree_at(lambda s: s.params, system, params)
    active, autonomous = _structure(system, dtype)
    nodes, weights = _hermite(order, len(active), dtype)
    intensity = driver_intensity(system.noise, system.noise_dim, dtype)
    return GaussianClosure(system, intensity, active, nodes, weights, linear=not active and autonomous)


def initial_moments(system, y0, cov0):
    d = system.state_dim
    y0 = system.state(y0)
    cov0 = jnp.zeros((d, d), y0.dtype) if cov0 is None else real_state("cov0", cov0).astype(y0.dtype)
    if cov0.shape != (d, d):
        raise ValueError(f"cov0 has shape {cov0.shape}; expected ({d}, {d}).")
    if is_concrete(cov0):
        c = np.asarray(cov0, np.float64)
        if (
            not np.all(np.isfinite(c))
            or not np.allclose(c, c.T)
            or np.min(np.linalg.eigvalsh(c)) < -1e-12 * max(1.0, np.abs(c).max())
        ):
            raise ValueError("cov0 must be a finite, symmetric, positive semi-definite matrix.")
    return y0, cov0


def _linear_flow(closure: GaussianClosure, m0, k0, t0: float, h: float, n: int):
    """Means and covariances after each of ``n`` intervals ``h`` of a linear autonomous system, exactly:
    ``m ← Φ m + g``, ``K ← Φ K Φᵀ + Q_h`` with ``Φ = e^{Ah}``, ``g = h φ₁(Ah) c`` and
    ``Q_h = ∫₀ʰ e^{As} Q e^{Aᵀs} ds`` (``a = c + A Z``, ``Q = b diag(ν) bᵀ``): the exponential step's
    :func:`~nhsde._solvers.linear_flow` (no exponential of ``−A``, which overflows where friction is strong)."""
    dtype, d = m0.dtype, m0.shape[0]
    c, a, q = closure.expectations(jnp.asarray(t0, dtype), jnp.zeros_like(m0), jnp.zeros_like(k0))
    flow = linear_flow(a, jnp.asarray(h, dtype), None, dtype)
    wide = flow.propagator.dtype
    phi = flow.propagator.astype(dtype)
    g = (flow.h_phi @ c.astype(wide)).astype(dtype)
    q_h = (flow.gram @ q.astype(wide).reshape(-1)).reshape(d, d).astype(dtype)
    q_h = 0.5 * (q_h + q_h.T)

    def interval(state, _):
        m, k = state
        k = phi @ k @ phi.T + q_h
        state = (phi @ m + g, 0.5 * (k + k.T))
        return state, state

    return jax.lax.scan(interval, (m0, k0), length=n)[1]


@eqx.filter_jit
def integrate_moments(closure: GaussianClosure, m0, k0, t0: float, t1: float, n_steps: int, n_save: int):
    """``(ts, means, covs)`` at ``n_save`` equally spaced times: exactly for a linear autonomous system
    (``closure.linear``, :func:`_linear_flow`), else with ``n_steps`` fixed Dopri8 steps."""
    dtype = m0.dtype
    ts = jnp.linspace(t0, t1, n_save, dtype=dtype)
    if closure.linear:
        ms, ks = _linear_flow(closure, m0, k0, t0, (t1 - t0) / (n_save - 1), n_save - 1)
        return ts, jnp.concatenate([m0[None], ms]), jnp.concatenate([k0[None], ks])
    solver = dfx.Dopri8(scan_kind="bounded")  # differentiable in forward and reverse mode (the default is reverse only)
    term = dfx.ODETerm(closure.rhs)
    dt = jnp.asarray((t1 - t0) / n_steps, dtype)
    per_save = n_steps // (n_save - 1)
    state0 = (m0, k0)
    solver_state = solver.init(term, jnp.asarray(t0, dtype), jnp.asarray(t0, dtype) + dt, state0, None)

    def interval(carry, j):
        def step(c, i):
            y, s = c
            t = t0 + (j * per_save + i).astype(dtype) * dt
            y1, _, _, s1, _ = solver.step(term, t, t + dt, y, None, s, False)
            return (y1, s1), None

        carry, _ = jax.lax.scan(step, carry, jnp.arange(per_save))
        return carry, carry[0]

    _, (ms, ks) = jax.lax.scan(interval, (state0, solver_state), jnp.arange(n_save - 1))
    return ts, jnp.concatenate([m0[None], ms]), jnp.concatenate([k0[None], ks])
