"""nhsde.fit: recovery of ε and ν on synthetic data, calibration of the reported errors, bad input."""

import warnings

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import nhsde
from nhsde import fit
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances

BALL_EPS, BALL_NU = 0.8, 1.5
NAMES = ("x", "u_x")


def ball_ensemble(key, n_paths, t1=4.0, dt=0.02, n_save=9, solver="sra1"):
    """Synthetic observations of (x, u_x); SRA1's weak error at dt = 0.02 is far below the Monte-Carlo error."""
    system = BallOnVibratingPlane(eps=BALL_EPS, nu=BALL_NU).build()
    return nhsde.simulate(
        system,
        jnp.zeros(4),
        key,
        n_paths=n_paths,
        t1=t1,
        dt=dt,
        solver=solver,
        save=nhsde.Save(names=NAMES, n=n_save, paths=True),
    )


def ball_data(*args, **kwargs):
    """Observation times after t = 0 and the paths there."""
    ens = ball_ensemble(*args, **kwargs)
    return np.asarray(ens.ts)[1:], np.asarray(ens.paths)[:, 1:]


def ball_closed_form(p, ts):
    """(mean, cov) of (x, u_x) from rest: S0 (3.1), ``ball_covariances``."""
    kxx, kxu, kuu = ball_covariances(ts, p.eps, p.nu, p.delta)
    cov = jnp.stack([jnp.stack([kxx, kxu], -1), jnp.stack([kxu, kuu], -1)], -2)
    return jnp.zeros(ts.shape + (2,), ts.dtype), cov


def closed_form_of(i):
    """The closed form of component ``i`` alone (0: x, 1: u_x)."""

    def fn(p, ts):
        mean, cov = ball_closed_form(p, ts)
        return mean[:, i : i + 1], cov[:, i : i + 1, i : i + 1]

    return fn


def ball_euler_moments(p, ts, dt):
    """(mean, cov) of (x, u_x) of the Euler–Maruyama chain from rest, exactly: K ← A K Aᵀ + Q per step.

    With A = [[1, dt], [0, 1 − 2ε dt]] and Q = diag(0, νδ² dt) (S0 (3.1) per axis); ``ts`` on the step grid.
    """
    steps = np.round(np.asarray(ts) / dt).astype(int)
    a = jnp.array([[1.0, dt], [0.0, 1.0 - 2.0 * p.eps * dt]])
    q = jnp.array([[0.0, 0.0], [0.0, p.nu * p.delta**2 * dt]])

    def step(cov, _):
        cov = a @ cov @ a.T + q
        return cov, cov

    _, covs = jax.lax.scan(step, jnp.zeros((2, 2)), length=int(steps[-1]))
    return jnp.zeros((len(steps), 2)), covs[steps - 1]


def statistics_jacobian(fn, params, ts, vary):
    """``∂s/∂θ (S, p)`` of the statistic vector of ``fn(params, ts) -> (mean, cov)`` in the parameters ``vary``."""

    def s(theta):
        return fit.statistic_vector(*fn(params.replace(**dict(zip(vary, theta))), ts))

    return np.asarray(jax.jacfwd(s)(jnp.asarray([getattr(params, n) for n in vary])))


def within_two_se(result, truth):
    z = (result.values - np.asarray(truth)) / result.se
    assert result.converged, result
    assert np.all(np.abs(z) <= 2), (z, str(result))
    return z


@pytest.fixture(scope="module")
def ball_simulated_fit():
    """``(observed, model, start, result)``: the ball's (ε, ν) fitted by Euler simulation, 8 times of (x, u_x)."""
    # Data and model share the solver and step, so the model's discretisation is the data's.
    ts, paths = ball_data(jax.random.key(11), 2048, solver="euler")
    observed = fit.Observations.from_paths(ts, paths, NAMES)
    start = BallOnVibratingPlane(eps=0.3, nu=0.5).build()
    model = fit.Simulated(jnp.zeros(4), jax.random.key(12), n_paths=2048, steps=0.02, solver="euler")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 2048 model paths: G's Monte-Carlo error (≈ 6 %) raises no warning
        result = fit.estimate(start, observed, model, vary=("eps", "nu"))
    return observed, model, start, result


