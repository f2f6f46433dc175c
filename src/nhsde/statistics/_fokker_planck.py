"""The Fokker–Planck–Kolmogorov equation (S0 (2.2)) on a grid, for one- and two-dimensional systems.

For the Itô system ``dx = a dt + b dW`` (Wiener noise), ``D = bbᵀ``:

    ∂f/∂t = −∇·J,    J_i = (a_i − ½ Σ_j ∂_j D_ij) f − ½ Σ_j D_ij ∂_j f.

Finite volumes on a uniform grid of cells, no flux through the boundary (mass
is conserved).  Along each axis the face flux is ``ã f_face − ½ D ∂f`` with
the third-order upwind-biased face value ``f_face = 5/6 f_U + 1/3 f_D − 1/6 f_UU``
(``U`` upwind, ``D`` downwind; central next to the boundary) and central
differences for ``∂f`` and for the mixed terms ``D_ij`` (``i ≠ j``): second
order also along directions without noise, where the flow only advects.
The stationary density is the normalised null vector of the sparse operator;
transient densities come from Crank–Nicolson steps (the first step as two
backward-Euler half steps, which damp rough initial data).  A third route to
densities, independent of Monte Carlo and of the closed forms: coefficients
are evaluated with JAX on the grid once, the linear algebra is scipy's sparse LU.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._misc import check_number, check_steps
from .._system import StochasticSystem
from ._drift import StationaryMoments

__all__ = ["GridDensity", "fokker_planck", "stationary_fokker_planck"]


class GridDensity(eqx.Module):
    """A density on the cell centres ``axes`` of a uniform grid: ``values[..., i(, j)]``.

    Stationary: ``ts`` is ``None``; transient: ``values`` has a leading time axis.
    """

    axes: tuple[Float[Array, " n"], ...]
    values: Array
    ts: Float[Array, " t"] | None
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def cell_volume(self) -> float:
        return float(np.prod([float(a[1] - a[0]) for a in self.axes]))

    def _points(self):
        return jnp.stack(jnp.meshgrid(*self.axes, indexing="ij"), axis=-1)  # (*n, k)

    def mean(self) -> Array:
        k = len(self.axes)
        x = self._points()
        return jnp.einsum(f"...{'ij'[:k]},{'ij'[:k]}l->...l", self.values, x) * self.cell_volume

    def cov(self) -> Array:
        """Covariance of the grid density (each cell's mass at its centre)."""
        k = len(self.axes)
        x = self._points()
        second = jnp.einsum(f"...{'ij'[:k]},{'ij'[:k]}l,{'ij'[:k]}m->...lm", self.values, x, x) * self.cell_volume
        m = self.mean()
        return second - m[..., :, None] * m[..., None, :]

    def moments(self) -> StationaryMoments:
        """Mean and covariance as :class:`StationaryMoments` (stationary densities)."""
        if self.ts is not None:
            raise ValueError("moments() is for a stationary density; use mean() and cov() over time.")
        return StationaryMoments(self.mean(), self.cov(), self.names)

    def cell_probabilities(self, edges) -> Array:
        """Probability of the bins ``edges[i], edges[i+1]`` of a one-dimensional density (edges on cell faces)."""
        if len(self.axes) != 1:
            raise ValueError("cell_probabilities is for one-dimensional densities.")
        a = np.asarray(self.axes[0])
        h = a[1] - a[0]
        faces = np.concatenate([a - h / 2, a[-1:] + h / 2])
        idx = np.searchsorted(faces, np.asarray(edges) - 1e-9 * h)
        if not np.allclose(faces[np.clip(idx, 0, len(faces) - 1)], edges, atol=1e-9 * h):
            raise ValueError("edges must lie on cell faces of the grid.")
        cum = jnp.concatenate(
            [jnp.zeros(self.values.shape[:-1] + (1,), self.values.dtype), jnp.cumsum(self.values, -1) * h], -1
        )
        return cum[..., idx[1:]] - cum[..., idx[:-1]]


def _grid(system, bounds, n):
    if not isinstance(system, StochasticSystem):
        raise TypeError(f"system={type(system).__name__}; expected a StochasticSystem.")
    k = system.state_dim
    if k not in (1, 2):
        raise ValueError(
            f"the Fokker–Planck grid solver handles 1- and 2-dimensional systems; this one has {k} components "
            f"{system.layout.names} (reduce it, or use normal_approximation / simulate)."
        )
    if not system.noise.continuous:
        raise ValueError(
            f"the Fokker–Planck equation (S0 (2.2)) is for Wiener noise; this system is driven by "
            f"{type(system.noise).__name__} (its density obeys an integro-differential equation)."
        )
    bounds = tuple(tuple(float(v) for v in b) for b in np.atleast_2d(np.asarray(bounds, dtype=float)))
    n = tuple(int(v) for v in np.atleast_1d(n))
    if len(bounds) != k or len(n) != k:
        raise ValueError(f"bounds and n need one entry per component of {system.layout.names}; got {bounds}, {n}.")
    for (lo, hi), m in zip(bounds, n):
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise ValueError(f"bounds ({lo}, {hi}): need finite lower < upper.")
        if m < 3:
            raise ValueError(f"n={m}: need at least 3 cells per axis.")
    if system.interpretation != "ito":
        system = system.converted("ito")
    axes = tuple(np.linspace(lo + (hi - lo) / (2 * m), hi - (hi - lo) / (2 * m), m) for (lo, hi), m in zip(bounds, n))
    return system, axes


def _along(values, axis, k):
    """A 1-D array shaped to broadcast along ``axis`` of a ``k``-dimensional grid."""
    return np.reshape(values, [-1 if j == axis else 1 for j in range(k)])


def _operator(system: StochasticSystem, axes, t: float):
    """Sparse ``M`` with ``df/dt = M f`` on the flattened grid (C order)."""
    import scipy.sparse as sp  # scipy where a density is solved for: `import nhsde` leaves it

    k = len(axes)
    shape = tuple(len(a) for a in axes)
    hs = [float(a[1] - a[0]) for a in axes]
    params = system.params

    def d_fn(z):
        b = system.diffusion(t, z, params)
        return b @ b.T

    def coefficients(x):
        div_d = jnp.trace(jax.jacfwd(d_fn)(x), axis1=1, axis2=2)
        return system.drift(t, x, params) - 0.5 * div_d, d_fn(x)

    coefficients = jax.jit(jax.vmap(coefficients))
    index = np.arange(int(np.prod(shape))).reshape(shape)
    rows, cols, vals = [], [], []

    def add(r, c, v):
        rows.append(r.ravel())
        cols.append(c.ravel())
        vals.append(v.ravel())

    for ax in range(k):
        # faces between cell i and i+1 along `ax`
        face_axes = [a if j != ax else (a[:-1] + a[1:]) / 2 for j, a in enumerate(axes)]
        pts = np.stack(np.meshgrid(*face_axes, indexing="ij"), -1).reshape(-1, k)
        drift, diff = (np.asarray(v, np.float64) for v in coefficients(jnp.asarray(pts)))
        fshape = tuple(len(a) for a in face_axes)
        a_ax = drift[:, ax].reshape(fshape)
        d_ax = diff[:, ax, ax].reshape(fshape)
        h = hs[ax]
        m_ax = np.arange(shape[ax] - 1)  # face i lies between cells i and i + 1
        cells = [np.take(index, np.clip(m_ax + shift, 0, shape[ax] - 1), axis=ax) for shift in (-1, 0, 1, 2)]
        left, right = cells[1], cells[2]
        # advection: third-order upwind-biased face value (κ = 1/3), central next to the boundary
        pos = a_ax > 0
        inner_l = np.broadcast_to(_along(m_ax >= 1, ax, k), fshape)
        inner_r = np.broadcast_to(_along(m_ax + 2 <= shape[ax] - 1, ax, k), fshape)
        w = np.zeros((4,) + fshape)
        w[:, pos & inner_l] = np.array([-1 / 6, 5 / 6, 1 / 3, 0.0])[:, None]
        w[:, ~pos & inner_r] = np.array([0.0, 1 / 3, 5 / 6, -1 / 6])[:, None]
        w[:, (pos & ~inner_l) | (~pos & ~inner_r)] = np.array([0.0, 0.5, 0.5, 0.0])[:, None]
        # J = Σ_c (a w_c) f_c − (D/2h)(f_R − f_L): out of the left cell, into the right one (÷h)
        coef = a_ax * w
        coef[1] += d_ax / (2 * h)
        coef[2] -= d_ax / (2 * h)
        for c, col in zip(coef, cells):
            add(left, col, -c / h)
            add(right, col, c / h)
        for other in range(k):
            if other == ax:
                continue
            # −½ D_{ax,other} ∂_other f at the face: mean of the two cells' central differences (one-sided at edges)
            m_o = np.arange(shape[other])
            up_o, down_o = np.minimum(m_o + 1, shape[other] - 1), np.maximum(m_o - 1, 0)
            up = np.take(index, up_o, axis=other)
            down = np.take(index, down_o, axis=other)
            span = np.broadcast_to(_along(up_o - down_o, other, k), shape)
            d_mixed = diff[:, ax, other].reshape(fshape)
            for offset in (0, 1):  # the face's left and right cell
                sel = np.arange(shape[ax] - 1) + offset
                coef = -0.25 * d_mixed / (np.take(span, sel, axis=ax) * hs[other])
                up_c, down_c = np.take(up, sel, axis=ax), np.take(down, sel, axis=ax)
                add(left, up_c, -coef / h)
                add(left, down_c, coef / h)
                add(right, up_c, coef / h)
                add(right, down_c, -coef / h)
    size = index.size
    return sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))


