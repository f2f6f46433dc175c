"""Derivatives of Monte-Carlo moments with their standard errors: ``moment_sensitivities``.

Against ``jax.jacfwd`` of ``simulate`` (same key, to rounding), against the analytic derivative of the ball's
covariance (S0 (3.1)) within the reported error, and the reported errors against the spread over independent keys.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ball_covariances
from nhsde.statistics import moment_sensitivities

EPS, NU, DELTA = 1.0, 1.5, 1 / 1.4
T1, DT, N = 1.0, 0.01, 256
SAVE = nhsde.Save(names=("x", "u_x"), n=3)
SYSTEM = BallOnVibratingPlane(eps=EPS, nu=NU).build()
# the ball launched with a velocity: mean and covariance both depend on eps, so the tangents have non-zero mean;
# one initial state per path, so that every test below runs the same two compiled programs
Y0 = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0, 0.5]), (N, 4))


def sensitivities(key, y0=Y0, **kw):
    return moment_sensitivities(SYSTEM, y0, key, wrt=("eps", "nu"), n_paths=N, t1=T1, dt=DT, save=SAVE, **kw)


@jax.jit
def reference(y0, key):
    """``jax.jacfwd`` of simulate's mean and cov in (eps, nu), and the moments themselves."""

    def moments(eps, nu):
        system = SYSTEM.replace_params(eps=eps, nu=nu)
        save = nhsde.Save(names=SAVE.names, n=SAVE.n, paths=True)
        ens = nhsde.simulate(system, y0, key, n_paths=N, t1=T1, dt=DT, save=save, on_failure="exclude")
        return (ens.mean, ens.cov), (ens.mean, ens.cov, ens.mean_se, ens.cov_se)

    return jax.jacfwd(moments, argnums=(0, 1), has_aux=True)(SYSTEM.params.eps, SYSTEM.params.nu)


def test_equals_jacfwd_of_simulate():
    key = jax.random.key(11)
    res = sensitivities(key)
    (d_mean, d_cov), (mean, cov, mean_se, cov_se) = reference(Y0, key)
    for got, want in [(res.mean, mean), (res.cov, cov), (res.mean_se, mean_se), (res.cov_se, cov_se)]:
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)
    for a in range(2):
        np.testing.assert_allclose(res.d_mean[a], d_mean[a], rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(res.d_cov[a], d_cov[a], rtol=1e-10, atol=1e-14)
    assert res.wrt == ("eps", "nu") and res.d_mean.shape == (2, 3, 2) and res.d_cov_se.shape == (2, 3, 2, 2)
    assert int(res.n_used) == N and int(res.n_failed) == 0
    np.testing.assert_allclose(res.ensemble.mean, mean, rtol=1e-12)  # the simulate result of the same paths
    np.testing.assert_array_equal(res.derivative("nu")[1], res.d_cov[1])


def euler_kxx(eps, nu, h, t):
    """k_xx(t) of Euler–Maruyama on (3.1), one axis, exactly: P ← M P Mᵀ + Q h (discrete Lyapunov recursion)."""
    m = jnp.array([[1.0, h], [0.0, 1.0 - 2.0 * eps * h]])
    q = jnp.array([[0.0, 0.0], [0.0, nu * DELTA**2 * h]])
    p = jax.lax.fori_loop(0, round(t / h), lambda _, p: m @ p @ m.T + q, jnp.zeros((2, 2)))
    return p[0, 0]


def test_ball_covariance_derivatives_match_closed_form():
    # 16 keys of N paths = 4096 paths (the compiled program of the other tests); pooled: mean of the
    # per-key derivatives, standard error √(Σ se²)/16, exact because the keys are independent.
    runs = [sensitivities(jax.random.key(100 + r), y0=jnp.zeros((N, 4))) for r in range(16)]
    d = np.mean([np.asarray(r.d_cov[:, -1, 0, 0]) for r in runs], axis=0)
    se = np.sqrt(np.sum([np.asarray(r.d_cov_se[:, -1, 0, 0]) ** 2 for r in runs], axis=0)) / len(runs)
    exact = np.array(jax.jit(jax.jacfwd(lambda e, n: ball_covariances(T1, e, n, DELTA)[0], argnums=(0, 1)))(EPS, NU))
    # Euler's own k_xx(1) at dt = 0.01 differs from (3.1) by O(dt); computed exactly, that bias is below
    # half the standard error (it moves z by < 0.5), so the comparison tests the estimator, not the scheme.
    scheme = np.array(jax.jit(jax.jacfwd(lambda e, n: euler_kxx(e, n, DT, T1), argnums=(0, 1)))(EPS, NU))
    assert np.all(np.abs(scheme - exact) < 0.5 * se), (scheme, exact, se)
    z = (d - exact) / se
    assert np.all(np.abs(z) <= 4), (d, exact, se, z)


def test_standard_errors_calibrated_across_keys():
    # R independent runs: if se is the standard deviation of one run's derivative, (R−1) s²/mean(se²)
    # is χ²(R−1) (approximately; the derivatives are means of N i.i.d. terms); bounds at 99.9 %
    # two-sided for all quantities together (Bonferroni).
    r_runs = 32
    runs = [sensitivities(jax.random.key(1000 + r)) for r in range(r_runs)]
    quantities = {
        "d_mean": lambda r: r.d_mean[:, -1],  # (2 params, 2 names)
        "d_cov": lambda r: r.d_cov[:, -1],  # (2, 2, 2)
    }
    n_checks = 2 * 2 + 2 * 3  # independent entries: d_mean (2×2), d_cov (2 × 3 of the symmetric 2×2)
    alpha = 1e-3 / n_checks
    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], r_runs - 1) / (r_runs - 1)
    for name, get in quantities.items():
        g = np.stack([np.asarray(get(r)) for r in runs])
        se = np.stack([np.asarray(get_se(r, name)) for r in runs])
        ratio = np.var(g, axis=0, ddof=1) / np.mean(se**2, axis=0)
        assert np.all((ratio > lo) & (ratio < hi)), (name, ratio, lo, hi)


