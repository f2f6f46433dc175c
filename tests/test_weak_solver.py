"""PlatenWeak2, Platen's explicit order-2.0 weak scheme (KP (15.1.3)), and its increments.

Weak order is measured exactly, without Monte Carlo: for a linear SDE the step is
linear in the state, so the scheme's moments follow from a recursion over the
finitely many values of the discrete increments (3^m three-point values ×
2^{m(m−1)/2} two-point values), computed with the solver's own ``step``.  Monte
Carlo through ``simulate`` is then checked against those exact scheme moments
within its standard error: the driver draws the law the recursion assumes.
"""

import dataclasses
import itertools
import math

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import nhsde
from nhsde import StateLayout, StochasticSystem
from nhsde.noise import CompoundPoisson, NormalJumps
from nhsde.scenes import BallOnVibratingPlane, ball_covariances

# dX = A X dt + Σ_j B_j X dW^j (Itô), B_1 B_2 ≠ B_2 B_1: non-commutative noise.
A = np.array([[-0.5, 1.0], [-1.0, -0.3]])
B = 2.5 * np.array([[[0.4, 0.3], [0.0, 0.2]], [[0.1, 0.0], [0.5, 0.3]]])
X0 = np.array([1.0, 0.5])


def linear_system():
    return StochasticSystem(
        drift_fn=lambda t, y, p: p["A"] @ y,
        diffusion_fn=lambda t, y, p: jnp.einsum("jab,b->aj", p["B"], y),
        params={"A": jnp.asarray(A), "B": jnp.asarray(B)},
        layout=StateLayout(("x1", "x2"), ("independent_coordinate", "independent_coordinate")),
        noise_dim=2,
    )


def linear_exact(t):
    """E X(t) = e^{At} X0; vec E[X Xᵀ](t) = exp(t (I⊗A + A⊗I + Σ_j B_j⊗B_j)) vec(X0 X0ᵀ)."""
    generator = np.kron(np.eye(2), A) + np.kron(A, np.eye(2)) + sum(np.kron(b, b) for b in B)
    second = scipy.linalg.expm(t * generator) @ np.kron(X0, X0)
    return scipy.linalg.expm(t * A) @ X0, second.reshape(2, 2)


class Fixed(dfx.AbstractBrownianPath):
    """A path that yields one given increment over any step."""

    increment: nhsde.WeakIncrement
    levy_area = nhsde.ThreePointIncrement

    @property
    def t0(self):
        return -jnp.inf

    @property
    def t1(self):
        return jnp.inf

    def evaluate(self, t0, t1=None, left=True, use_levy=False):
        return self.increment if use_levy else self.increment.W


def outcomes(h, m):
    """Every value of (ΔŴ, V) with its probability: three-point ΔŴ^j, two-point V_{rj} (r > j)."""
    s = math.sqrt(3 * h)
    pairs = [(r, j) for r in range(m) for j in range(r)]
    ws, vs, ps = [], [], []
    for w in itertools.product([(-s, 1 / 6), (0.0, 2 / 3), (s, 1 / 6)], repeat=m):
        for signs in itertools.product([-1.0, 1.0], repeat=len(pairs)):
            v = -h * np.eye(m)
            for (r, j), sign in zip(pairs, signs):
                v[r, j], v[j, r] = sign * h, -sign * h
            ws.append([x for x, _ in w])
            vs.append(v)
            ps.append(np.prod([p for _, p in w]) * 0.5 ** len(pairs))
    return np.array(ws), np.array(vs), np.array(ps)