def _check_autonomous(system, axes, t0):
    pts = jnp.asarray(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes)))
    f = jax.jit(
        jax.vmap(lambda t, x: (system.drift(t, x, system.params), system.diffusion(t, x, system.params)), (None, 0))
    )
    a0, b0 = f(t0, pts)
    a1, b1 = f(t0 + 1.0, pts)
    if not (np.allclose(a0, a1, rtol=1e-12, atol=0) and np.allclose(b0, b1, rtol=1e-12, atol=0)):
        raise ValueError("the Fokker–Planck grid solver needs time-independent drift and diffusion.")


def stationary_fokker_planck(system: StochasticSystem, bounds, n) -> GridDensity:
    """Stationary density of ``system`` (1 or 2 components) on the grid ``bounds`` × ``n`` cells.

    The normalised null vector of the finite-volume operator of ``∂f/∂t = −∇·J`` (S0 (2.2)).

    Arguments:
        system: an autonomous Wiener-driven system of one or two components.
        bounds: ``(lower, upper)`` per component, wide enough that the density vanishes at the edges.
        n: cells per component.

    Returns:
        a :class:`GridDensity` (``ts`` is ``None``) with ``mean()``, ``cov()`` and ``cell_probabilities``.

    Examples:
        The ball's velocity variance ``νδ²/(4ε) = 0.1276`` (S0 (3.1)), to the grid's accuracy:

        >>> import nhsde
        >>> system = nhsde.scenes.BallOnVibratingPlane(eps=1.0, nu=1.0, drift=False).build()
        >>> density = nhsde.statistics.stationary_fokker_planck(system, bounds=[(-1.5, 1.5)] * 2, n=[31, 31])
        >>> density.names, density.values.shape
        (('u_x', 'u_y'), (31, 31))
        >>> print(round(float(density.cov()[0, 0]), 3))
        0.128
    """
    import scipy.sparse.linalg as spla

    system, axes = _grid(system, bounds, n)
    _check_autonomous(system, axes, 0.0)
    m = _operator(system, axes, 0.0).tolil()
    vol = float(np.prod([a[1] - a[0] for a in axes]))
    m[0, :] = vol  # the equations are dependent (columns sum to 0): one is replaced by the normalisation
    rhs = np.zeros(m.shape[0])
    rhs[0] = 1.0
    f = spla.spsolve(m.tocsc(), rhs)
    shape = tuple(len(a) for a in axes)
    return GridDensity(tuple(jnp.asarray(a) for a in axes), jnp.asarray(f.reshape(shape)), None, system.layout.names)


