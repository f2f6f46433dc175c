"""Poincaré sections of rubber rolling on ``E = h``, ``g = g₀`` in Andoyer-like variables, S2 (1.17)–(1.18).

On ``M⁴ = {γ² = 1, (ω, γ) = 0}`` (S2 (1.16)):

    ω = (√(G² − L²) sin l, √(G² − L²) cos l, L),
    γ = (c cos g sin l + sin g cos l,  c cos g cos l − sin g sin l,  −√(1 − c²) cos g),   c = L/G,

so ``G = |ω|``, ``L = ω₃``, ``l`` is the longitude of ``ω`` and ``g`` the angle of
``γ`` about ``ω``.  The section ``g = g₀`` of the energy level ``E = h`` is drawn
in ``(l mod 2π, L/G)``, a point of the unit sphere.  Since ``γ`` depends on
``L/G`` only, an energy ``E = G² T(ω/G, γ) + U(γ)`` fixes ``G`` in closed form.
"""

from __future__ import annotations

from collections.abc import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from .._misc import cast_floats

__all__ = ["PoincareSection", "andoyer", "from_andoyer", "poincare_section"]


def from_andoyer(L, G, l, g):
    """The state ``(ω, γ)`` of S2 (1.17)."""
    c = L / G
    s = jnp.sqrt(jnp.maximum(1 - c**2, 0.0))
    omega = jnp.stack([G * s * jnp.sin(l), G * s * jnp.cos(l), L])
    gamma = jnp.stack(
        [
            c * jnp.cos(g) * jnp.sin(l) + jnp.sin(g) * jnp.cos(l),
            c * jnp.cos(g) * jnp.cos(l) - jnp.sin(g) * jnp.sin(l),
            -s * jnp.cos(g),
        ]
    )
    return jnp.concatenate([omega, gamma])


def _frame(y):
    """``(a, b)``: ``γ = cos g · a + sin g · b`` on ``M⁴``."""
    omega = y[:3]
    G = jnp.linalg.norm(omega)
    l = jnp.arctan2(omega[0], omega[1])
    c = omega[2] / G
    a = jnp.stack([c * jnp.sin(l), c * jnp.cos(l), -jnp.sqrt(jnp.maximum(1 - c**2, 0.0))])
    b = jnp.stack([jnp.cos(l), -jnp.sin(l), jnp.zeros_like(l)])
    return a, b


def andoyer(y):
    """``(L, G, l, g)`` of the state ``(ω, γ)``, S2 (1.17); ``l, g ∈ (−π, π]``.

    Arguments:
        y: a state whose first six components are ``(ω, γ)``.

    Returns:
        ``(L, G, l, g)``: ``L = ω₃``, ``G = |ω|`` and the two Andoyer angles; :func:`from_andoyer` inverts it.

    Examples:
        >>> from nhsde import analysis
        >>> y = analysis.from_andoyer(0.6, 1.0, 0.3, -1.2)
        >>> print([round(float(v), 6) for v in analysis.andoyer(y)])
        [0.6, 1.0, 0.3, -1.2]
    """
    omega, gamma = y[:3], y[3:6]
    a, b = _frame(y)
    return omega[2], jnp.linalg.norm(omega), jnp.arctan2(omega[0], omega[1]), jnp.arctan2(gamma @ b, gamma @ a)


class PoincareSection(eqx.Module):
    """Crossings of ``g = g₀`` with ``g`` increasing in forward time, for each initial point.

    ``l`` (in ``[0, 2π)``) and ``ratio = L/G`` have shape ``(n_points, n_crossings)``;
    ``states`` ``(n_points, n_crossings, 6)``; ``valid`` marks crossings found within
    ``max_time`` for initial points that lie on the energy level.
    """

    l: jax.Array
    ratio: jax.Array
    states: jax.Array
    valid: jax.Array


_SOLVERS = {"dopri8": dfx.Dopri8, "tsit5": dfx.Tsit5}


