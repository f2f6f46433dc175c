"""What the estimators accept and refuse: path counts below four, targets finer than the precision resolves, and
quasi-Monte Carlo under ``jit``, ``grad`` and ``vmap`` (as plain and multilevel Monte Carlo)."""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane
from nhsde.statistics import (
    Mean,
    PlainMonteCarlo,
    control_variate,
    extrapolate,
    multilevel_monte_carlo,
    quasi_monte_carlo,
    to_accuracy,
)

BALL = BallOnVibratingPlane(eps=1.0, nu=1.0)
Y0 = jnp.zeros(4)
KEY = jax.random.key(0)
SPAN: dict[str, Any] = dict(t1=0.5, dt=0.0625)


@pytest.mark.parametrize(
    "n_paths, message",
    [
        ((1,), r"n_paths=\(1,\): level 0 has 1 path; each level needs ≥ 4"),
        ((256, 1), r"n_paths=\(256, 1\): level 1 has 1 path; each level needs ≥ 4"),
        ((3, 256), r"n_paths=\(3, 256\): level 0 has 3 paths; each level needs ≥ 4"),
        ((0,), r"n_paths=\(0,\): level 0 has 0 paths; each level needs ≥ 4"),
    ],
)
def test_multilevel_refuses_fewer_than_four_paths_on_any_level(n_paths, message):
    """One path on a level gave a nan covariance with standard error 0; two or three were taken though ``simulate``
    needs four (a covariance and its standard error)."""
    with pytest.raises(ValueError, match=message + r" \(a covariance and its standard error need 4\)"):
        multilevel_monte_carlo(BALL.build(), Y0, KEY, n_paths=n_paths, statistic=("cov", "x", "x"), **SPAN)
    with pytest.raises(TypeError, match=r"n_paths=\(\); expected one count per level"):
        multilevel_monte_carlo(BALL.build(), Y0, KEY, n_paths=(), statistic=("cov", "x", "x"), **SPAN)


@pytest.mark.parametrize("estimator", [extrapolate, control_variate], ids=lambda f: f.__name__)
@pytest.mark.parametrize("n_paths", [0, 2, 3, -5])
def test_single_count_estimators_refuse_fewer_than_four_paths_with_simulates_message(estimator, n_paths):
    """``extrapolate(n_paths=0)`` raised numpy's "need at least one array to concatenate"; 2 and 3 ran."""
    with pytest.raises(ValueError, match=rf"^n_paths={n_paths}; must be ≥ 4 \(a covariance and its standard error"):
        estimator(BALL.build(), Y0, KEY, n_paths=n_paths, **SPAN)


def test_four_paths_are_enough_for_every_estimator():
    for estimate in (
        multilevel_monte_carlo(BALL.build(), Y0, KEY, n_paths=(4, 4), statistic=("cov", "x", "x"), **SPAN),
        extrapolate(BALL.build(), Y0, KEY, n_paths=4, **SPAN),
    ):
        assert np.all(np.isfinite(np.asarray(estimate.cov))) and float(estimate.cov_se[-1, 0, 0]) > 0


def drifting(dtype):
    """``dx = 10⁻⁸ dt + 10⁻¹² dW`` from 1: in float32 every increment is below half an ulp of 1 (6e-8), so every path
    stays at exactly 1 (variance 0) while ``E x(1) = 1 + 10⁻⁸``."""
    return nhsde.StochasticSystem(
        drift_fn=lambda t, y, p: p[0] * jnp.ones_like(y),
        diffusion_fn=lambda t, y, p: p[1] * jnp.ones((1, 1), y.dtype),
        params=jnp.array([1e-8, 1e-12], dtype),
        layout=nhsde.StateLayout(("x",), ("independent_coordinate",)),
        noise_dim=1,
        additive_noise=True,
    )


ONE_ESTIMATOR: dict[str, Any] = dict(
    t1=1.0, statistic=Mean("x"), estimators=(PlainMonteCarlo("euler"),), pilot_paths=256
)


def test_a_target_finer_than_float32_resolves_is_refused_and_float64_meets_it():
    """``to_accuracy(rmse=1e-12)`` in float32 answered 1 ± 0 (estimated rmse 0) for a true 1 + 10⁻⁸: a target below
    the statistic's change when every path's value moves one ulp (here eps·|1| = 1.19e-7) is refused, naming the
    target, the floor and the fix; float64 resolves it and meets it."""
    with pytest.raises(ValueError, match=r"^rmse=1e-12 is below 1\.19e-07, what float32 resolves of mean x .*float64"):
        to_accuracy(drifting(jnp.float32), jnp.ones(1, jnp.float32), KEY, rmse=1e-12, **ONE_ESTIMATOR)
    with pytest.raises(ValueError, match=r"^rmse=1e-08 is below 1\.19e-07"):  # the true error itself: not resolved
        to_accuracy(drifting(jnp.float32), jnp.ones(1, jnp.float32), KEY, rmse=1e-8, **ONE_ESTIMATOR)
    r = to_accuracy(drifting(jnp.float64), jnp.ones(1, jnp.float64), KEY, rmse=1e-12, **ONE_ESTIMATOR)
    value, se = r.value()
    assert abs(value - (1 + 1e-8)) <= 3 * r.rmse and r.estimated_rmse <= r.rmse, r.report()
    assert 0 < r.pilot[0].resolution < 1e-15


def test_a_target_the_precision_resolves_is_met_in_float32():
    """Above the floor float32 answers (its rounding, 1e-8 here, is within the target)."""
    r = to_accuracy(drifting(jnp.float32), jnp.ones(1, jnp.float32), KEY, rmse=1e-6, **ONE_ESTIMATOR)
    assert abs(r.value()[0] - (1 + 1e-8)) <= r.rmse, r.report()


def test_quasi_monte_carlo_runs_under_jit_grad_and_vmap_as_monte_carlo_does():
    """``quasi_monte_carlo`` raised a raw ``TracerArrayConversionError`` under ``jit``, ``grad`` and ``vmap`` (its
    sums were reduced on the host); now, as :func:`multilevel_monte_carlo` with fixed counts, it traces: the same
    value under ``jit`` and ``vmap``, and ``grad`` equal to its forward-mode ``wrt`` derivative of the same points."""
    y0 = Y0.astype(jnp.float64)

    def k_xx(eps):
        system = BALL.build().replace_params(eps=eps)
        return quasi_monte_carlo(system, y0, KEY, n_paths=64, replicates=4, **SPAN).cov[-1, 0, 0]

    plain = quasi_monte_carlo(BALL.build(), y0, KEY, n_paths=64, replicates=4, wrt=("eps",), **SPAN)
    assert plain.derivatives is not None
    value, derivative = float(plain.cov[-1, 0, 0]), float(plain.derivatives.d_cov[0, -1, 0, 0])
    np.testing.assert_allclose(jax.jit(k_xx)(jnp.float64(1.0)), value, rtol=1e-12)
    np.testing.assert_allclose(jax.vmap(k_xx)(jnp.array([1.0, 1.0])), [value, value], rtol=1e-12)
    np.testing.assert_allclose(jax.grad(k_xx)(jnp.float64(1.0)), derivative, rtol=1e-10)
