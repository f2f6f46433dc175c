"""What a fit accepts as data, and what it refuses before any run.

Times outside the model's span and spans beyond the step budget are refused naming the argument, the value and
what is allowed; negative variances and standard errors, and complex values (data or initial state), are refused
naming the column or statistic; statistics of zero variance (a deterministic start written into the file) are left
out of the fit, which says so; Excel's byte-order mark is read; the columnar CSV reader keeps the checks and line
numbers of the file; ``nhsde fit --json`` carries the fit's diagnostics.

Data: 512 paths of the ball (ε = 0.7, ν = 1.3) drawn exactly from its Gaussian law at 8 times (the two-time
covariance of ``ball_two_time_covariances``), so that the closed form is the exact model and no simulation runs.
"""

import io
import json
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nhsde import fit
from nhsde.runs import _fit as runs_fit, fit_data, main
from nhsde.scenes import BallOnVibratingPlane, ball_covariances, ball_two_time_covariances

EPS, NU = 0.7, 1.3
NAMES = ("x", "u_x")
TS = 0.5 * np.arange(1, 9)
N_PATHS = 512


def ball_closed_form(p, ts):
    """(mean, cov) of (x, u_x) from rest: S0 (3.1)."""
    kxx, kxu, kuu = ball_covariances(ts, p.eps, p.nu, p.delta)
    cov = jnp.stack([jnp.stack([kxx, kxu], -1), jnp.stack([kxu, kuu], -1)], -2)
    return jnp.zeros(ts.shape + (2,), ts.dtype), cov


def joint_covariance(ts) -> np.ndarray:
    """``Cov`` of ``(z(t_1), …, z(t_T))``, z = (x, u_x), flattened time-major: ``Φ(t − s) K(s)`` for s ≤ t."""
    p = BallOnVibratingPlane(eps=EPS, nu=NU).params
    ts = jnp.asarray(ts)
    s, t = jnp.minimum(ts[:, None], ts[None, :]), jnp.maximum(ts[:, None], ts[None, :])
    cxx, cxu, cux, cuu = ball_two_time_covariances(s, t, p.eps, p.nu, p.delta)
    later_first = jnp.stack([jnp.stack([cxx, cxu], -1), jnp.stack([cux, cuu], -1)], -2)
    cross = jnp.where((ts[:, None] >= ts[None, :])[..., None, None], later_first, jnp.swapaxes(later_first, -1, -2))
    return np.asarray(cross).transpose(0, 2, 1, 3).reshape(2 * len(ts), 2 * len(ts))


@pytest.fixture(scope="module")
def paths() -> np.ndarray:
    """``(512, 8, 2)`` exact draws of (x, u_x) at ``TS``."""
    c = joint_covariance(TS)
    chol = np.linalg.cholesky(c + 1e-12 * np.max(np.diag(c)) * np.eye(len(c)))
    z = np.random.default_rng(3).standard_normal((N_PATHS, len(c))) @ chol.T
    return z.reshape(N_PATHS, len(TS), 2)


def write_per_path(file, ts, z, encoding="utf-8"):
    rows = ["path,t,x,u_x"]
    rows += [f"{p},{t!r},{a!r},{b!r}" for p, path in enumerate(z.tolist()) for t, (a, b) in zip(ts.tolist(), path)]
    file.write_text("\n".join(rows) + "\n", encoding=encoding)
    return file


def with_start(z) -> tuple[np.ndarray, np.ndarray]:
    """The times and paths with the deterministic start at t = 0 (every path at the origin) put first."""
    return np.concatenate([[0.0], TS]), np.concatenate([np.zeros((len(z), 1, 2)), z], axis=1)


SUMMARY = "t,n_paths,mean_x,se_mean_x,cov_x_x,se_cov_x_x\n1,400,0.01,0.05,1.02,0.07\n2,400,-0.03,0.07,2.1,0.15\n"


def no_run(*args, **kwargs):
    raise AssertionError("a fit ran")


# --- statistics of zero variance: left out, and said ------------------------------------------------------------


