"""Honest error bars from summary tables: the correlations of the statistics across times, and calibration.

A summary table gives each statistic's standard error but not the correlations between statistics at
different times of the same paths; ignoring them makes the reported errors too small.  Over 32 synthetic
data sets of the ball (ε = 0.7, ν = 1.3), the z-scores ``(θ̂ − θ)/se`` must spread with a standard deviation
in [0.8, 1.25] on every route: per path, a summary with its covariance given, and a summary whose
correlations come from the model at the estimate (the ball's exact two-time covariance).
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import fit
from nhsde.scenes import BallOnVibratingPlane, ball_covariances, ball_two_time_covariances

EPS, NU = 0.7, 1.3
NAMES = ("x", "u_x")
N_SETS, N_PATHS = 32, 1024


def ball_closed_form(p, ts):
    """(mean, cov) of (x, u_x) from rest: S0 (3.1)."""
    kxx, kxu, kuu = ball_covariances(ts, p.eps, p.nu, p.delta)
    cov = jnp.stack([jnp.stack([kxx, kxu], -1), jnp.stack([kxu, kuu], -1)], -2)
    return jnp.zeros(ts.shape + (2,), ts.dtype), cov


def ball_cross(p, ts):
    """``C[a, b] = Cov(z(t_a), z(t_b))`` of z = (x, u_x): Φ(t − s) K(s) for the later time first, else its
    transpose (``ball_two_time_covariances``)."""
    s, t = jnp.minimum(ts[:, None], ts[None, :]), jnp.maximum(ts[:, None], ts[None, :])
    cxx, cxu, cux, cuu = ball_two_time_covariances(s, t, p.eps, p.nu, p.delta)
    later_first = jnp.stack([jnp.stack([cxx, cxu], -1), jnp.stack([cux, cuu], -1)], -2)
    return jnp.where((ts[:, None] >= ts[None, :])[..., None, None], later_first, jnp.swapaxes(later_first, -1, -2))


def summary_of(observed):
    """``(mean_se, cov_se)`` of a per-path ``Observations``: its Σ's diagonal, as a summary table gives it."""
    se = np.sqrt(np.diag(observed.covariance)).reshape(len(observed.ts), 5)
    cov_se = np.zeros((len(observed.ts), 2, 2))
    i, j = np.triu_indices(2)
    cov_se[:, i, j] = cov_se[:, j, i] = se[:, 2:]
    return se[:, :2], cov_se


@pytest.fixture(scope="module")
def data_sets():
    """``(ts, paths (32 · 1024, 8, 2))``: SRA1 at dt = 0.05, whose weak error is far below the Monte-Carlo error."""
    ens = nhsde.simulate(
        BallOnVibratingPlane(eps=EPS, nu=NU).build(),
        jnp.zeros(4),
        jax.random.key(5),
        n_paths=N_SETS * N_PATHS,
        t1=4.0,
        dt=0.05,
        solver="sra1",
        save=nhsde.Save(names=NAMES, n=9, paths=True),
    )
    return np.asarray(ens.ts)[1:], np.asarray(ens.paths)[:, 1:]


def test_two_time_covariance_against_the_paths(data_sets):
    """The closed form ``Φ(t − s) K(s)`` against the sample two-time covariances of 32768 paths: z-scores from
    the products' own standard errors (the 256 entries are correlated: only the extreme is held, at 4.5)."""
    ts, paths = data_sets
    exact = np.asarray(ball_cross(BallOnVibratingPlane(eps=EPS, nu=NU).params, jnp.asarray(ts)))
    z = paths - paths.mean(0)
    products = np.einsum("pai,pbj->pabij", z, z)
    sample = products.sum(0) / (len(z) - 1)
    z_scores = (sample - exact) / (products.std(0) / np.sqrt(len(z)))
    assert np.max(np.abs(z_scores)) < 4.5, np.max(np.abs(z_scores))
    # on the diagonal, the one-time covariances of ball_covariances
    np.testing.assert_allclose(
        exact[np.arange(8), np.arange(8)], ball_closed_form(BallOnVibratingPlane(eps=EPS, nu=NU).params, ts)[1]
    )


