"""Fits from data files: CSV, pandas and xarray tables per path or as summaries, ``nhsde fit --data``."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import fit
from nhsde.runs import main, read_data
from nhsde.scenes import BallOnVibratingPlane, ball_covariances

EPS, NU = 0.7, 1.3
NAMES = ("x", "u_x")
N_PATHS = 1024


def ball_closed_form(p, ts):
    """(mean, cov) of (x, u_x) from rest: S0 (3.1)."""
    kxx, kxu, kuu = ball_covariances(ts, p.eps, p.nu, p.delta)
    cov = jnp.stack([jnp.stack([kxx, kxu], -1), jnp.stack([kxu, kuu], -1)], -2)
    return jnp.zeros(ts.shape + (2,), ts.dtype), cov


def write_per_path(file, ts, paths):
    rows = ["path,t,x,u_x"]
    rows += [f"{p},{t!r},{z[0]!r},{z[1]!r}" for p, path in enumerate(paths.tolist()) for t, z in zip(ts.tolist(), path)]
    file.write_text("\n".join(rows) + "\n")


def write_summary(file, observed):
    """A summary table of ``observed``: means, covariances and their standard errors (Σ's diagonal) per time."""
    se = np.sqrt(np.diag(observed.covariance)).reshape(len(observed.ts), 5)
    labels = ["mean_x", "mean_u_x", "cov_x_x", "cov_x_u_x", "cov_u_x_u_x"]
    rows = [",".join(["t", "n_paths"] + [f"{se}{label}" for label in labels for se in ("", "se_")])]
    for j, t in enumerate(observed.ts.tolist()):
        values = [observed.mean[j, 0], observed.mean[j, 1], *observed.cov[j][np.triu_indices(2)]]
        cells = [repr(float(v)) for pair in zip(values, se[j]) for v in pair]
        rows.append(",".join([repr(t), str(observed.n_paths), *cells]))
    file.write_text("\n".join(rows) + "\n")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """``(per-path CSV, summary CSV, Observations.from_paths)`` of 1024 paths of the ball at 8 times.

    SRA1 at dt = 0.02: its weak error is far below the Monte-Carlo error, so the closed form is the exact model.
    """
    ens = nhsde.simulate(
        BallOnVibratingPlane(eps=EPS, nu=NU).build(),
        jnp.zeros(4),
        jax.random.key(7),
        n_paths=N_PATHS,
        t1=4.0,
        dt=0.02,
        solver="sra1",
        save=nhsde.Save(names=NAMES, n=9, paths=True),
    )
    ts, paths = np.asarray(ens.ts)[1:], np.asarray(ens.paths)[:, 1:]
    folder = tmp_path_factory.mktemp("data")
    write_per_path(folder / "paths.csv", ts, paths)
    observed = fit.Observations.from_paths(ts, paths, NAMES)
    write_summary(folder / "summary.csv", observed)
    return folder / "paths.csv", folder / "summary.csv", observed


def test_per_path_csv_fit_recovers_known_parameters_within_4_se(data):
    per_path, _, observed = data
    read = fit.Observations.from_csv(per_path, system=BallOnVibratingPlane().build())
    assert read.names == NAMES and read.n_paths == N_PATHS and read.from_trajectories
    np.testing.assert_allclose(read.ts, observed.ts, rtol=0, atol=0)
    np.testing.assert_allclose(read.statistics(), observed.statistics(), rtol=1e-12)
    np.testing.assert_allclose(read.covariance, observed.covariance, rtol=1e-10, atol=1e-16)
    start = BallOnVibratingPlane(eps=0.4, nu=0.8).build()
    result = fit.estimate(start, read, fit.ClosedForm(ball_closed_form))
    assert result.converged, result
    z = (result.values - np.array([EPS, NU])) / result.se
    assert np.all(np.abs(z) < 4), (z, str(result))


def test_summary_csv_holds_the_statistics_and_their_errors(data):
    _, summary, observed = data
    read = fit.Observations.from_csv(summary)
    assert read.names == NAMES and read.n_paths == N_PATHS and not read.from_trajectories
    np.testing.assert_allclose(read.statistics(), observed.statistics(), rtol=1e-12)
    np.testing.assert_allclose(np.diag(read.covariance), np.diag(observed.covariance), rtol=1e-12)
    # a component subset, and the covariance column of a pair in the other order
    text = summary.read_text().replace("cov_x_u_x", "cov_u_x_x")
    (summary.parent / "swapped.csv").write_text(text)
    swapped = fit.Observations.from_csv(summary.parent / "swapped.csv")
    np.testing.assert_array_equal(swapped.statistics(), read.statistics())
    alone = fit.Observations.from_csv(summary, names=("u_x",))
    np.testing.assert_array_equal(alone.cov[:, 0, 0], read.cov[:, 1, 1])


def test_dataframe_and_xarray_read_as_the_csv(data):
    pd = pytest.importorskip("pandas")
    per_path, summary, _ = data
    csv_paths, csv_summary = fit.Observations.from_csv(per_path), fit.Observations.from_csv(summary)
    table = pd.read_csv(per_path)
    for read in (
        fit.Observations.from_dataframe(table),
        fit.Observations.from_dataframe(table.set_index(["path", "t"])),
        fit.Observations.from_xarray(table.set_index(["path", "t"]).to_xarray()),
    ):
        np.testing.assert_array_equal(read.statistics(), csv_paths.statistics())
        np.testing.assert_allclose(read.covariance, csv_paths.covariance, rtol=1e-12, atol=1e-18)
    read = fit.Observations.from_dataframe(pd.read_csv(summary))
    np.testing.assert_array_equal(read.statistics(), csv_summary.statistics())
    np.testing.assert_array_equal(read.covariance, csv_summary.covariance)


def test_run_file_layouts_read_through_xarray(data):
    """The run file's variables: ``paths`` over path × time × name, or the moments with ``n_used``."""
    xr = pytest.importorskip("xarray")
    _, _, observed = data
    ds = xr.Dataset(
        {
            "mean": (("time", "name"), observed.mean),
            "cov": (("time", "name", "name2"), observed.cov),
            "mean_se": (("time", "name"), np.full_like(observed.mean, 0.1)),
            "cov_se": (("time", "name", "name2"), np.full_like(observed.cov, 0.2)),
        },
        coords={"time": observed.ts, "name": list(NAMES), "name2": list(NAMES)},
        attrs={"n_used": N_PATHS},
    )
    read = fit.Observations.from_xarray(ds, names=("u_x",))
    np.testing.assert_array_equal(read.cov[:, 0, 0], observed.cov[:, 1, 1])
    assert read.n_paths == N_PATHS
    np.testing.assert_allclose(np.diag(read.covariance), np.tile([0.1**2, 0.2**2], len(observed.ts)))


def test_cli_fit_from_a_csv_prints_json(data, capsys):
    """``nhsde fit --data FILE --scene SCENE --fit eps,nu --json``: the normal-approximation model is exact here."""
    per_path, _, _ = data
    argv = ["fit", "--data", str(per_path), "--scene", "ball-on-vibrating-plane", "--fit", "eps,nu"]
    assert main([*argv, "--model", "moments", "--dt", "0.5", "--set", "eps=0.5", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    fit_keys = {"chi2", "dof", "chi2_per_dof", "converged", "steps", "note"}
    assert set(out) == {"eps", "nu"} | fit_keys and all(set(out[n]) == {"value", "se"} for n in ("eps", "nu"))
    for name, truth in (("eps", EPS), ("nu", NU)):
        assert abs(out[name]["value"] - truth) < 4 * out[name]["se"], out
    assert out["dof"] == 8 * 5 - 2 and out["chi2_per_dof"] == pytest.approx(out["chi2"] / out["dof"])
    assert out["converged"] is True and isinstance(out["steps"], int) and out["steps"] >= 1 and out["note"] == ""


@pytest.mark.parametrize(
    "text, message",
    [
        ("path,t,x,z\n0,1,0.1,0.2\n", "column 'z' is not a state component or observable"),
        ("path,t,x\n0,1,0.1\n0,2,\n", "line 3: column 'x' is missing"),
        ("path,t,x\n0,1,0.1\n0,2,abc\n", "line 3: column 'x' holds 'abc', not a number"),
        ("path,t,x\n0,1,0.1\n0,2,0.3\n1,1,0.2\n", "path '1' \\(from .*line 4\\) has no row at t=2.*ragged"),
        ("path,t,x\n0,1,0.1\n0,1,0.3\n", "line 3: path '0' at t=1 again \\(first in .*line 2\\)"),
        ("path,t,x\n0,1,0.1,7\n", "line 2: 4 fields; the header names 3 columns"),
        ("t,mean_x,se_mean_x,cov_x_x,se_cov_x_x,extra\n1,0,1,1,1,0\n", "unknown column 'extra'"),
        ("t,n_paths,mean_x,se_mean_x,cov_x_x\n1,10,0,1,1\n", "no column 'se_cov_x_x'"),
        ("t,mean_x,se_mean_x,cov_x_x,se_cov_x_x\n1,0,1,1,1\n", "add a column 'n_paths' or give n_paths="),
        ("t,n_paths,mean_x,se_mean_x,cov_x_x,se_cov_x_x\n1,10,0,1,1,1\n1,10,0,1,1,1\n", "line 3: t=1 again"),
        ("path,x\n0,1\n", "no column 't'"),
        ("t,x,x\n", "column 3 of the header is 'x' again"),
    ],
)
def test_bad_files_are_refused_naming_the_row_or_column(tmp_path, text, message):
    file = tmp_path / "bad.csv"
    file.write_text(text)
    with pytest.raises(ValueError, match=message):
        fit.Observations.from_csv(file, system=BallOnVibratingPlane().build())


def test_cli_data_errors_are_one_line(tmp_path, capsys):
    file = tmp_path / "bad.csv"
    file.write_text("path,t,x,z\n0,1,0.1,0.2\n")
    assert main(["fit", "--data", str(file), "--scene", "ball-on-vibrating-plane"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "column 'z' is not a state component or observable" in err
    assert main(["fit", "--data", str(file)]) == 2
    assert "--data needs --scene" in capsys.readouterr().err
    assert main(["fit"]) == 2
    assert "give --config FILE" in capsys.readouterr().err


def test_a_netcdf_data_file_reads_as_the_dataset(data, tmp_path):
    """``nhsde fit --data FILE.nc``: any dataset from_xarray reads (here the run-file layout of paths)."""
    xr = pytest.importorskip("xarray")
    _, _, observed = data
    paths = np.random.default_rng(0).normal(size=(64, len(observed.ts), 2))  # any values in the layout
    ds = xr.Dataset({"paths": (("path", "time", "name"), paths)}, coords={"time": observed.ts, "name": list(NAMES)})
    ds.to_netcdf(tmp_path / "data.nc", engine="h5netcdf")
    read = read_data(tmp_path / "data.nc", BallOnVibratingPlane().build())
    np.testing.assert_array_equal(
        read.statistics(), fit.Observations.from_paths(observed.ts, paths, NAMES).statistics()
    )