def test_a_deterministic_start_in_the_file_is_left_out_and_said(paths, tmp_path):
    """The t = 0 rows (every path the same) give 5 statistics of zero variance: the fit leaves them out, says so,
    and is the fit of the file without them, which recovers (ε, ν) within 4 of its standard errors."""
    ts, z = with_start(paths)
    observed = fit.Observations.from_csv(write_per_path(tmp_path / "start.csv", ts, z))
    assert observed.ts.tolist() == ts.tolist() and len(observed.used) == 8 * 5
    assert observed.note.startswith("left out 5 statistics of zero variance") and "every statistic at t=0" in (
        observed.note
    )
    assert np.all(observed.covariance[:5] == 0) and np.all(observed.covariance[:, :5] == 0)
    without = fit.Observations.from_paths(TS, paths, NAMES)
    assert without.note == ""
    np.testing.assert_allclose(observed.covariance[5:, 5:], without.covariance, rtol=1e-10, atol=1e-18)

    start = BallOnVibratingPlane(eps=0.4, nu=0.8).build()
    result = fit.estimate(start, observed, fit.ClosedForm(ball_closed_form))
    assert result.converged and result.note == observed.note and result.note in str(result)
    assert result.dof == 8 * 5 - 2 and result.jacobian is not None and result.jacobian.shape == (8 * 5, 2)
    # its χ² is that of the file without the start, at the estimate
    at = BallOnVibratingPlane(eps=result.values[0], nu=result.values[1]).params
    r = np.asarray(fit.statistic_vector(*ball_closed_form(at, jnp.asarray(TS)))) - without.statistics()
    assert result.chi2 == pytest.approx(r @ np.linalg.solve(without.covariance, r), rel=1e-8)
    z_scores = (result.values - np.array([EPS, NU])) / result.se
    assert np.all(np.abs(z_scores) < 4), (z_scores, str(result))


def test_a_component_constant_at_one_time_leaves_its_statistics_out(paths):
    z = paths.copy()
    z[:, 2, 0] = 0.25  # x the same on every path at t = 1.5
    observed = fit.Observations.from_paths(TS, z, NAMES)
    labels = fit.statistic_labels(TS, NAMES)
    left_out = sorted(set(range(len(labels))) - set(observed.used.tolist()))
    assert [labels[i] for i in left_out] == ["mean[x] at t=1.5", "cov[x,x] at t=1.5", "cov[x,u_x] at t=1.5"]
    assert "left out 3 statistics" in observed.note and "cov[x,u_x] at t=1.5" in observed.note


def test_a_summary_standard_error_of_zero_is_left_out(tmp_path):
    file = tmp_path / "summary.csv"
    file.write_text(SUMMARY.replace("1,400,0.01,0.05,1.02,0.07", "0,400,0,0,0,0") + "3,400,0.02,0.08,3.1,0.2\n")
    observed = fit.Observations.from_csv(file)
    assert observed.ts.tolist() == [0.0, 2.0, 3.0] and observed.used.tolist() == [2, 3, 4, 5]
    assert "every statistic at t=0" in observed.note
    with pytest.raises(ValueError, match="every statistic of \\('x',\\) has zero variance"):
        fit.Observations.from_statistics([1.0], ("x",), [[0.0]], [[[0.0]]], [[0.0]], [[[0.0]]], 100)


