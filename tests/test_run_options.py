"""One run-options object, passed whole: every entry point takes ``run=nhsde.RunOptions(...)`` and gives bitwise what
its flat keywords give; both at once, or a wrong object, is refused naming them; the estimator objects are callable
to a target, and an accuracy result reads any saved statistic.

The entry points are a registry: a new one joins every test here by one line.
"""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ball_covariances
from nhsde.statistics import Covariance, Mean

SCENE = BallOnVibratingPlane(eps=1.0, nu=1.0, drift=False)
SYSTEM, Y0, KEY = SCENE.build(), jnp.zeros(2), jax.random.key(3)
STATISTIC = Covariance("u_x", "u_x")
RUN = nhsde.RunOptions(t1=0.5, steps=nhsde.FixedSteps(0.125), save=nhsde.Save(n=2))
# to_accuracy: run='s solver is the one considered
FLAT: dict[str, Any] = dict(t1=0.5, dt=0.125, solver="euler", save=nhsde.Save(n=2))
S = nhsde.statistics

ENTRY_POINTS = {
    "simulate": lambda **kw: nhsde.simulate(SYSTEM, Y0, KEY, n_paths=64, **kw).cov,
    "moment_sensitivities": lambda **kw: S.moment_sensitivities(SYSTEM, Y0, KEY, wrt=("eps",), n_paths=64, **kw).d_cov,
    "sweep": lambda **kw: nhsde.sweep(SYSTEM, {"eps": [1.0]}, key=KEY, n_paths=64, y0=Y0, **kw)["cov"].values,
    "extrapolate": lambda **kw: S.extrapolate(SYSTEM, Y0, KEY, n_paths=64, **kw).cov,
    "multilevel_monte_carlo": lambda **kw: (
        S.multilevel_monte_carlo(SYSTEM, Y0, KEY, statistic=STATISTIC, n_paths=(64, 64), **kw).cov
    ),
    "quasi_monte_carlo": lambda **kw: S.quasi_monte_carlo(SYSTEM, Y0, KEY, n_paths=64, replicates=2, **kw).cov,
    "multilevel_quasi_monte_carlo": lambda **kw: (
        S.multilevel_quasi_monte_carlo(SYSTEM, Y0, KEY, statistic=STATISTIC, n_points=(64,), replicates=2, **kw).cov
    ),
    "control_variate": lambda **kw: S.control_variate(SYSTEM, Y0, KEY, n_paths=64, **kw).cov,
    "martingale_control_variate": lambda **kw: (
        S.martingale_control_variate(SYSTEM, Y0, KEY, STATISTIC, n_paths=64, n_pilot=128, **kw).cov
    ),
    "to_accuracy": lambda **kw: np.array(
        S.to_accuracy(SYSTEM, Y0, KEY, statistic=STATISTIC, relative_rmse=0.3, **kw).value()
    ),
}


@pytest.mark.parametrize("entry", ENTRY_POINTS)
def test_run_options_give_what_the_keywords_give(entry):
    f = ENTRY_POINTS[entry]
    with_run = np.asarray(f(run=RUN))
    assert np.all(np.isfinite(with_run))
    np.testing.assert_array_equal(with_run, np.asarray(f(**FLAT)))


@pytest.mark.parametrize("entry", ENTRY_POINTS)
def test_run_options_and_keywords_at_once_are_refused_naming_both(entry):
    with pytest.raises(TypeError, match=r"run= and dt= both given; give the run's options once"):
        ENTRY_POINTS[entry](run=RUN, dt=0.25)
    with pytest.raises(TypeError, match=r"run=\{'t1': 0.5\}; expected nhsde.RunOptions"):
        ENTRY_POINTS[entry](run={"t1": 0.5})


def test_run_options_check_themselves():
    with pytest.raises(ValueError, match="dt=0.3 must divide t1 − t0 = 1.0"):
        nhsde.RunOptions(t1=1.0, steps=nhsde.FixedSteps(0.3))
    with pytest.raises(TypeError, match="steps=0.1; expected nhsde.FixedSteps"):
        nhsde.RunOptions(t1=1.0, steps=0.1)  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="simulate needs t1"):
        nhsde.simulate(SYSTEM, Y0, KEY, n_paths=64, dt=0.1)
    with pytest.raises(ValueError, match="compares solves on fixed step grids"):
        S.extrapolate(SYSTEM, Y0, KEY, n_paths=64, run=nhsde.RunOptions(t1=1.0, steps=nhsde.AdaptiveSteps(0.1)))


@pytest.mark.parametrize(
    "estimator", [S.PlainMonteCarlo(), S.Multilevel(), S.MartingaleControlVariate()], ids=lambda e: e.name
)
def test_an_estimator_object_is_called_to_a_target(estimator):
    """``Estimator()(system, y0, key, statistic, rmse=…, run=…)`` meets the target against the closed form of S0
    (3.1), k_uu = νδ²(1 − e^{−4εt})/(4ε); the result reads another saved statistic of the same run: the mean
    velocity, 0 by symmetry, within 5 of its standard errors."""
    run = nhsde.RunOptions(t1=1.0, steps=nhsde.FixedSteps(0.25))
    exact = float(ball_covariances(1.0, 1.0, 1.0, float(SYSTEM.params.delta))[2])
    rmse = 0.02 * exact
    result = estimator(SYSTEM, Y0, KEY, STATISTIC, rmse=rmse, run=run)
    value, se = result.value()
    assert result.choice.startswith(estimator.method)
    assert abs(value - exact) < 4 * rmse and 0 < se <= 2 * rmse
    mean, mean_se = result.value(Mean("u_x"))
    assert mean_se > 0 and abs(mean) < 5 * mean_se
    assert result.value(("cov", "u_x", "u_x")) == (value, se)