def test_gaussian_statistic_covariance_matches_the_models_own_paths():
    """Two routes to the model's Σ at θ: the Gaussian (Wishart) formula from the two-time covariance, and the
    influence functions of a simulated model's own 8192 paths.  Their correlations agree to the Monte-Carlo
    error of a sample correlation, about 1/√n (held at 5/√n)."""
    ts = (0.5, 1.0, 2.0, 4.0)
    system = BallOnVibratingPlane(eps=EPS, nu=NU).build()
    n_model, n_obs = 8192, 1000
    simulated = fit.Simulated(jnp.zeros(4), jax.random.key(9), n_paths=n_model, steps=0.05, solver="sra1")
    closed = fit.ClosedForm(ball_closed_form, cross=ball_cross)
    a = simulated.statistics_covariance(system, ts, NAMES, n_obs)
    b = closed.statistics_covariance(system, ts, NAMES, n_obs)
    assert a is not None and b is not None and a.shape == b.shape == (20, 20)
    np.testing.assert_allclose(np.sqrt(np.diag(a)), np.sqrt(np.diag(b)), rtol=0.1)
    corr = lambda c: c / np.sqrt(np.outer(np.diag(c), np.diag(c)))
    assert np.max(np.abs(corr(a) - corr(b))) < 5 / np.sqrt(n_model)
    assert fit.MomentEquations(jnp.zeros(4)).statistics_covariance(system, ts, NAMES, n_obs) is None


def test_summary_error_bars_are_calibrated(data_sets):
    ts, paths = data_sets
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    truth = np.array([EPS, NU])
    z = {"paths": [], "given": [], "model": []}
    for s in range(N_SETS):
        observed = fit.Observations.from_paths(ts, paths[s * N_PATHS : (s + 1) * N_PATHS], NAMES)
        mean_se, cov_se = summary_of(observed)
        given = fit.Observations.from_statistics(
            ts, NAMES, observed.mean, observed.cov, mean_se, cov_se, N_PATHS, covariance=observed.covariance
        )
        bare = fit.Observations.from_statistics(ts, NAMES, observed.mean, observed.cov, mean_se, cov_se, N_PATHS)
        assert (observed.correlations, given.correlations, bare.correlations) == ("paths", "given", "unknown")
        fits = {
            "paths": fit.estimate(start, observed, fit.ClosedForm(ball_closed_form)),
            "given": fit.estimate(start, given, fit.ClosedForm(ball_closed_form)),
            "model": fit.estimate(start, bare, fit.ClosedForm(ball_closed_form, cross=ball_cross)),
        }
        assert fits["model"].correlations == "model" and "the model's at the estimate" in str(fits["model"])
        for route, result in fits.items():
            assert result.converged, (route, str(result))
            z[route].append((result.values - truth) / result.se)
    for route, scores in z.items():
        spread = np.std(scores, axis=0, ddof=1)
        assert np.all((spread >= 0.8) & (spread <= 1.25)), (route, spread)


def test_summary_without_correlations_warns_and_inflates(data_sets):
    """A model that cannot give the correlations (no two-time covariance): a warning, χ²/dof inflation, said."""
    ts, paths = data_sets
    observed = fit.Observations.from_paths(ts, paths[:N_PATHS], NAMES)
    bare = fit.Observations.from_statistics(ts, NAMES, observed.mean, observed.cov, *summary_of(observed), N_PATHS)
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    with pytest.warns(UserWarning, match="summary without correlations across times.*inflated by chi2/dof"):
        result = fit.estimate(start, bare, fit.ClosedForm(ball_closed_form))
    assert result.correlations == "unknown" and result.inflation == max(1.0, result.chi2 / result.dof)
    assert "correlations across times are unknown: errors inflated" in str(result)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        exact = fit.estimate(start, bare, fit.ClosedForm(ball_closed_form, cross=ball_cross))
    assert exact.inflation == 1.0 and exact.correlations == "model"