def test_cli_reads_a_file_with_its_deterministic_start_and_prints_the_note(paths, tmp_path, capsys, monkeypatch):
    """The command passes the data, note included, to ``estimate`` (a stand-in here, which returns the note as
    ``estimate`` does; test_fit_data fits through the command) and prints the note, in the table and in JSON."""
    seen = []

    def stand_in(system, observed, model, *, vary, max_steps, progress):
        seen.append((observed, model))
        cov = np.diag([0.01, 0.04])
        return fit.FitResult(
            vary,
            np.array([0.7, 1.3]),
            cov,
            np.array([0.5, 1.0]),
            40.0,
            38,
            9,
            True,
            np.zeros((9, 3)),
            note=observed.note,
        )

    monkeypatch.setattr(runs_fit, "estimate", stand_in)
    file = write_per_path(tmp_path / "start.csv", *with_start(paths))
    argv = ["fit", "--data", str(file), "--scene", "ball-on-vibrating-plane", "--model", "moments", "--dt", "0.5"]
    assert main([*argv, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["note"].startswith("left out 5 statistics of zero variance") and "every statistic at t=0" in out["note"]
    assert out["eps"] == {"value": 0.7, "se": 0.1} and out["nu"] == {"value": 1.3, "se": 0.2}
    assert (out["chi2"], out["dof"], out["converged"], out["steps"]) == (40.0, 38, True, 9)
    assert out["chi2_per_dof"] == pytest.approx(40 / 38)
    observed, model = seen[0]
    assert observed.ts[0] == 0.0 and len(observed.used) == 40 and model.t0 == 0.0
    assert main(argv) == 0
    assert "left out 5 statistics of zero variance" in capsys.readouterr().out


# --- times outside the model's span, and the step budget, refused before any run ---------------------------------


@pytest.mark.parametrize(
    "ts, t0, message",
    [
        (TS, 1.0, "--t0 1: the data .* start at t=0.5, before it; .* give --t0 ≤ 0.5"),
        (TS - 1.0, None, "--t0 0: the data .* start at t=-0.5, before it; .* give --t0 ≤ -0.5"),
    ],
)
@pytest.mark.parametrize("model", ["simulate", "moments"])
def test_cli_refuses_times_before_t0(paths, tmp_path, capsys, monkeypatch, ts, t0, message, model):
    monkeypatch.setattr(runs_fit, "estimate", no_run)
    file = write_per_path(tmp_path / "data.csv", ts, paths)
    argv = ["fit", "--data", str(file), "--scene", "ball-on-vibrating-plane", "--model", model]
    assert main(argv + ([] if t0 is None else ["--t0", str(t0)])) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(message, err), err


@pytest.mark.parametrize(
    "ts, steps",
    [(TS * 1e6, "400000000 steps"), (1.0 + 1e-9 * np.arange(8), r"\d{9} steps")],
    ids=["times-scaled-by-1e6", "times-1e-9-apart"],
)
@pytest.mark.parametrize("model", ["simulate", "moments"])
def test_cli_refuses_a_span_beyond_the_step_budget_before_any_run(
    paths, tmp_path, capsys, monkeypatch, ts, steps, model
):
    monkeypatch.setattr(runs_fit, "estimate", no_run)
    file = write_per_path(tmp_path / "data.csv", ts, paths)
    assert main(["fit", "--data", str(file), "--scene", "ball-on-vibrating-plane", "--model", model]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert re.search(f"{steps} of \\(t0, t1\\).*beyond the budget max_steps=10000000", err), err
    assert "give a larger --dt, or the data's times in the scene's time unit" in err


def test_models_refuse_times_before_t0_and_spans_beyond_their_budget(paths, monkeypatch):
    """In the library: ``estimate`` asks the model first (``check_times``), so nothing runs."""
    import nhsde.fit._estimate as estimate_module

    monkeypatch.setattr(estimate_module, "simulate", no_run)
    monkeypatch.setattr(estimate_module, "normal_approximation", no_run)
    system = BallOnVibratingPlane().build()
    observed = fit.Observations.from_paths(TS, paths, NAMES)
    key = jax.random.key(0)
    for model in (
        fit.Simulated(jnp.zeros(4), key, n_paths=64, steps=0.05, t0=1.0),
        fit.MomentEquations(jnp.zeros(4), dt=0.05, t0=1.0),
    ):
        with pytest.raises(ValueError, match="t0=1 is after the first observation time 0.5; .*take t0 ≤ 0.5"):
            fit.estimate(system, observed, model)
    far = fit.Observations.from_paths(TS * 1e6, paths, NAMES)
    for model, remedy in (
        (fit.Simulated(jnp.zeros(4), key, n_paths=64, steps=0.1), r"Simulated\(steps=FixedSteps\(dt, max_steps=…\)\)"),
        (fit.MomentEquations(jnp.zeros(4), dt=0.1), r"MomentEquations\(max_steps=…\)"),
    ):
        budget = f"40000000 steps .* beyond the budget max_steps=10000000; raise it with {remedy}"
        with pytest.raises(ValueError, match=budget):
            fit.estimate(system, far, model)
    allowed = fit.MomentEquations(jnp.zeros(4), dt=0.5, max_steps=10**7)
    allowed.check_times(TS * 1e5)  # 800000 steps: within the budget


# --- negative variances and standard errors --------------------------------------------------------------------


@pytest.mark.parametrize(
    "before, after, message",
    [
        ("1.02,0.07\n2", "-1.02,0.07\n2", "line 2: column 'cov_x_x' holds -1.02, a negative variance; it must be ≥ 0"),
        ("0.05,1.02", "-0.05,1.02", "line 2: column 'se_mean_x' holds -0.05, a negative standard error"),
        ("2.1,0.15", "2.1,-0.15", "line 3: column 'se_cov_x_x' holds -0.15, a negative standard error"),
    ],
)
def test_a_summary_with_a_negative_variance_or_error_is_refused(tmp_path, before, after, message):
    file = tmp_path / "summary.csv"
    file.write_text(SUMMARY.replace(before, after))
    with pytest.raises(ValueError, match=message):
        fit.Observations.from_csv(file)


def test_from_statistics_refuses_negative_variances_and_errors():
    def read(cov, mean_se, cov_se):
        return fit.Observations.from_statistics([1.0, 2.0], ("x", "y"), np.zeros((2, 2)), cov, mean_se, cov_se, 100)

    cov, se, cov_se = np.stack([np.eye(2), 2 * np.eye(2)]), np.full((2, 2), 0.1), np.full((2, 2, 2), 0.2)
    bad = cov.copy()
    bad[1, 1, 1] = -0.5
    with pytest.raises(ValueError, match="cov: the variance cov\\[y,y\\] at t=2 is -0.5; a variance must be ≥ 0"):
        read(bad, se, cov_se)
    with pytest.raises(ValueError, match="mean_se: the standard error of mean\\[y\\] at t=1 is -0.1"):
        read(cov, se * [[1, -1], [1, 1]], cov_se)
    with pytest.raises(ValueError, match="cov_se: the standard error of cov\\[x,y\\] at t=2 is -0.2"):
        read(cov, se, cov_se * [[[1, 1], [1, 1]], [[1, -1], [-1, 1]]])


# --- complex values ----------------------------------------------------------------------------------------------


def test_complex_data_is_refused(paths, tmp_path):
    pd = pytest.importorskip("pandas")
    xr = pytest.importorskip("xarray")
    table = pd.DataFrame({"path": [0, 0, 1, 1], "t": [1.0, 2.0, 1.0, 2.0], "x": [0.1, 0.2 + 0.5j, 0.3, 0.4]})
    with pytest.raises(ValueError, match="df row 1: column 'x' holds the complex number \\(0.2\\+0.5j\\); only real"):
        fit.Observations.from_dataframe(table)
    file = tmp_path / "complex.csv"
    file.write_text("path,t,x\n0,1,0.1\n0,2,1+2j\n")
    with pytest.raises(ValueError, match="line 3: column 'x' holds the complex number '1\\+2j'; only real values"):
        fit.Observations.from_csv(file)
    z = paths.astype(complex)
    z[3, 2, 1] += 1e-3j
    with pytest.raises(ValueError, match="paths holds the complex number"):
        fit.Observations.from_paths(TS, z, NAMES)
    ds = xr.Dataset({"paths": (("path", "time", "name"), z)}, coords={"time": TS, "name": list(NAMES)})
    with pytest.raises(ValueError, match="paths holds the complex number"):
        fit.Observations.from_xarray(ds)
    with pytest.raises(ValueError, match="mean holds the complex number 1j"):
        fit.Observations.from_statistics([1.0], ("x",), [[1j]], [[[1.0]]], [[0.1]], [[[0.2]]], 100)


def test_a_complex_initial_state_is_refused(paths, tmp_path, monkeypatch):
    key = jax.random.key(0)
    y0 = jnp.zeros(4, complex)
    with pytest.raises(TypeError, match="y0 has dtype complex.*; expected real values"):
        fit.Simulated(y0, key, n_paths=64, steps=0.05)
    with pytest.raises(TypeError, match="y0 has dtype complex"):
        fit.MomentEquations(y0)
    with pytest.raises(TypeError, match="cov0 has dtype complex"):
        fit.MomentEquations(jnp.zeros(4), cov0=jnp.eye(4, dtype=complex))
    monkeypatch.setattr(runs_fit, "estimate", no_run)
    monkeypatch.setattr(BallOnVibratingPlane, "initial_state", lambda self: jnp.full(4, 0.5j, dtype=complex))
    file = write_per_path(tmp_path / "data.csv", TS, paths)
    with pytest.raises(ValueError, match="--scene: the initial state of BallOnVibratingPlane is complex"):
        fit_data(file, BallOnVibratingPlane, ("eps", "nu"))


# --- what the reader accepts -----------------------------------------------------------------------------------


def test_a_byte_order_mark_is_read(paths, tmp_path):
    plain, marked = tmp_path / "plain.csv", tmp_path / "marked.csv"
    plain.write_text(SUMMARY)
    marked.write_text(SUMMARY, encoding="utf-8-sig")
    assert marked.read_bytes().startswith(b"\xef\xbb\xbf")
    a, b = fit.Observations.from_csv(plain), fit.Observations.from_csv(marked)
    assert a.names == b.names == ("x",)
    np.testing.assert_array_equal(a.statistics(), b.statistics())
    per_path = fit.Observations.from_csv(write_per_path(tmp_path / "paths.csv", TS, paths, encoding="utf-8-sig"))
    np.testing.assert_allclose(per_path.statistics(), fit.Observations.from_paths(TS, paths, NAMES).statistics())


def test_blank_lines_comments_and_line_endings_are_skipped_and_lines_counted(tmp_path):
    values = np.random.default_rng(1).normal(size=(8, 2)).round(3).tolist()
    lines = ["path,t,x"] + [f"{p},{t + 1},{values[p][t]!r}" for p in range(8) for t in range(2)]
    clean = "\n".join(lines) + "\n"
    # lines 1-2 before the header (line 3); data on 4-6, then a blank, a comment and an empty record (7-9)
    messy = "\n".join(["# made by hand", "", lines[0], *lines[1:4], "  ", "# a comment", ",,", *lines[4:]]) + "\n"
    (tmp_path / "clean.csv").write_text(clean)
    (tmp_path / "messy.csv").write_text(messy.replace("\n", "\r\n"))
    a, b = (fit.Observations.from_csv(tmp_path / f) for f in ("clean.csv", "messy.csv"))
    np.testing.assert_array_equal(a.statistics(), b.statistics())
    np.testing.assert_array_equal(a.covariance, b.covariance)
    tenth, twelfth = lines[4], lines[6]  # lines 10 and 12 of the messy file: path 1 at t=2, path 2 at t=2
    assert tenth.startswith("1,2,") and twelfth.startswith("2,2,")
    for name, line, message in [
        ("bad", tenth.replace(tenth.split(",")[2], "abc"), "bad.csv, line 10: column 'x' holds 'abc', not a number"),
        ("long", twelfth + ",1,2", "long.csv, line 12: 5 fields; the header names 3 columns"),
        ("wide", twelfth + ",1", "wide.csv, line 12: 4 fields; the header names 3 columns"),
        ("again", "1" + twelfth[1:], "again.csv, line 12: path '1' at t=2 again \\(first in .*line 10\\)"),
    ]:
        (tmp_path / f"{name}.csv").write_text(messy.replace(twelfth if name != "bad" else tenth, line))
        with pytest.raises(ValueError, match=message):
            fit.Observations.from_csv(tmp_path / f"{name}.csv")


def test_text_path_labels_and_a_header_only_file(tmp_path):
    file = tmp_path / "labels.csv"
    values = np.random.default_rng(2).normal(size=(8, 2)).round(3).tolist()
    rows = [f" {label} ,{t + 1},{values[p][t]!r}" for p, label in enumerate("abcdefgh") for t in range(2)]
    file.write_text("\n".join(["path,t,x", *rows]) + "\n")
    observed = fit.Observations.from_csv(file)
    assert observed.n_paths == 8 and observed.ts.tolist() == [1.0, 2.0]
    np.testing.assert_allclose(observed.mean[:, 0], np.mean(values, 0))
    (tmp_path / "header.csv").write_text("path,t,x\n")
    with pytest.raises(ValueError, match="header.csv holds no data rows"):
        fit.Observations.from_csv(tmp_path / "header.csv")


def test_an_empty_dataset_is_refused_by_the_library():
    xr = pytest.importorskip("xarray")
    with pytest.raises(ValueError, match="ds holds no data variables; expected paths over path × time × name"):
        fit.Observations.from_xarray(xr.Dataset())


def test_the_command_prints_each_step_on_a_terminal_only(monkeypatch):
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert runs_fit.terminal_progress() is None
    monkeypatch.setattr("sys.stderr", Terminal())
    show = runs_fit.terminal_progress()
    assert show is not None
    show(3, 29.29, {"eps": 0.697, "nu": 1.28})
    assert sys.stderr.getvalue() == "fit step   3: chi2/2 = 29.29  eps = 0.697  nu = 1.28\n"


# --- the loss's gradient in forward mode -----------------------------------------------------------------------


def test_the_loss_gradient_in_forward_mode_equals_reverse_mode_under_every_transform():
    """``_gradient_in_forward_mode(f)`` has ``f``'s value, and its ``jax.grad`` is ``f``'s analytic gradient, under
    ``jit``, ``vmap`` and ``value_and_grad``, also where only the derivative is returned."""
    from nhsde.fit._estimate import _gradient_in_forward_mode

    def f(phi):
        return jnp.sin(phi[0]) * jnp.exp(phi[1]) + phi[2] ** 3

    def exact(phi):
        return jnp.stack([jnp.cos(phi[0]) * jnp.exp(phi[1]), jnp.sin(phi[0]) * jnp.exp(phi[1]), 3 * phi[2] ** 2])

    g = _gradient_in_forward_mode(f)
    phis = jnp.asarray([[0.3, -0.2, 1.5], [1.1, 0.4, -0.7]])
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.grad(g)))(phis), jax.vmap(exact)(phis), rtol=1e-13)
    value, grad = jax.jit(jax.value_and_grad(g))(phis[0])
    assert float(value) == pytest.approx(float(f(phis[0])), rel=1e-15)
    np.testing.assert_allclose(grad, exact(phis[0]), rtol=1e-13)


def test_a_fit_is_the_same_with_its_gradient_in_forward_or_reverse_mode(paths, monkeypatch):
    """The fit of two parameters (forward mode) and the same fit with reverse mode forced agree to the optimiser's
    tolerance: the same estimates within 1e-3 of their standard errors, the same χ²."""
    from nhsde.fit import _estimate

    observed = fit.Observations.from_paths(TS, paths, NAMES)
    start = BallOnVibratingPlane(eps=0.4, nu=0.8).build()
    forward = fit.estimate(start, observed, fit.ClosedForm(ball_closed_form))
    monkeypatch.setattr(_estimate, "FORWARD_MODE_UP_TO", 0)
    reverse = fit.estimate(start, observed, fit.ClosedForm(ball_closed_form))
    assert forward.converged and reverse.converged
    np.testing.assert_allclose(forward.values, reverse.values, atol=1e-3 * float(np.min(forward.se)))
    assert forward.chi2 == pytest.approx(reverse.chi2, rel=1e-6)
