"""Internals of quasi-Monte Carlo: the Sobol' generator against SciPy, the scrambling's nets, and the Brownian
bridge driver's increments."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import qmc

from nhsde.statistics._qmc import (
    MAX_DIMENSION,
    ScrambledSobol,
    _direction_numbers,
    scrambled_sobol,
    sobol_points,
    stacked_scramblings,
)


def test_unscrambled_points_are_scipys():
    # SciPy draws in Gray-code order: its point i is the direct-order point i ^ (i >> 1)
    d, n = 7, 64
    v = jnp.asarray(_direction_numbers(d))
    i = np.arange(n)
    x = sobol_points(v, jnp.zeros(d, jnp.uint32), jnp.asarray(i ^ (i >> 1), jnp.uint32), jnp.arange(d))
    reference = qmc.Sobol(d, scramble=False, bits=32).random(n) * 2.0**32
    np.testing.assert_array_equal(np.asarray(x, np.float64), reference)


def test_direction_numbers_are_scipys_in_every_dimension():
    """Joe & Kuo's recurrence over SciPy's table, without importing ``scipy.stats``: every one of the 21201
    dimensions' 32 direction numbers equals SciPy's own, and a prefix of them is the same table's prefix."""
    v = _direction_numbers(MAX_DIMENSION)
    reference = np.asarray(qmc.Sobol(MAX_DIMENSION, scramble=False, bits=32)._sv, np.uint32)
    np.testing.assert_array_equal(v, reference)
    np.testing.assert_array_equal(_direction_numbers(3), reference[:3])


def test_scrambled_points_stratify_every_dimension():
    # LMS + digital shift keeps the (0, k, 1)-net of each coordinate: one point per interval [i/N, (i+1)/N)
    d, k = 40, 10
    v, shift = scrambled_sobol(jax.random.key(5), d)
    x = np.asarray(sobol_points(v, shift, jnp.arange(2**k, dtype=jnp.uint32), jnp.arange(d)))
    for j in range(d):
        assert len(np.unique(x[:, j] >> (32 - k))) == 2**k, j
    # and the scrambling changes the points
    unscrambled = sobol_points(
        jnp.asarray(_direction_numbers(d)), jnp.zeros(d, jnp.uint32), jnp.arange(4), jnp.arange(d)
    )
    assert not np.array_equal(np.asarray(unscrambled), x[:4])


def test_the_extreme_points_give_finite_normals_in_either_precision():
    """The points ``x = 0`` and ``x = 2^32 − 1`` (a scrambled coordinate reaches them once in 2^32 draws) map to
    ``u`` strictly inside (0, 1) and to finite, opposite normals in float32 and float64.  In float32 with the top 24
    bits, ``2^24 − 1 + 1/2`` rounded to ``2^24``: ``u = 1``, an infinite increment, and a failed path (found as
    one failed path in 16 × 1024 on the sleigh, key 2, float32)."""
    n_base, m = 4, 1
    v = jnp.zeros((1, n_base * m, 32), jnp.uint32)
    lanes = jnp.arange(2, dtype=jnp.uint32)
    for dtype, top in ((jnp.float32, 1 - 2.0**-24), (jnp.float64, 1 - 2.0**-33)):
        z = []
        for fill in (0, 2**32 - 1):
            shift = jnp.full((1, n_base * m), fill, jnp.uint32)
            driver = ScrambledSobol(v=v, shift=shift, log_base=jnp.int32(2), channels=m)
            z.append(np.asarray(driver._normals(jnp.int32(0), jnp.uint32(0), lanes, jnp.int32(0), dtype)))
        low, high = z
        assert np.all(np.isfinite(low)) and np.all(np.isfinite(high)), dtype
        np.testing.assert_allclose(high, -low, rtol=1e-6)
        assert float(high.max()) > 4.5 and float(high.max()) < 6.5, (dtype, float(high.max()), top)


def test_increments_have_the_wiener_law_and_sum_to_the_endpoint():
    n_base, m, blocks = 16, 2, 64  # 4096 paths
    v, shift = stacked_scramblings(jax.random.key(2), 2, n_base * m)  # two scramblings of 2048 points
    driver = ScrambledSobol(v=v, shift=shift, log_base=jnp.int32(4), channels=m)
    dt = jnp.float64(0.05)

    def increments(substeps):
        def one(block, k):
            return driver.block_increment(None, block, k, dt, (m,), substeps, dfx.BrownianIncrement)

        steps = jnp.arange(n_base // substeps, dtype=jnp.int32)
        w = jax.vmap(jax.vmap(one, (None, 0)), (0, None))(jnp.arange(blocks, dtype=jnp.int32), steps)
        return np.asarray(w).transpose(0, 2, 1, 3).reshape(blocks * 64, len(steps), m)

    w = increments(1)
    n = w.shape[0]
    # tolerances of independent samples (the Sobol' points do better)
    np.testing.assert_array_less(np.abs(w.mean(0)), 4 * np.sqrt(dt / n))
    np.testing.assert_array_less(np.abs(w.var(0) / dt - 1), 4 * np.sqrt(2 / n))
    # W(T), the root of the bridge (one step of all n_base base steps): the increments telescope to it
    endpoint = increments(n_base)[:, 0]
    np.testing.assert_allclose(w.sum(1), endpoint, rtol=0, atol=1e-13)
    np.testing.assert_array_less(np.abs(endpoint.var(0) / (n_base * dt) - 1), 4 * np.sqrt(2 / n))
    # a step of two base steps is their sum: brownian_dt works on the same path
    np.testing.assert_allclose(increments(2), w[:, 0::2] + w[:, 1::2], rtol=0, atol=1e-14)