def test_singular_model_correlations_fall_back_to_independent_statistics_and_say_why(data_sets):
    """A model whose correlations at the estimate are singular (here its two-time covariance is 0: every statistic
    held constant) is not used to whiten the data (a Cholesky error before); the fit keeps independent statistics,
    inflated, and says why.  A singular observed covariance is refused by name."""
    ts, paths = data_sets
    observed = fit.Observations.from_paths(ts, paths[:N_PATHS], NAMES)
    bare = fit.Observations.from_statistics(ts, NAMES, observed.mean, observed.cov, *summary_of(observed), N_PATHS)
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    singular = fit.ClosedForm(ball_closed_form, cross=lambda p, ts: 0.0 * ball_cross(p, ts))
    with pytest.warns(UserWarning, match=r"correlations at the estimate are singular .* inflated by chi2/dof"):
        result = fit.estimate(start, bare, singular)
    plain = fit.estimate(start, bare, fit.ClosedForm(ball_closed_form))
    assert result.correlations == "unknown" and np.array_equal(result.values, plain.values)
    dependent = np.ones_like(observed.covariance)
    with pytest.raises(ValueError, match="observed: the covariance of the observed statistics is not positive"):
        fit.estimate(start, observed.with_correlations(dependent, "given"), fit.ClosedForm(ball_closed_form))


def test_a_summary_dataset_carries_its_covariance(data_sets):
    """from_xarray reads ``covariance`` over statistic × statistic2 beside the summary's moments."""
    xr = pytest.importorskip("xarray")
    ts, paths = data_sets
    observed = fit.Observations.from_paths(ts, paths[:N_PATHS], NAMES)
    mean_se, cov_se = summary_of(observed)
    labels = fit.statistic_labels(ts, NAMES)
    ds = xr.Dataset(
        {
            "mean": (("time", "name"), observed.mean),
            "cov": (("time", "name", "name2"), observed.cov),
            "mean_se": (("time", "name"), mean_se),
            "cov_se": (("time", "name", "name2"), cov_se),
            "covariance": (("statistic", "statistic2"), observed.covariance),
        },
        coords={"time": ts, "name": list(NAMES), "name2": list(NAMES), "statistic": labels, "statistic2": labels},
        attrs={"n_used": N_PATHS},
    )
    read = fit.Observations.from_xarray(ds)
    assert read.correlations == "given"
    np.testing.assert_allclose(read.covariance, observed.covariance, rtol=1e-12)
    with pytest.raises(ValueError, match=r"holds the statistics' covariance of all of \('x', 'u_x'\)"):
        fit.Observations.from_xarray(ds, names=("x",))


def test_given_covariance_is_checked():
    with pytest.raises(ValueError, match="covariance has shape \\(3, 3\\); expected a symmetric \\(2, 2\\)"):
        fit.Observations.from_statistics(
            [1.0], ("x",), [[0.0]], [[[1.0]]], [[0.1]], [[[0.2]]], 100, covariance=np.eye(3)
        )
    with pytest.raises(ValueError, match="diagonal at cov\\[x,x\\] at t=1 is 1, but the standard error"):
        fit.Observations.from_statistics(
            [1.0], ("x",), [[0.0]], [[[1.0]]], [[0.1]], [[[0.2]]], 100, covariance=np.diag([0.01, 1.0])
        )


@pytest.mark.slow
def test_summary_error_bars_through_a_simulated_model_are_calibrated(data_sets):
    """As the calibration test, with the correlations from a simulated model's own paths at the estimate.

    16 data sets (slow: each is fitted twice through the simulator); the bounds are those of the 32-set test
    carried to 15 degrees of freedom at the same tail probabilities of (n − 1)s²/σ² ~ χ²(n − 1).
    """
    from scipy import stats

    n_sets = 16
    ts, paths = data_sets
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    scores = []
    for s in range(n_sets):
        observed = fit.Observations.from_paths(ts, paths[s * N_PATHS : (s + 1) * N_PATHS], NAMES)
        bare = fit.Observations.from_statistics(ts, NAMES, observed.mean, observed.cov, *summary_of(observed), N_PATHS)
        model = fit.Simulated(jnp.zeros(4), jax.random.key(100 + s), n_paths=4096, steps=0.05, solver="sra1")
        result = fit.estimate(start, bare, model)
        assert result.converged and result.correlations == "model", str(result)
        scores.append((result.values - np.array([EPS, NU])) / result.se)
    tails = stats.chi2.cdf([31 * 0.8**2, 31 * 1.25**2], N_SETS - 1)
    lo, hi = np.sqrt(stats.chi2.ppf(tails, n_sets - 1) / (n_sets - 1))
    spread = np.std(scores, axis=0, ddof=1)
    assert np.all((spread >= lo) & (spread <= hi)), (spread, lo, hi)