def get_se(r, name):
    return (r.d_mean_se if name == "d_mean" else r.d_cov_se)[:, -1]


def test_failed_paths_are_excluded_from_values_and_derivatives():
    # a path whose fourth power overflows float64 counts as failed in simulate; it must enter neither
    # the moments nor their derivatives
    y0 = Y0.at[5, 0].set(1e90)
    key = jax.random.key(3)
    with pytest.raises(nhsde.SimulationError, match=f"1 of {N} paths failed"):
        sensitivities(key, y0=y0)
    res = sensitivities(key, y0=y0, on_failure="exclude")
    assert int(res.n_failed) == 1 and bool(res.failed[5]) and int(res.n_used) == N - 1
    assert np.all(np.isfinite(res.d_cov_se)) and np.all(np.isfinite(res.d_mean_se))
    (d_mean, d_cov), (mean, cov, _, _) = reference(y0, key)
    np.testing.assert_allclose(res.cov, cov, rtol=1e-10, atol=1e-14)
    for a in range(2):
        np.testing.assert_allclose(res.d_mean[a], d_mean[a], rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(res.d_cov[a], d_cov[a], rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"wrt": ("mass",)}, ValueError, r"wrt=\('mass',\): 'mass' is not a parameter of this system"),
        ({"wrt": ()}, TypeError, r"wrt=\(\); expected a non-empty tuple"),
        ({"wrt": ("eps", "eps")}, ValueError, r"wrt=\('eps', 'eps'\) names a parameter twice"),
        ({"wrt": ("eps",), "on_failure": "ignore"}, ValueError, r"on_failure='ignore'; allowed"),
        ({"wrt": ("eps",), "save": "x"}, TypeError, r"save='x'; expected nhsde.Save"),
    ],
)
def test_bad_input_names_the_argument(kwargs, error, match):
    with pytest.raises(error, match=match):
        moment_sensitivities(SYSTEM, Y0, jax.random.key(0), n_paths=N, t1=T1, dt=DT, **kwargs)


RAISED = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)  # eqx.filter_jit and eager; jax.jit
SMALL: dict[str, Any] = dict(wrt=("eps", "nu"), n_paths=64, t1=1.0, save=nhsde.Save(names=("x", "u_x"), n=3))


def d_cov(system, y0, dt=0.1):
    """A plain call's derivative; under the user's jit the parameters are traced and the checks are the program's."""
    return moment_sensitivities(system, y0, jax.random.key(0), dt=dt, **SMALL).d_cov


def test_a_parameter_out_of_range_is_refused_plain_and_under_jit():
    """A plain call checks the ranges on the host, in the state's precision (a radius of 1e-50 is 0 in float32);
    under the user's jit the program checks them with the message naming the parameter."""
    y0 = jnp.zeros(4, jnp.float32)
    tiny = BallOnVibratingPlane(eps=EPS, nu=NU, radius=1e-50).build()
    with pytest.raises(ValueError, match=r"parameter radius=0\.0 is not allowed; radius must be finite and > 0"):
        d_cov(tiny, y0)
    with pytest.raises(RAISED, match="parameter eps must be finite and ≥ 0"):
        jax.jit(lambda eps: d_cov(SYSTEM.replace_params(eps=eps), Y0[0]))(-1.0)


def test_an_unstable_step_is_refused_plain_and_under_jit():
    """ε·dt = 1 is Euler's stability limit on the ball (inclusive): a plain call refuses it before the run with
    simulate's plain message; under the user's jit the run's check says the same (the stability limit, the fix)."""
    unstable = SYSTEM.replace_params(eps=10.0)
    with pytest.raises(ValueError, match=r"dt=0\.1: solver 'euler' is unstable .* stability limit") as plain:
        d_cov(unstable, Y0[0])
    assert "solver='exponential'" in str(plain.value)
    with pytest.raises(RAISED, match="stability limit") as traced:
        jax.jit(lambda eps: d_cov(SYSTEM.replace_params(eps=eps), Y0[0]))(10.0)
    assert "solver='exponential'" in str(traced.value)
    with pytest.warns(nhsde.StationaryVarianceWarning, match=r"stationary variance 2× the exact one"):
        d_cov(SYSTEM.replace_params(eps=5.0), Y0[0])  # ε·dt = 1/2: the plain call's warning, with the step


def test_moment_sums_that_overflow_are_refused_plain_and_under_jit():
    """float32 paths at ±3e9 (their fourth powers finite, so no path fails) whose fourth-moment sums about the first
    path overflow: never a silent inf in the standard errors, plain or under jit."""
    y0 = jnp.zeros((64, 4), jnp.float32).at[:, 0].set(jnp.where(jnp.arange(64) % 2 == 0, 3e9, -3e9))
    with pytest.raises(nhsde.SimulationError, match="moment_sensitivities: the moment sums overflow"):
        d_cov(SYSTEM, y0, dt=0.05)
    with pytest.raises(RAISED, match="the moment sums overflow"):
        jax.jit(lambda eps: d_cov(SYSTEM.replace_params(eps=eps), y0, dt=0.05))(EPS)