def scheme_moments(system, x0, h, t1):
    """Exact E X_n and E[X_n X_nᵀ] of PlatenWeak2 on a system whose drift and diffusion are affine in the state."""
    d, m = system.state_dim, system.noise_dim
    ws, vs, ps = outcomes(h, m)
    solver = nhsde.PlatenWeak2()

    def step(w, v, y):
        inc = nhsde.ThreePointIncrement(dt=jnp.float64(h), W=w, V=v)
        terms = dfx.MultiTerm(dfx.ODETerm(system.drift), dfx.ControlTerm(system.diffusion, Fixed(inc)))
        return solver.step(terms, 0.0, h, y, system.params, None, False)[0]

    basis = jnp.concatenate([jnp.zeros((1, d)), jnp.eye(d)])
    images = jax.jit(jax.vmap(jax.vmap(step, (None, None, 0)), (0, 0, None)))(ws, vs, basis)  # (outcome, 1 + d, d)
    shift = np.asarray(images[:, 0])
    maps = np.zeros((len(ps), d + 1, d + 1))  # the affine step on (y, 1)
    maps[:, :d, :d] = np.swapaxes(np.asarray(images[:, 1:]) - shift[:, None], 1, 2)
    maps[:, :d, d] = shift
    maps[:, d, d] = 1.0
    first = np.einsum("o,oab->ab", ps, maps)
    second = np.einsum("o,oab,ocd->acbd", ps, maps, maps).reshape((d + 1) ** 2, (d + 1) ** 2)
    y = np.append(x0, 1.0)
    n = round(t1 / h)
    mean = np.linalg.matrix_power(first, n) @ y
    moment = (np.linalg.matrix_power(second, n) @ np.kron(y, y)).reshape(d + 1, d + 1)
    return mean[:d], moment[:d, :d]


def slope(hs, errors):
    return np.polyfit(np.log(hs), np.log(errors), 1)[0]


def sciml_non_commutative():
    """The 2-D non-commutative test SDE of SciML's weak-convergence suite (StochasticDiffEq.jl, DRI1 tests):
    X(0) = (1, 1), E[X₁(t)²] = e^{−t} (the X₁ row alone gives d E[X₁²] = (−273/256 + 1/16 + 1/256) E[X₁²] dt)."""
    s2 = math.sqrt(2)
    drift = np.array([[-273 / 512, 0.0], [-1 / 160, 785 / 512 - s2 / 8]])
    # diffusion column j is B_j X
    b1 = np.array([[1 / 4, 0.0], [(1 - 2 * s2) / 4, 0.0]])
    b2 = np.array([[1 / 16, 0.0], [1 / 10, 1 / 16]])
    return drift, np.stack([b1, b2]), np.array([1.0, 1.0])


def gbm():
    """Geometric Brownian motion dX = μX dt + σX dW, μ = 1.5, σ = 0.6, X(0) = 0.5: E[X(t)²] = X0² e^{(2μ+σ²)t}."""
    return np.array([[1.5]]), np.array([[[0.6]]]), np.array([0.5])


def affine_system(drift, diffusions):
    d, m = drift.shape[0], diffusions.shape[0]
    return StochasticSystem(
        drift_fn=lambda t, y, p: p["A"] @ y,
        diffusion_fn=lambda t, y, p: jnp.einsum("jab,b->aj", p["B"], y),
        params={"A": jnp.asarray(drift), "B": jnp.asarray(diffusions)},
        layout=StateLayout(tuple(f"x{i}" for i in range(d)), ("independent_coordinate",) * d),
        noise_dim=m,
    )


def euler_second_moment(drift, diffusions, x0, h, t1):
    """Exact E[X_n X_nᵀ] of Euler–Maruyama on dX = AX dt + Σ_j B_j X dW^j: M ← (I+Ah) M (I+Ah)ᵀ + h Σ_j B_j M B_jᵀ."""
    step = np.eye(len(x0)) + drift * h
    moment = np.outer(x0, x0)
    for _ in range(round(t1 / h)):
        moment = step @ moment @ step.T + h * sum(b @ moment @ b.T for b in diffusions)
    return moment


@pytest.mark.parametrize(
    "problem, t1, exact",
    [(sciml_non_commutative, 3.0, lambda t: math.exp(-t)), (gbm, 1.0, lambda t: 0.25 * math.exp(3.36 * t))],
    ids=["sciml-non-commutative", "gbm"],
)
def test_weak_order_two_and_euler_order_one_on_published_problems(problem, t1, exact):
    """Bias of E[X₁(t1)²] against the step, computed exactly (no Monte-Carlo error: the schemes' moments follow
    from recursions over the discrete increments, module docstring): slope 2.0 ± 0.25 for PlatenWeak2, 1.0 ± 0.25
    for Euler–Maruyama on the same problem."""
    drift, diffusions, x0 = problem()
    if len(diffusions) > 1:
        assert np.abs(diffusions[0] @ diffusions[1] - diffusions[1] @ diffusions[0]).max() > 0.02  # non-commutative
    system = affine_system(drift, diffusions)
    hs = [2.0**-k for k in (3, 4, 5)]
    weak2 = [abs(scheme_moments(system, x0, h, t1)[1][0, 0] - exact(t1)) for h in hs]
    euler = [abs(euler_second_moment(drift, diffusions, x0, h, t1)[0, 0] - exact(t1)) for h in hs]
    assert abs(slope(hs, weak2) - 2) <= 0.25, weak2
    assert abs(slope(hs, euler) - 1) <= 0.25, euler