@eqx.filter_jit
def _section(vector_field, energy, params, points, h, g0, n_crossings, dt, max_steps, sign, solver_name):
    solver = _SOLVERS[solver_name]()
    term = dfx.ODETerm(lambda t, y, p: sign * vector_field(t, y, p))
    cg, sg = jnp.cos(g0), jnp.sin(g0)

    def crossing(y):
        """``(sign·sin(g − g₀), cos(g − g₀))``: the section is crossed where the first turns positive."""
        a, b = _frame(y)
        return sign * (jnp.dot(y[3:6], b) * cg - jnp.dot(y[3:6], a) * sg), jnp.dot(y[3:6], a) * cg + jnp.dot(
            y[3:6], b
        ) * sg

    def start(point):
        l, ratio = point[0], point[1]
        unit = from_andoyer(ratio, jnp.ones_like(ratio), l, g0)
        e0 = energy(unit.at[:3].set(0.0), params)
        e1 = energy(unit, params) - e0
        big = jnp.sqrt(jnp.maximum((h - e0) / e1, 0.0))
        ok = (e1 > 0) & (h > e0) & (jnp.abs(ratio) < 1)
        return unit.at[:3].multiply(big), ok

    def one(point):
        y0, ok = start(point)
        state0 = solver.init(term, 0.0, dt, y0, params)
        # start of the step of each crossing; refined on the step's dense output after the loop
        buf = jnp.full((n_crossings, y0.shape[0] + 1), jnp.nan, y0.dtype)

        def cond(carry):
            return ok & (carry[4] < n_crossings) & (carry[5] < max_steps)

        def body(carry):
            y, f0, t, state, count, step, buf = carry
            y1, _, _, state, _ = solver.step(term, t, t + dt, y, params, state, False)
            f1, front = crossing(y1)
            hit = (f0 < 0) & (f1 >= 0) & (front > 0)
            buf = buf.at[jnp.where(hit, count, n_crossings)].set(jnp.concatenate([t[None], y]), mode="drop")
            return y1, f1, t + dt, state, count + hit.astype(count.dtype), step + 1, buf

        zero = jnp.zeros((), y0.dtype)
        # y0 lies on the section by construction: its rounded crossing function (±1e-17) must not count it as the
        # first crossing, so the loop starts as if just past the section
        carry = (y0, jnp.ones((), y0.dtype), zero, state0, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), buf)
        buf = jax.lax.while_loop(cond, body, carry)[-1]
        return jax.vmap(refine)(buf[:, 0], buf[:, 1:])

    def refine(t, y):
        """Bisection for ``crossing = 0`` on the dense output of the step ``[t, t + dt]`` from ``y``."""
        dense = solver.step(term, t, t + dt, y, params, solver.init(term, t, t + dt, y, params), False)[2]
        interp = solver.interpolation_cls(t0=t, t1=t + dt, **dense)

        def bisect(_, bracket):
            lo, hi = bracket
            mid = 0.5 * (lo + hi)
            below = crossing(interp.evaluate(mid))[0] < 0
            return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

        lo, hi = jax.lax.fori_loop(0, 60, bisect, (t, t + dt))
        return jnp.where(jnp.isfinite(t), interp.evaluate(0.5 * (lo + hi)), jnp.nan)

    states = jax.vmap(one)(points)
    valid = jnp.all(jnp.isfinite(states), axis=-1)
    _, _, l, _ = jax.vmap(jax.vmap(andoyer))(jnp.where(valid[..., None], states, 1.0))
    ratio = states[..., 2] / jnp.linalg.norm(states[..., :3], axis=-1)
    return PoincareSection(l=jnp.mod(l, 2 * jnp.pi), ratio=ratio, states=states, valid=valid)


def poincare_section(
    vector_field: Callable,
    energy: Callable,
    params,
    points,
    *,
    h: float,
    g0: float,
    n_crossings: int,
    dt: float = 0.01,
    max_time: float = 1000.0,
    backward: bool = False,
    solver: str = "dopri8",
) -> PoincareSection:
    """The Poincaré map ``Φ_{h,g₀}`` of S2 (1.18) iterated from each of ``points``, vmapped.

    - ``points``: ``(n, 2)`` initial points ``(l, L/G)`` on the section; ``G`` follows
      from ``energy(y, params) = h`` (points off the energy level are invalid).
    - Fixed steps ``dt`` of ``solver`` (Dopri8: global error ``O(dt⁸)``); each
      crossing is located by bisection on the solver's dense output.
    - ``backward=True`` iterates the inverse map ``Φ⁻¹`` (integrates ``ẏ = −v``):
      its attractors are the repellers of ``Φ``.

    Arguments:
        vector_field: the rolling body's field ``v(t, y, params)`` on ``y = (ω, γ)`` (e.g. a scene's
            ``vector_field``).
        energy: ``energy(y, params)``, the first integral fixing the level ``E = h``.
        params: the field's parameters.
        points: ``(n, 2)`` initial points ``(l, L/G)`` on the section.
        h: the energy level.
        g0: the Andoyer angle ``g`` of the section.
        n_crossings: crossings recorded per point.
        dt: the fixed step.
        max_time: the longest integration per point.
        backward: iterate ``Φ⁻¹``.
        solver: ``"dopri8"`` or ``"tsit5"``.

    Returns:
        a :class:`PoincareSection` of Andoyer coordinates ``l``, ``ratio = L/G`` and states at each crossing,
        with ``valid`` flags.
    """
    if solver not in _SOLVERS:
        raise ValueError(f"solver={solver!r}; allowed: {', '.join(_SOLVERS)}.")
    if n_crossings < 1:
        raise ValueError(f"n_crossings={n_crossings}; must be ≥ 1.")
    if not dt > 0 or not max_time > dt:
        raise ValueError(f"dt={dt}, max_time={max_time}: need 0 < dt < max_time.")
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"points has shape {points.shape}; expected (n, 2) pairs (l, L/G).")
    dtype = points.dtype if jnp.issubdtype(points.dtype, jnp.floating) else jnp.result_type(float)
    points = points.astype(dtype)
    params = cast_floats(params, dtype)
    return _section(
        vector_field,
        energy,
        params,
        points,
        jnp.asarray(h, dtype),
        jnp.asarray(g0, dtype),
        int(n_crossings),
        jnp.asarray(dt, dtype),
        round(max_time / dt),
        jnp.asarray(-1.0 if backward else 1.0, dtype),
        solver,
    )