def fokker_planck(
    system: StochasticSystem, initial: Callable, bounds, n, *, t1: float, dt: float, save_n: int = 2, t0: float = 0.0
) -> GridDensity:
    """Transient density from ``initial`` (a function of points ``(..., k)`` → density) at ``save_n`` times in
    ``[t0, t1]``.

    Crank–Nicolson with step ``dt`` (the first step as two backward-Euler half steps).

    Arguments:
        system: an autonomous Wiener-driven system of one or two components.
        initial: the initial density, a function of points ``(..., k)``.
        bounds: ``(lower, upper)`` per component.
        n: cells per component.
        t0, t1: the time interval.
        dt: the Crank–Nicolson step (divides ``t1 − t0``).
        save_n: equally spaced save times from ``t0`` to ``t1`` (``save_n − 1`` divides the steps).

    Returns:
        a :class:`GridDensity` with ``ts`` ``(save_n,)`` and ``values`` ``(save_n, *n)``.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    system, axes = _grid(system, bounds, n)
    t0, t1 = check_number("t0", t0), check_number("t1", t1)
    if t1 <= t0:
        raise ValueError(f"t1={t1} must be > t0={t0}.")
    n_steps = check_steps("dt", t1 - t0, check_number("dt", dt, positive=True))
    save_n = int(check_number("save_n", save_n, integer=True))
    if save_n < 2 or n_steps % (save_n - 1):
        raise ValueError(f"save_n={save_n}: save_n − 1 must be ≥ 1 and divide the {n_steps} steps.")
    _check_autonomous(system, axes, t0)
    m = _operator(system, axes, t0)
    h = (t1 - t0) / n_steps
    shape = tuple(len(a) for a in axes)
    size = int(np.prod(shape))  # cells: the order of M
    # backward Euler over h/2 and Crank–Nicolson over h share the matrix I − (h/2) M
    lu = spla.splu((sp.identity(size, format="csc") - (h / 2) * m).tocsc())
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    f = np.asarray(initial(jnp.asarray(pts)), np.float64).reshape(-1)
    if f.shape[0] != size or not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ValueError("initial must map grid points (..., k) to finite non-negative density values.")
    saved = [f]
    per_save = n_steps // (save_n - 1)
    for step in range(n_steps):
        f = lu.solve(lu.solve(f)) if step == 0 else lu.solve(f + (h / 2) * (m @ f))
        if (step + 1) % per_save == 0:
            saved.append(f)
    values = np.stack(saved).reshape((save_n,) + shape)
    ts = np.linspace(t0, t1, save_n)
    return GridDensity(tuple(jnp.asarray(a) for a in axes), jnp.asarray(values), jnp.asarray(ts), system.layout.names)
