"""nhsde.sweep: pointwise simulate bitwise, derivatives, failing points named, the plot, ``nhsde sweep``."""

import warnings
from typing import Any

import matplotlib

matplotlib.use("Agg")

import jax
import matplotlib.pyplot as plt
import numpy as np
import pytest

import nhsde
import nhsde.plot
from nhsde.runs import load_run, main
from nhsde.scenes import BallOnVibratingPlane
from nhsde.statistics import moment_sensitivities

EPS, NU = (0.5, 1.0, 2.0), (0.5, 1.5)
RUN: dict[str, Any] = dict(n_paths=256, t1=2.0, dt=0.025)
SCENE = BallOnVibratingPlane(drift=False)
STATISTIC = ("cov", "u_x", "u_x")


@pytest.fixture(scope="module")
def grid_sweep():
    """The velocity variance over a 3 × 2 grid of (ε, ν), with derivatives in both."""
    return nhsde.sweep(SCENE, {"eps": EPS, "nu": NU}, statistic=STATISTIC, key=jax.random.key(3), **RUN)


def test_sweep_matches_pointwise_simulate_bitwise(grid_sweep):
    ds = grid_sweep
    assert ds["value"].dims == ("eps", "nu") and ds["mean"].dims == ("eps", "nu", "time", "name")
    np.testing.assert_array_equal(ds["eps"], EPS)
    plain = nhsde.sweep(SCENE, {"eps": EPS, "nu": NU}, wrt=(), key=jax.random.key(3), batch=4, **RUN)
    assert "value" not in plain and "d_mean_d_eps" not in plain
    for i, eps in enumerate(EPS):
        for j, nu in enumerate(NU):
            ens = nhsde.simulate(
                SCENE.build().replace_params(eps=eps, nu=nu), SCENE.initial_state(), jax.random.key(3), **RUN
            )
            for field in ("mean", "cov", "mean_se", "cov_se"):
                np.testing.assert_array_equal(ds[field].values[i, j], getattr(ens, field), err_msg=field)
                np.testing.assert_array_equal(plain[field].values[i, j], getattr(ens, field), err_msg=field)
            assert ds["value"].values[i, j] == ens.cov[-1, 0, 0] and ds["value_se"].values[i, j] == ens.cov_se[-1, 0, 0]
            assert ds["n_used"].values[i, j] == RUN["n_paths"] and ds["n_failed"].values[i, j] == 0


def test_sweep_derivatives_are_those_of_moment_sensitivities(grid_sweep):
    ds = grid_sweep
    # paths scale as √ν at fixed noise: the variance is linear in ν, pathwise, so d/dν = value/ν to rounding
    np.testing.assert_allclose(ds["d_value_d_nu"], ds["value"] / ds["nu"], rtol=1e-9)
    sens = moment_sensitivities(
        SCENE.build().replace_params(eps=EPS[1], nu=NU[0]),
        SCENE.initial_state(),
        jax.random.key(3),
        wrt=("eps",),
        **RUN,
    )
    d_cov, _, d_cov_se = sens.derivative("eps")[1:]
    np.testing.assert_allclose(ds["d_value_d_eps"].values[1, 0], d_cov[-1, 0, 0], rtol=1e-10)
    np.testing.assert_allclose(ds["d_value_d_eps_se"].values[1, 0], d_cov_se[-1, 0, 0], rtol=1e-8)
    # friction lowers the variance
    assert np.all(ds["d_value_d_eps"] < 0)


