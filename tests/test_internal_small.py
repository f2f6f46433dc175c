"""The spec route's unrolled small factorisation (``nhsde.mechanics._small``) against LAPACK."""

import jax
import jax.numpy as jnp
import numpy as np

from nhsde.mechanics import _small as small


def test_the_unrolled_small_factorisation_is_lapacks_to_rounding():
    """The mass matrices and Schur complements are factorised entry by entry (fused into the step); the result is
    LAPACK's Cholesky and solve to 1e-12 in float64, for every size a scene has, under jit and grad too."""
    rng = np.random.default_rng(0)
    for n in range(1, small.UNROLL_UP_TO + 1):
        m = rng.standard_normal((n, n))
        a = jnp.asarray(m @ m.T + n * np.eye(n))
        b = jnp.asarray(rng.standard_normal((n, 3)))
        np.testing.assert_allclose(small.cholesky(a), jnp.linalg.cholesky(a), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(jax.jit(small.spd_solve)(a, b), jnp.linalg.solve(a, b), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(small.spd_solve(a, b[:, 0]), jnp.linalg.solve(a, b[:, 0]), rtol=1e-12, atol=1e-12)
        # derivatives along symmetric directions (a mass matrix stays symmetric; the factorisation reads its lower
        # triangle, so the gradient with respect to a general matrix differs by where it puts the off-diagonal part)
        d = jnp.asarray(rng.standard_normal((n, n)))
        d = d + d.T
        ours = jax.jvp(lambda a: small.spd_solve(a, b), (a,), (d,))[1]
        np.testing.assert_allclose(
            ours, jax.jvp(lambda a: jnp.linalg.solve(a, b), (a,), (d,))[1], rtol=1e-9, atol=1e-11
        )
        g = jax.grad(lambda a: jnp.sum(small.spd_solve(a, b)))(a)
        lapack = jax.grad(lambda a: jnp.sum(jnp.linalg.solve(a, b)))(a)
        np.testing.assert_allclose(jnp.sum(g * d), jnp.sum(lapack * d), rtol=1e-9)  # reverse mode, the same


def test_the_unrolled_products_are_matmul_to_rounding():
    """``small.matmul`` (sums of products, which fuse under vmap; no batched dot per path) is ``@`` to rounding."""
    rng = np.random.default_rng(1)
    for shapes in (((3, 4), (4, 2)), ((4,), (4, 2)), ((3, 4), (4,)), ((4,), (4,)), ((0, 3), (3,)), ((2, 1), (1, 3))):
        a, b = (jnp.asarray(rng.standard_normal(s)) for s in shapes)
        np.testing.assert_allclose(small.matmul(a, b), a @ b, rtol=1e-13, atol=1e-14)
