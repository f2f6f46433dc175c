"""Realised RMSE of ``to_accuracy`` over many keys against the RMSE it was asked for, estimator by estimator.

The sleigh (``ChaplyginSleigh(eps=0.5, nu=1.0, drift=False)``, y0 = [1, 0.5]) has the closed form
``E[H](t) = H0 e^{−4εt} + ν(1 − e^{−4εt})/(4ε)``, H0 = 0.75.  Statistics: each run ``i`` of ``to_accuracy`` with
target ``ε`` promises ``E e_i² ≤ ε²`` for its error ``e_i``; the runs use independent keys, so with about Gaussian
errors ``Σ e_i²/ε²`` is stochastically below ``χ²_n`` (for a fixed MSE a bias only narrows its spread: the variance
of ``Σ e_i²`` is ``2nε⁴`` with no bias, ``2n(ε⁴ − b⁴)`` with bias ``b``).  So ``√(Σ e_i²/n) ≤ ε √(χ²_{n,0.99}/n)``
holds with probability ≥ 99 % for each estimator: ≈ 1.37 ε for n = 20, ≈ 1.74 ε for n = 5.  The keys are fixed
(``jax.random.key(1000 + i)``), so the outcome is deterministic; a failure means a promise broken at 99 %
confidence (with eighteen estimators in the slow test, about 17 % of all sets of keys would fail one by chance
alone).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import nhsde
from nhsde.scenes import ChaplyginSleigh
from nhsde.statistics import (
    ControlVariate,
    Mean,
    Multilevel,
    MultilevelQuasiMonteCarlo,
    PlainMonteCarlo,
    QuasiMonteCarlo,
    Richardson,
    to_accuracy,
)

EPS, NU, T1 = 0.5, 1.0, 2.0
SLEIGH = ChaplyginSleigh(eps=EPS, nu=NU, drift=False).build()
Y0 = jnp.array([1.0, 0.5])
EXACT = 0.75 * math.exp(-4 * EPS * T1) + NU * (1 - math.exp(-4 * EPS * T1)) / (4 * EPS)
GAUSS = nhsde.PlatenWeak2(increments="gaussian")
ESTIMATORS = {
    "plain-euler": PlainMonteCarlo("euler"),
    "plain-weak2": PlainMonteCarlo(GAUSS),
    "richardson-euler": Richardson("euler"),
    "richardson-weak2": Richardson(GAUSS),
    "multilevel-euler": Multilevel("euler"),
    "multilevel-weak2": Multilevel(GAUSS),
    "multilevel-weak2-anti": Multilevel(GAUSS, antithetic=True),
    "multilevel-euler-control": Multilevel("euler", control=True),
    "multilevel-weak2-control": Multilevel(GAUSS, control=True),
    "control-variate": ControlVariate(),
    "qmc": QuasiMonteCarlo(),
    "qmc-weak2": QuasiMonteCarlo(GAUSS),
    "qmc-anti": QuasiMonteCarlo(antithetic=True),
    "multilevel-heun2": Multilevel("heun2"),
    "mlqmc": MultilevelQuasiMonteCarlo(),
    "mlqmc-weak2": MultilevelQuasiMonteCarlo(GAUSS),
    "qmc-weak2-control": QuasiMonteCarlo(GAUSS, control=True),
    "mlqmc-weak2-control": MultilevelQuasiMonteCarlo(GAUSS, control=True),
}


def chi2_bound(n: int, level: float = 0.99) -> float:
    """√(χ²_{n,level}/n): the bound on realised RMSE/ε over n independent runs each of MSE ≤ ε² (module)."""
    return math.sqrt(scipy.stats.chi2.ppf(level, n) / n)


def realised(estimator, n_keys: int, rel: float):
    """(realised RMSE/ε, errors/ε, the last run) over the keys 1000 … 1000 + n_keys − 1."""
    eps = rel * EXACT
    errors, last = [], None
    for i in range(n_keys):
        last = to_accuracy(
            SLEIGH,
            Y0,
            jax.random.key(1000 + i),
            t1=T1,
            statistic=Mean("energy"),
            rmse=eps,
            save=nhsde.Save(names=("energy",), n=2),
            estimators=(estimator,),
        )
        errors.append((last.value()[0] - EXACT) / eps)
    errors = np.array(errors)
    return float(np.sqrt(np.mean(errors**2))), errors, last


def test_realised_rmse_fast_plain_euler():
    """Plain Euler Monte Carlo at a loose target (relative 0.05), 5 keys: RMSE/ε ≤ √(χ²_{5,0.99}/5) ≈ 1.74."""
    ratio, errors, last = realised(PlainMonteCarlo("euler"), 5, 0.05)
    assert ratio <= chi2_bound(5), (errors, last.report())


@pytest.mark.slow
@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_realised_rmse_every_estimator(name):
    """Each estimator alone at relative RMSE 1e-2, 20 keys: RMSE/ε ≤ √(χ²_{20,0.99}/20) ≈ 1.37 (module)."""
    ratio, errors, last = realised(ESTIMATORS[name], 20, 1e-2)
    assert ratio <= chi2_bound(20), (name, ratio, errors, last.report())