def test_exact_weak_order_two_with_non_commutative_noise():
    """Every first and second moment of a 2-D system with strongly non-commutative noise converges at order 2."""
    assert np.abs(B[0] @ B[1] - B[1] @ B[0]).max() > 0.1
    system = linear_system()
    mean, second = linear_exact(1.0)
    hs = [2.0**-k for k in (3, 4, 5)]
    moments = [scheme_moments(system, X0, h, 1.0) for h in hs]
    mean_err = [np.abs(m - mean).max() for m, _ in moments]
    second_err = [np.abs(s - second).max() for _, s in moments]
    assert abs(slope(hs, mean_err) - 2) < 0.15, mean_err
    assert abs(slope(hs, second_err) - 2) < 0.15, second_err


def test_exact_weak_order_two_on_the_ball():
    ball = BallOnVibratingPlane(eps=1.0, nu=1.0)
    system = ball.build()
    exact = float(ball_covariances(jnp.float64(2.0), 1.0, 1.0, 1 / 1.4)[0])
    hs = [2.0**-k for k in (3, 4, 5)]
    errors = []
    for h in hs:
        mean, moment = scheme_moments(system, np.zeros(4), h, 2.0)
        errors.append(abs(moment[0, 0] - mean[0] ** 2 - exact))
    assert abs(slope(hs, errors) - 2) < 0.15, errors


@pytest.mark.parametrize("h", [0.25, 0.125])
def test_monte_carlo_draws_the_law_of_the_scheme(h):
    """simulate's mean and covariance are the exact scheme moments within 4 standard errors."""
    system = linear_system()
    save = nhsde.Save(n=2)
    ens = nhsde.simulate(system, X0, jax.random.key(5), n_paths=2**16, t1=1.0, dt=h, solver="weak2", save=save)
    scheme_mean, scheme_second = scheme_moments(system, X0, h, 1.0)
    mean, cov, mean_se, cov_se = (np.asarray(a[-1]) for a in (ens.mean, ens.cov, ens.mean_se, ens.cov_se))
    scheme_cov = scheme_second - np.outer(scheme_mean, scheme_mean)
    assert np.all(np.abs(mean - scheme_mean) <= 4 * mean_se), (mean, scheme_mean, mean_se)
    assert np.all(np.abs(cov - scheme_cov) <= 4 * cov_se), (cov, scheme_cov, cov_se)


def test_monte_carlo_resolves_the_weak_error_on_the_ball():
    """At h = 1/2 the ball's K_xx(2) is off the exact value by > 4 SE, and by the scheme's exact error within 4 SE."""
    ball = BallOnVibratingPlane(eps=1.0, nu=1.0)
    system, h = ball.build(), 0.5
    save = nhsde.Save(names=("x",), n=2)
    y0, key = jnp.zeros(4), jax.random.key(2)
    ens = nhsde.simulate(system, y0, key, n_paths=2**16, t1=2.0, dt=h, solver="weak2", save=save)
    k, se = float(ens.cov[-1, 0, 0]), float(ens.cov_se[-1, 0, 0])
    mean, moment = scheme_moments(system, np.zeros(4), h, 2.0)
    exact = float(ball_covariances(jnp.float64(2.0), 1.0, 1.0, 1 / 1.4)[0])
    assert abs(k - exact) > 4 * se
    assert abs(k - (moment[0, 0] - mean[0] ** 2)) <= 4 * se


