"""The work-precision harness measures what it claims and picks the cheapest adequate setting."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ball_covariances


@pytest.fixture(scope="module")
def rows():
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    reference = float(ball_covariances(jnp.float64(1.0), 1.0, 1.0, 1 / 1.4)[2])
    return nhsde.work_precision(
        scene.build(),
        scene.initial_state().astype(jnp.float64),
        jax.random.key(0),
        t1=1.0,
        solvers=["euler", "sra1"],
        dts=[0.25, 0.125, 0.0625],
        n_paths=2048,
        strong_paths=128,
        statistic=lambda ens: (ens.cov[-1, 2, 2], ens.cov_se[-1, 2, 2]),
        reference=reference,
        save=nhsde.Save(names=("u_x",), n=2),
    )


def test_rows_cover_every_setting_and_errors_shrink(rows):
    assert [(r.solver, r.dt) for r in rows] == [(s, h) for s in ("euler", "sra1") for h in (0.25, 0.125, 0.0625)]
    for solver, order in (("euler", 1.0), ("sra1", 2.0)):
        errs = [r.strong_error for r in rows if r.solver == solver]
        assert errs[0] > errs[1] > errs[2]
        # halving dt divides the strong error by about 2^order (ball: see test_solvers)
        assert abs(np.log2(errs[1] / errs[2]) - order) < 0.35
    for r in rows:
        assert r.seconds > 0 and r.peak_bytes > 0 and r.weak_se > 0


def test_cheapest_setting(rows):
    best = nhsde.cheapest_setting(rows, 0.05, kind="strong")
    assert best.strong_error <= 0.05
    assert all(r.seconds >= best.seconds for r in rows if r.strong_error <= 0.05)
    with pytest.raises(ValueError, match="no measured setting reaches strong error 1e-09"):
        nhsde.cheapest_setting(rows, 1e-9, kind="strong")
    with pytest.raises(ValueError, match="kind='mean'"):
        nhsde.cheapest_setting(rows, 0.1, kind="mean")
