"""Statistics and forward-mode gradients of the ball, the sleigh and the Chaplygin ball equal, to rounding, the values
recorded before the redesign of ``simulate`` (tests/data/redesign_baseline.json, same key and settings)."""

import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ChaplyginBall, ChaplyginSleigh

BASELINE = json.loads((pathlib.Path(__file__).parent / "data" / "redesign_baseline.json").read_text())
SCENES = {"ball": BallOnVibratingPlane, "sleigh": ChaplyginSleigh, "chaplygin-ball": ChaplyginBall}


@pytest.mark.parametrize("name", sorted(BASELINE))
def test_statistics_and_gradients_unchanged_by_the_redesign(name):
    rec, cls = BASELINE[name], SCENES[name]
    y0 = cls(**rec["kwargs"]).initial_state()

    def stats(eps, nu):
        system = cls(eps=eps, nu=nu).build()
        ens = nhsde.simulate(
            system,
            y0,
            jax.random.key(rec["key"]),
            n_paths=rec["n_paths"],
            t1=rec["t1"],
            dt=rec["dt"],
            solver=rec["solver"],
        )
        return ens.mean[-1], ens.cov[-1]

    args = (jnp.float64(rec["kwargs"]["eps"]), jnp.float64(rec["kwargs"]["nu"]))
    mean, cov = stats(*args)
    (dm_eps, dm_nu), (dc_eps, dc_nu) = jax.jacfwd(stats, argnums=(0, 1))(*args)
    np.testing.assert_allclose(mean, rec["mean"], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(cov, rec["cov"], rtol=1e-12, atol=1e-14)
    for got, want in zip((dm_eps, dm_nu, dc_eps, dc_nu), (*rec["d_mean"], *rec["d_cov"]), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-13)