def test_a_failing_point_is_named_by_its_parameters():
    with pytest.raises(ValueError, match="sweep: at eps=50: dt=0.025: solver 'euler' is unstable"):
        nhsde.sweep(SCENE, {"eps": [0.5, 50.0]}, wrt=(), key=jax.random.key(0), **RUN)
    # paths that overflow the float64 moment sums fail: the point is named
    with pytest.raises(nhsde.SimulationError, match="sweep: at nu=1e\\+300: simulate: 256 of 256 paths failed"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            nhsde.sweep(SCENE, {"nu": [1.0, 1e300]}, wrt=(), key=jax.random.key(0), **RUN)
    with pytest.raises(ValueError, match="'mass' is not a parameter"):
        nhsde.sweep(SCENE, {"mass": [1.0]}, key=jax.random.key(0), **RUN)
    with pytest.raises(ValueError, match="grid\\['eps'\\]=\\[\\]"):
        nhsde.sweep(SCENE, {"eps": []}, key=jax.random.key(0), **RUN)


def test_plot_draws_bands_over_one_parameter_and_a_heat_map_over_two(grid_sweep):
    ax = nhsde.plot.sweep(grid_sweep.isel(nu=0))
    assert len(ax.collections) == 1  # the band
    # labels a paper can use (they were "eps" and "cov x x at t1"), the fixed parameters in the title
    t1 = grid_sweep.attrs["t1"]
    assert ax.get_xlabel() == r"$\varepsilon$" and ax.get_ylabel() == rf"$\mathrm{{Var}}[\mathrm{{u\_x}}](t = {t1:g})$"
    assert "paths" in ax.get_title()
    # nothing cut off on a plain savefig: every label's box lies inside the figure
    fig = ax.figure
    fig.canvas.draw()
    box = fig.bbox
    for text in (ax.xaxis.label, ax.yaxis.label, ax.title):
        extent = text.get_window_extent()
        assert box.x0 <= extent.x0 and extent.x1 <= box.x1 and box.y0 <= extent.y0 and extent.y1 <= box.y1, text
    plt.close("all")
    ax = nhsde.plot.sweep(grid_sweep, "d_value_d_eps")
    mesh = ax.collections[0]
    np.testing.assert_array_equal(np.asarray(mesh.get_array()).reshape(3, 2), grid_sweep["d_value_d_eps"].values)
    plt.close("all")
    with pytest.raises(ValueError, match="no 'value'"):
        nhsde.plot.sweep(grid_sweep.drop_vars("value"))


def test_cli_sweep_writes_a_sweep_file(tmp_path, capsys):
    out = tmp_path / "sweep.nc"
    argv = ["sweep", "ball-on-vibrating-plane", "--paths", "64", "--t1", "1", "--dt", "0.05", "--x64"]
    assert main([*argv, "--grid", "eps=0.5:1.5:3", "nu=1", "--statistic", "cov u_x u_x", "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "3 grid points × 64 paths" in printed.out and "d/d eps" in printed.out
    ds = load_run(out)  # checked against its checksum
    assert ds.attrs["format"] == "nhsde-sweep" and ds.attrs["statistic"] == "cov u_x u_x"
    np.testing.assert_allclose(ds["eps"], [0.5, 1.0, 1.5])
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    ens = nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=64, t1=1.0, dt=0.05)
    np.testing.assert_array_equal(ds["cov"].values[1, 0], ens.cov)
    assert main([*argv, "--grid", "eps=1,30"]) == 2
    assert "sweep: at eps=30: dt=0.05: solver 'euler' is unstable" in capsys.readouterr().err
    assert main([*argv, "--grid", "eps=1:2"]) == 2
    assert "--grid 'eps=1:2': expected NAME=START:STOP:COUNT" in capsys.readouterr().err


def test_a_grid_too_large_is_refused_before_any_value_is_made(capsys):
    """``--grid eps=1:2:1000000000`` was killed by the kernel (rc 137, no message); 1e8 grew to 15.7 GB."""
    for grid in (["eps=1:2:1000000000"], ["eps=1:2:1000", "nu=1:2:1000"]):
        assert main(["sweep", "ball-on-vibrating-plane", "--grid", *grid]) == 2
        err = capsys.readouterr().err
        assert "points; at most 100,000 (each point is a simulation)" in err, err