def test_ball_fit_through_simulation_recovers_eps_and_nu(ball_simulated_fit):
    *_, result = ball_simulated_fit
    within_two_se(result, (BALL_EPS, BALL_NU))
    # χ² of a model that fits: below its 99.9 % quantile.
    assert result.chi2 < stats.chi2.ppf(0.999, result.dof), result


def test_simulated_jacobian_standard_errors_are_honest(ball_simulated_fit):
    """G = ∂s/∂θ of the simulated fit against the exact G of the Euler chain: z = ΔG/se(G) ~ N(0, 1).

    The reference is the Euler–Maruyama chain's own exact moments at the same dt and θ̂, so the comparison
    has no discretisation bias (against the continuous closed form, Euler's bias at dt = 0.02 reaches
    ≈ 2.5 se(G) here).  The 80 entries (5 statistics × 8 times × 2 parameters) are correlated across the
    times of one path set, so mean z² is held to the χ² band of a pessimistic 10 independent values (one
    per statistic and parameter, as if the 8 times were one): the 0.1 % and 99.9 % quantiles of χ²(10)/10.
    """
    observed, model, start, result = ball_simulated_fit
    ts = tuple(float(t) for t in observed.ts)
    vary = ("eps", "nu")
    params = start.params.replace(**result.params)
    # the standard errors come from the very paths (and layout) of the fitted Jacobian; strong float64
    # parameters, as estimate passes them, reuse its compiled program
    fitted = start.replace_params(**dict(zip(vary, jnp.asarray(result.values))))
    g, g_se = model.sensitivities(fitted, ts, NAMES, vary)
    np.testing.assert_allclose(g, result.jacobian, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(g_se, result.jacobian_se)
    assert result.jacobian.shape == result.jacobian_se.shape == (40, 2)

    exact = statistics_jacobian(lambda p, t: ball_euler_moments(p, t, 0.02), params, jnp.asarray(ts), vary)
    # the Euler chain's moments are near the closed form's (a check of ball_euler_moments itself)
    closed = statistics_jacobian(ball_closed_form, params, jnp.asarray(ts), vary)
    np.testing.assert_allclose(exact, closed, rtol=0.05, atol=0.02)
    noisy = result.jacobian_se > 0
    assert noisy.sum() == 80  # every entry is a Monte-Carlo estimate, the zero means' derivatives included
    z = (result.jacobian - exact)[noisy] / result.jacobian_se[noisy]
    lo, hi = stats.chi2.ppf([0.001, 0.999], 10) / 10
    assert np.max(np.abs(z)) < 4.5, z
    assert lo < np.mean(z**2) < hi, (np.mean(z**2), lo, hi)
    # with 2048 paths the information of each parameter is known to a few per cent, and the table says so
    rel = result.jacobian_relative_se
    assert np.all((rel > 0.01) & (rel < 0.15)), rel
    assert "MC err" in str(result)


def test_too_few_model_paths_warn(ball_simulated_fit):
    """16 model paths for the 2048 observed: ∂s/∂θ is too noisy (relative errors ≈ 0.5–0.8 per parameter)."""
    observed, *_ = ball_simulated_fit
    start = BallOnVibratingPlane(eps=BALL_EPS, nu=BALL_NU).build()
    model = fit.Simulated(jnp.zeros(4), jax.random.key(14), n_paths=16, steps=0.1)
    # one optimizer step from the truth: the warning concerns the final Jacobian, not the search
    with pytest.warns(UserWarning, match="relative Monte-Carlo error of ∂s/∂(eps|nu) is .*use more n_paths"):
        result = fit.estimate(start, observed, model, max_steps=1)
    assert np.all(result.jacobian_relative_se > 0.3), result.jacobian_relative_se  # the warning's threshold


def test_exact_models_have_exact_jacobians(ball_simulated_fit):
    """ClosedForm and MomentEquations: zero Monte-Carlo error of ∂s/∂θ, no warning, no column for it."""
    observed, *_ = ball_simulated_fit  # the calibration test's times and model: its compiled program
    ts = tuple(float(t) for t in observed.ts)
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = fit.estimate(start, observed, fit.ClosedForm(ball_closed_form))
    assert result.jacobian_se is not None and result.jacobian_se.shape == (40, 2)
    assert np.all(result.jacobian_se == 0) and np.all(result.jacobian_relative_se == 0)
    assert "MC err" not in str(result)
    params = start.params.replace(**result.params)
    exact = statistics_jacobian(ball_closed_form, params, jnp.asarray(ts), ("eps", "nu"))
    np.testing.assert_allclose(result.jacobian, exact, rtol=1e-10)
    moments = fit.MomentEquations(jnp.zeros(4), dt=0.1, order=1)
    np.testing.assert_array_equal(moments.jacobian_se(start, ts, NAMES, ("eps", "nu")), np.zeros((40, 2)))


def test_jacobian_errors_of_a_solver_object_with_its_default_scan_are_known():
    """diffrax's SRA1 with its default (reverse-only) scan had no JVP, and the errors of ∂s/∂θ were NaN; simulate
    now runs every solver's stages as a scan both modes differentiate, so they are finite and positive."""
    model = fit.Simulated(jnp.zeros(4), jax.random.key(16), n_paths=64, steps=0.5, solver=dfx.SRA1())
    system = BallOnVibratingPlane(eps=BALL_EPS, nu=BALL_NU).build()
    se = model.jacobian_se(system, (1.0,), NAMES, ("eps",))
    assert se.shape == (5, 1) and np.all(np.isfinite(se)) and np.any(se > 0)


def test_sleigh_fit_through_simulation_recovers_eps_and_nu():
    """The nonlinear scene: statistics of (v, ω) of the noisy Chaplygin sleigh."""
    eps, nu = 0.5, 0.8
    y0 = jnp.array([1.0, 0.5])
    data = nhsde.simulate(
        ChaplyginSleigh(eps=eps, nu=nu, drift=False).build(),
        y0,
        jax.random.key(21),
        n_paths=2048,
        t1=3.0,
        dt=0.02,
        save=nhsde.Save(n=7, paths=True),
    )
    observed = fit.Observations.from_paths(data.ts[1:], data.paths[:, 1:], ("v", "omega"))
    start = ChaplyginSleigh(eps=0.2, nu=0.3, drift=False).build()
    model = fit.Simulated(y0, jax.random.key(22), n_paths=4096, steps=0.02)
    result = fit.estimate(start, observed, model)
    within_two_se(result, (eps, nu))
    assert result.chi2 < stats.chi2.ppf(0.999, result.dof), result


def test_reported_errors_are_calibrated():
    """Over 40 independent data sets, Σ (θ̂ − θ)ᵀ Cov⁻¹ (θ̂ − θ) follows χ²(2·40).

    This checks the Fisher-information covariance itself (not only one
    estimate): the sum must fall between the 0.1 % and 99.9 % quantiles.
    """
    n_sets, n_paths = 40, 1024
    ts, paths = ball_data(jax.random.key(31), n_sets * n_paths)
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    model = fit.ClosedForm(ball_closed_form)
    total, estimates = 0.0, []
    for s in range(n_sets):
        observed = fit.Observations.from_paths(ts, paths[s * n_paths : (s + 1) * n_paths], NAMES)
        result = fit.estimate(start, observed, model)
        assert result.converged
        d = result.values - np.array([BALL_EPS, BALL_NU])
        total += d @ np.linalg.solve(result.cov, d)
        estimates.append(result.values)
    lo, hi = stats.chi2.ppf([0.001, 0.999], 2 * n_sets)
    assert lo < total < hi, (total, lo, hi)
    # and the spread of the estimates matches the reported standard errors
    ratio = np.std(estimates, axis=0, ddof=1) / result.se
    assert np.all((ratio > 0.6) & (ratio < 1.4)), ratio


def test_statistic_covariance_agrees_with_simulate_standard_errors():
    """Σ's diagonal (influence functions) against simulate's exact-moment standard errors."""
    ens = ball_ensemble(jax.random.key(41), 4096, n_save=3)
    observed = fit.Observations.from_paths(ens.ts[1:], ens.paths[:, 1:], NAMES)
    se = np.asarray(fit.statistic_vector(ens.mean_se[1:], ens.cov_se[1:]))
    np.testing.assert_allclose(np.sqrt(np.diag(observed.covariance)), se, rtol=1e-3)
    np.testing.assert_allclose(observed.statistics(), fit.statistic_vector(ens.mean[1:], ens.cov[1:]), rtol=1e-9)


def test_single_statistic_fit_is_the_analytic_estimate():
    """One measured k_xx(t) and ν alone: ν̂ = ν₀ k̂/k(t; ν₀) exactly, se(ν̂) = ν₀ se(k̂)/k(t; ν₀)."""
    t, k_hat, k_se = 3.0, 2.7, 0.11
    observed = fit.Observations.from_statistics([t], ("x",), [[0.0]], [[[k_hat]]], [[0.05]], [[[k_se]]], n_paths=1000)
    start = BallOnVibratingPlane(eps=BALL_EPS, nu=0.4).build()
    result = fit.estimate(start, observed, fit.ClosedForm(closed_form_of(0)), vary=("nu",))
    k_unit = float(ball_covariances(t, BALL_EPS, 1.0, 1 / 1.4)[0])
    np.testing.assert_allclose(result.values[0], k_hat / k_unit, rtol=1e-8)
    np.testing.assert_allclose(result.se[0], k_se / k_unit, rtol=1e-8)
    assert result.dof == 1 and result.chi2 < 1e-12


def test_bad_input_is_named():
    ts, paths = ball_data(jax.random.key(51), 256, n_save=3)
    observed = fit.Observations.from_paths(ts, paths, NAMES)
    system = BallOnVibratingPlane().build()
    model = fit.ClosedForm(ball_closed_form)
    with pytest.raises(ValueError, match="'mass' is not a parameter"):
        fit.estimate(system, observed, model, vary=("mass",))
    with pytest.raises(ValueError, match="init: eps=-1.0 must be > 0"):
        fit.estimate(system, observed, model, init={"eps": -1.0})
    # a deterministic start carries no information: left out, with a note (it used to be refused)
    started = fit.Observations.from_paths(np.r_[0.0, ts], np.concatenate([np.zeros((256, 1, 2)), paths], 1), NAMES)
    assert "every statistic at t=0" in started.note and len(started.used) == len(observed.used)
    with pytest.raises(ValueError, match="paths cannot estimate"):
        fit.Observations.from_paths(ts, paths[:10], NAMES)
    with pytest.raises(
        ValueError, match="Simulated: observation times \\[1.0, 2.5\\] are not on an equally spaced grid"
    ):
        bad = fit.Observations.from_paths(np.array([1.0, 2.5]), paths, NAMES)
        fit.estimate(system, bad, fit.Simulated(jnp.zeros(4), jax.random.key(0), n_paths=64, steps=0.5))
    with pytest.raises(ValueError, match="do not determine \\('eps', 'nu'\\) separately"):
        # k_uu at one late time fixes only νδ²/(4ε): a ridge, not a point
        late = fit.Observations.from_statistics([40.0], ("u_x",), [[0.0]], [[[0.5]]], [[0.01]], [[[0.01]]], 1000)
        fit.estimate(system, late, fit.ClosedForm(closed_form_of(1)))
    with pytest.raises(ValueError, match="save: unknown name 'z'"):
        fit.estimate(system, fit.Observations.from_paths(ts, paths, ("x", "z")), model)


def test_moment_equation_model_is_exact_for_the_linear_ball():
    """The normal approximation is exact for the linear ball: its statistics are the closed form's."""
    system = BallOnVibratingPlane(eps=BALL_EPS, nu=BALL_NU).build()
    ts = (1.0, 2.0, 3.0, 4.0)
    # one Gauss–Hermite node is exact for a linear drift
    moments = fit.MomentEquations(jnp.zeros(4), dt=0.1, order=1).moments(system, ts, NAMES)
    exact = fit.ClosedForm(ball_closed_form).moments(system, ts, NAMES)
    for a, b in zip(moments, exact):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_moment_equation_fit_equals_the_closed_form_fit_for_the_linear_ball():
    """Two routes, one estimate (slow: compiling reverse mode through the Dopri8 moment equations)."""
    ts, paths = ball_data(jax.random.key(61), 1024, n_save=5)
    observed = fit.Observations.from_paths(ts, paths, NAMES)
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    exact = fit.estimate(start, observed, fit.ClosedForm(ball_closed_form))
    moments = fit.estimate(start, observed, fit.MomentEquations(jnp.zeros(4), dt=0.1, order=1))
    np.testing.assert_allclose(moments.values, exact.values, rtol=1e-6)
    np.testing.assert_allclose(moments.se, exact.se, rtol=1e-5)
    assert np.all(moments.jacobian_se == 0)
    within_two_se(moments, (BALL_EPS, BALL_NU))


@pytest.mark.slow
def test_reported_errors_of_simulated_fits_are_calibrated():
    """As the calibration test, through the simulator: the model's Monte-Carlo term must be right too.

    16 data sets of 1024 paths, each fitted with 512 simulated paths of another
    key, so two thirds of each variance is the model's: Σ Mahalanobis² ~ χ²(32),
    where leaving the model's term out would give about 3 × 32.
    """
    n_sets, n_paths = 16, 1024
    ts, paths = ball_data(jax.random.key(71), n_sets * n_paths, solver="euler")
    start = BallOnVibratingPlane(eps=0.5, nu=1.0).build()
    total = 0.0
    for s in range(n_sets):
        observed = fit.Observations.from_paths(ts, paths[s * n_paths : (s + 1) * n_paths], NAMES)
        model = fit.Simulated(jnp.zeros(4), jax.random.key(1000 + s), n_paths=n_paths // 2, steps=0.02)
        result = fit.estimate(start, observed, model)
        d = result.values - np.array([BALL_EPS, BALL_NU])
        total += d @ np.linalg.solve(result.cov, d)
    lo, hi = stats.chi2.ppf([0.001, 0.999], 2 * n_sets)
    assert lo < total < hi, (total, lo, hi)


def test_moment_equations_that_overflow_stop_the_fit_with_a_clear_error():
    """The fit's step carries no run-time check of the moment equations (its program enters the compilation cache):
    the host refuses a loss or gradient that is not finite, naming the parameters.  Here Dopri8 at dt = 0.5 is
    unstable at ε = 1e3 on the sleigh (the velocities' relaxation rate 2ε; a nonlinear system's moments are
    integrated, a linear one's follow their exact flow at any step)."""
    scene = ChaplyginSleigh(eps=1e3, nu=0.4)
    observed = fit.Observations.from_statistics([3.0], ("x",), [[0.0]], [[[2.7]]], [[0.05]], [[[0.11]]], 1000)
    model = fit.MomentEquations(y0=scene.initial_state(), dt=0.5)
    message = r"the loss is (inf|nan) and its gradient \[(inf|nan)\] at eps=1000; the model's statistics are not finite"
    with pytest.raises(FloatingPointError, match=message):
        fit.estimate(scene.build(), observed, model, vary=("eps",), max_steps=3)


def test_progress_is_called_once_per_optimizer_step():
    """``estimate(progress=...)`` sees each step's loss and values, the same as the fit's history."""
    scene = BallOnVibratingPlane(eps=0.8, nu=0.4)
    observed = fit.Observations.from_statistics([3.0], ("x",), [[0.0]], [[[2.7]]], [[0.05]], [[[0.11]]], 1000)
    seen = []
    result = fit.estimate(
        scene.build(),
        observed,
        fit.MomentEquations(y0=scene.initial_state(), dt=0.5),
        vary=("nu",),
        progress=lambda step, loss, values: seen.append((step, loss, values["nu"])),
    )
    assert [s for s, _, _ in seen] == list(range(1, result.steps + 1))
    np.testing.assert_array_equal([[loss, nu] for _, loss, nu in seen], result.history)
