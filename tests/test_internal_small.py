"""The spec route's unrolled small factorisation (``nhsde.mechanics._small``) against LAPACK."""

import jax
import jax.numpy as jnp
import numpy as np

from nhsde.mechanics import _small as small


def test_the_unrolled_small_factorisation_is_lapacks_to_rounding():
    """The mass matrices and Schur complements are factorised entry by entry (fused into the step); the result is
    LAPACK's Cholesky and solve to 1e-12 in float64, under jit and grad too, for the sizes the shipped scenes have
    (1, 2 and 3) and the largest unrolled one (the loops are the same Python for every size)."""

    @jax.jit
    def both(a, b, d):
        # derivatives along symmetric directions (a mass matrix stays symmetric; the factorisation reads its lower
        # triangle, so the gradient with respect to a general matrix differs by where it puts the off-diagonal part)
        def routes(cholesky, solve):
            tangent = jax.jvp(lambda a: solve(a, b), (a,), (d,))[1]
            gradient = jax.grad(lambda a: jnp.sum(solve(a, b)))(a)
            return cholesky(a), solve(a, b), solve(a, b[:, 0]), tangent, jnp.sum(gradient * d)

        return routes(small.cholesky, small.spd_solve), routes(jnp.linalg.cholesky, jnp.linalg.solve)

    rng = np.random.default_rng(0)
    for n in (1, 2, 3, small.UNROLL_UP_TO):
        m = rng.standard_normal((n, n))
        a = jnp.asarray(m @ m.T + n * np.eye(n))
        b = jnp.asarray(rng.standard_normal((n, 3)))
        d = jnp.asarray(rng.standard_normal((n, n)))
        ours, lapack = both(a, b, d + d.T)
        tolerances = ((1e-12, 1e-12),) * 3 + ((1e-9, 1e-11), (1e-9, 0.0))  # the last: reverse mode, the same
        for got, want, (rtol, atol) in zip(ours, lapack, tolerances, strict=True):
            np.testing.assert_allclose(got, want, rtol=rtol, atol=atol)


def test_the_unrolled_products_are_matmul_to_rounding():
    """``small.matmul`` (sums of products, which fuse under vmap; no batched dot per path) is ``@`` to rounding."""
    rng = np.random.default_rng(1)
    for shapes in (((3, 4), (4, 2)), ((4,), (4, 2)), ((3, 4), (4,)), ((4,), (4,)), ((0, 3), (3,)), ((2, 1), (1, 3))):
        a, b = (jnp.asarray(rng.standard_normal(s)) for s in shapes)
        np.testing.assert_allclose(small.matmul(a, b), a @ b, rtol=1e-13, atol=1e-14)


def test_the_unrolled_general_solve_pivots_and_is_lapacks_to_rounding():
    """``small.solve`` (Gaussian elimination with partial pivoting, unrolled) against LAPACK's, with a zero leading
    entry (which needs the pivot), one or several right-hand sides, in both modes."""

    @jax.jit
    def both(a, b, d):
        def routes(solve):
            value, tangent = jax.jvp(lambda a: solve(a, b), (a,), (d,))
            return value, solve(a, b[:, 1]), tangent, jax.grad(lambda a: jnp.sum(solve(a, b)))(a)

        return routes(small.solve), routes(jnp.linalg.solve)

    rng = np.random.default_rng(2)
    for n in (1, 2, 3, small.UNROLL_UP_TO):  # the sizes of the shipped scenes' blocks, and the largest unrolled
        a = rng.standard_normal((n, n)) + n * np.eye(n)[::-1]  # dominant anti-diagonal: every column must pivot
        a[0, 0] = 0.0 if n > 1 else a[0, 0]
        ours, lapack = both(a, rng.standard_normal((n, 3)), rng.standard_normal((n, n)))
        for x, y in zip(ours, lapack):
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(y))))
    assert small.solve(jnp.zeros((0, 0)), jnp.zeros(0)).shape == (0,)
    batched = jax.jit(jax.vmap(small.solve)).lower(jnp.ones((4, 3, 3)), jnp.ones((4, 3))).as_text()
    assert "lapack" not in batched  # under vmap: plain arithmetic, no batched LAPACK kernel


def test_dependent_rows_are_found_without_an_svd():
    """``small.rank_deficient`` (Cholesky pivots of the Gram matrix): dependent rows, a zero row and a repeated row
    are found; independent rows, however differently scaled, are not."""
    check = jax.jit(jax.vmap(small.rank_deficient))
    rows = jnp.asarray(
        [
            [[1.0, 2.0, 0.0], [2.0, 4.0, 0.0]],  # parallel
            [[1.0, 0.0, 3.0], [0.0, 0.0, 0.0]],  # a zero row
            [[1.0, 2.0, 0.0], [0.0, 1e-3, 1.0]],  # independent, different scales
            [[1e6, 0.0, 0.0], [0.0, 1e-2, 0.0]],  # independent, far apart in scale
        ]
    )
    assert check(rows).tolist() == [True, True, False, False]
    assert "lapack" not in check.lower(rows).as_text()