def test_three_point_and_two_point_laws():
    h, m, blocks = 0.01, 3, 512
    draws = jax.vmap(lambda k: nhsde.ThreePointIncrement.block_draw(jax.random.key(0), k, jnp.float64(h), (64, m), 1))(
        jnp.arange(blocks, dtype=jnp.int32)
    )
    w, v = np.asarray(draws.W).ravel(), np.asarray(draws.V).reshape(-1, m, m)
    n = w.size
    s = math.sqrt(3 * h)
    assert np.all(np.isclose(np.abs(w), s) | (w == 0))
    for value, p in ((s, 1 / 6), (0.0, 2 / 3), (-s, 1 / 6)):
        assert abs(np.mean(np.isclose(w, value)) - p) <= 4 * math.sqrt(p * (1 - p) / n)
    np.testing.assert_array_equal(v, -np.swapaxes(v, 1, 2) - 2 * h * np.eye(m))
    below = v[:, 1, 0]
    assert np.all(np.isclose(np.abs(below), h))
    assert abs(np.mean(below > 0) - 0.5) <= 4 * 0.5 / math.sqrt(below.size)


def test_gaussian_increments_share_one_path_between_steps():
    """On dX = dW, X(t1) is W(t1) at every step on one Brownian path: the coarse step sums the fine increments."""
    system = StochasticSystem(
        drift_fn=lambda t, y, p: jnp.zeros_like(y),
        diffusion_fn=lambda t, y, p: jnp.eye(2, dtype=y.dtype),
        params={},
        layout=StateLayout(("a", "b"), ("independent_coordinate", "independent_coordinate")),
        noise_dim=2,
        additive_noise=True,
    )

    def final(dt):
        steps = nhsde.FixedSteps(dt, brownian_dt=0.125)
        save = nhsde.Save(n=2, paths=True)
        solver = nhsde.PlatenWeak2(increments="gaussian")
        ens = nhsde.simulate(
            system, jnp.zeros(2), jax.random.key(3), n_paths=4096, t1=1.0, steps=steps, solver=solver, save=save
        )
        return np.asarray(ens.paths[:, -1])

    coarse, fine = final(0.5), final(0.125)
    np.testing.assert_allclose(coarse, fine, rtol=0, atol=1e-13)
    z = fine.ravel()
    assert abs(np.mean(z)) <= 4 / np.sqrt(z.size) and abs(np.var(z) - 1) <= 4 * np.sqrt(2 / z.size)


def test_bitwise_independent_of_the_chunking():
    system = linear_system()

    def run(chunk):
        return nhsde.simulate(
            system,
            X0,
            jax.random.key(1),
            n_paths=256,
            t1=1.0,
            dt=0.125,
            solver="weak2",
            save=nhsde.Save(n=3, paths=True),
            batching=nhsde.Batching(chunk_size=chunk),
        )

    a, b = run(64), run(256)
    np.testing.assert_array_equal(np.asarray(a.paths), np.asarray(b.paths))
    np.testing.assert_array_equal(np.asarray(a.cov), np.asarray(b.cov))


def test_plain_diffrax_solve_with_a_path_that_yields_the_increments():
    system = linear_system()
    inc = nhsde.ThreePointIncrement(
        dt=jnp.float64(0.25), W=jnp.array([0.5 * 3**0.5, 0.0]), V=jnp.array([[-0.25, 0.25], [-0.25, -0.25]])
    )
    terms = dfx.MultiTerm(dfx.ODETerm(system.drift), dfx.ControlTerm(system.diffusion, Fixed(inc)))
    sol = dfx.diffeqsolve(terms, nhsde.PlatenWeak2(), 0.0, 1.0, 0.25, jnp.asarray(X0), system.params)
    y = jnp.asarray(X0)
    for k in range(4):
        y = nhsde.PlatenWeak2().step(terms, 0.25 * k, 0.25 * (k + 1), y, system.params, None, False)[0]
    np.testing.assert_allclose(np.asarray(sol.ys[-1]), np.asarray(y), rtol=1e-12)


def test_bad_input_raises_naming_the_argument():
    with pytest.raises(ValueError, match="increments="):
        nhsde.PlatenWeak2(increments="normal")
    ball = BallOnVibratingPlane().build()
    jumps = dataclasses.replace(ball, noise=CompoundPoisson(law=NormalJumps(), intensity=1.0))
    with pytest.raises(ValueError, match="solver='weak2'"):
        nhsde.simulate(jumps, jnp.zeros(4), jax.random.key(0), n_paths=64, t1=1.0, dt=0.5, solver="weak2")
