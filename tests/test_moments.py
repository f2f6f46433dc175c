"""Normal-approximation method (S0 §6): closed forms on the linear ball, Monte Carlo on the nonlinear sleigh,
gradients by every route, stationary drift formulas and Green–Kubo diffusion."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances
from nhsde.statistics import (
    DriftStatistics,
    NormalApproximation,
    drift_statistics,
    effective_diffusion,
    green_kubo,
    normal_approximation,
    stationary_drift,
)


@pytest.mark.parametrize("eps", [0.3, 1.0, 2.5])
def test_ball_moment_equations_reproduce_the_closed_forms(eps):
    nu = 1.7
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    ens = normal_approximation(
        scene.build(), scene.initial_state().astype(jnp.float64), t1=4.0, dt=0.01, save=nhsde.Save(n=9)
    )
    # its own type: moments without placeholder Monte-Carlo fields
    assert isinstance(ens, NormalApproximation) and ens.standard_errors() is None and not hasattr(ens, "mean_se")
    k_xx, k_xu, k_uu = ball_covariances(ens.ts, eps, nu, float(scene.params.delta))
    for (i, j), exact in [((0, 0), k_xx), ((1, 1), k_xx), ((0, 2), k_xu), ((2, 2), k_uu), ((3, 3), k_uu)]:
        np.testing.assert_allclose(ens.cov[:, i, j], exact, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(ens.cov[:, 0, 1], 0.0, atol=1e-15)
    np.testing.assert_allclose(ens.mean, 0.0, atol=1e-15)
    stats = drift_statistics(ens)  # the Monte-Carlo statistic applies unchanged
    assert isinstance(stats, DriftStatistics) and stats.names == ("x", "y")
    assert stats.fluctuation_se is None and stats.systematic_se is None
    np.testing.assert_allclose(stats.fluctuation[:, 0, 0], k_xx, rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize(
    "eps, dtype, rtol", [(0.3, jnp.float64, 1e-12), (1e3, jnp.float64, 1e-12), (1.0, jnp.float32, 2e-5)]
)
def test_linear_moment_equations_are_exact_at_any_step_and_any_friction(eps, dtype, rtol):
    """A linear autonomous system's moments follow its exact flow (matrix exponentials): one step per save interval of
    length 0.5 at ε = 1e3 (ε·dt = 500, where Dopri8 overflows) still gives the closed forms."""
    nu = 1.7
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    ens = normal_approximation(scene.build(), scene.initial_state().astype(dtype), t1=4.0, dt=0.5, save=nhsde.Save(n=9))
    assert ens.cov.dtype == dtype
    k_xx, k_xu, k_uu = ball_covariances(np.asarray(ens.ts, np.float64), eps, nu, float(scene.params.delta))
    for (i, j), exact in [((0, 0), k_xx), ((0, 2), k_xu), ((2, 2), k_uu), ((3, 3), k_uu)]:
        np.testing.assert_allclose(ens.cov[:, i, j], exact, rtol=rtol, atol=rtol * np.max(np.abs(exact)))


def test_a_linear_system_driven_in_time_is_integrated_not_taken_as_autonomous():
    """q̇ = p, ṗ = −2p + cos t: linear but not autonomous, so its moments are integrated (Dopri8); taking the forcing
    as constant would miss the closed form m_p = (2 cos t + sin t − 2 e^{−2t})/5."""
    forced = nhsde.StochasticSystem(
        drift_fn=lambda t, y, p: jnp.stack([y[1], -2 * y[1] + jnp.cos(t)]),
        diffusion_fn=lambda t, y, p: jnp.eye(2, 1, -1, dtype=y.dtype),
        params={},
        layout=nhsde.StateLayout(("q", "p"), ("independent_coordinate", "momentum")),
        noise_dim=1,
        additive_noise=True,
    )
    ens = normal_approximation(forced, jnp.zeros(2, jnp.float64), t1=4.0, dt=0.01, save=nhsde.Save(n=9))
    t = np.asarray(ens.ts)
    np.testing.assert_allclose(ens.mean[:, 1], (2 * np.cos(t) + np.sin(t) - 2 * np.exp(-2 * t)) / 5, atol=1e-12)
    np.testing.assert_allclose(ens.cov[:, 1, 1], (1 - np.exp(-4 * t)) / 4, atol=1e-12)  # K̇ = −4K + 1


def sleigh_statistics(nu, eps=0.1, n_paths=4096):
    scene = ChaplyginSleigh(eps=eps, nu=nu)
    y0 = scene.initial_state().astype(jnp.float64)
    save = nhsde.Save(n=4)
    moments = drift_statistics(normal_approximation(scene.build(), y0, t1=3.0, dt=0.02, save=save))
    mc = drift_statistics(
        nhsde.simulate(scene.build(), y0, jax.random.key(0), n_paths=n_paths, t1=3.0, dt=0.01, solver="sra1", save=save)
    )
    return moments, mc


def test_sleigh_moment_drift_against_monte_carlo_and_its_growth_with_nu():
    """Weak noise: the Gaussian closure agrees with Monte Carlo within 4 SE.  Stronger noise (more nonlinearity):
    the fluctuation drift K_yy is off by many SE and the relative error grows with ν (benchmarks/ has the curve)."""
    errors = {}
    for nu in (0.003, 0.3):
        moments, mc = sleigh_statistics(nu)
        dm = np.abs(np.asarray(moments.systematic - mc.systematic))
        dk = np.abs(np.asarray(moments.fluctuation - mc.fluctuation))
        if nu == 0.003:
            assert np.all(dm[1:] <= 4 * np.asarray(mc.systematic_se[1:])), (dm, mc.systematic_se)
            assert np.all(dk[1:] <= 4 * np.asarray(mc.fluctuation_se[1:]) + 1e-15), (dk, mc.fluctuation_se)
        errors[nu] = dk[-1, 1, 1] / float(mc.fluctuation[-1, 1, 1])
        if nu == 0.3:
            assert dk[-1, 1, 1] > 4 * float(mc.fluctuation_se[-1, 1, 1])
    assert errors[0.3] > 5 * errors[0.003], errors


def test_moment_method_gradients_on_the_ball_are_the_closed_form_derivatives():
    """∂K_xx(t)/∂(ε, ν) of the moment method, reverse and forward mode, against the derivative of the closed form
    (finite differences: the slow test below)."""

    def k_xx(eps, nu):
        scene = BallOnVibratingPlane(eps=eps, nu=nu)
        return normal_approximation(scene.build(), jnp.zeros(4), t1=2.0, dt=0.01, save=nhsde.Save(n=3)).cov[:, 0, 0]

    args = (jnp.float64(0.8), jnp.float64(1.3))
    rev = jax.jacrev(k_xx, argnums=(0, 1))(*args)
    fwd = jax.jacfwd(k_xx, argnums=(0, 1))(*args)
    ts = jnp.linspace(0.0, 2.0, 3)
    exact = jax.jacfwd(lambda e, n: ball_covariances(ts, e, n, 1 / 1.4)[0], argnums=(0, 1))(*args)
    for r, f, x in zip(rev, fwd, exact):
        np.testing.assert_allclose(r, x, rtol=1e-9, atol=1e-14)
        np.testing.assert_allclose(f, x, rtol=1e-9, atol=1e-14)


@pytest.mark.slow
def test_gradients_of_drift_statistics_by_every_route():
    """∂/∂(ε, ν) of m_x(t1) and K_yy(t1) on the sleigh at weak noise: Monte Carlo in reverse and forward mode
    (equal), central finite differences of Monte Carlo (common random numbers) and of the moment method, and the
    moment method's own reverse and forward derivatives — all within the Monte-Carlo error of the pathwise gradient.
    (∂m_x/∂ε is nearly deterministic, SE ≈ 0.1 %: the step must keep Euler's O(ε dt) bias below it.)"""
    n, t1, dt = 2048, 2.0, 0.004  # Euler's bias in ∂m_x/∂ε: 0.0032 here (0.008 at dt = 0.01), ≈ 1.3 SE
    y0 = ChaplyginSleigh().initial_state().astype(jnp.float64)

    def system(eps, nu):
        return ChaplyginSleigh(eps=eps, nu=nu).build()

    def mc_paths(eps, nu):
        ens = nhsde.simulate(
            system(eps, nu),
            y0,
            jax.random.key(4),
            n_paths=n,
            t1=t1,
            dt=dt,
            save=nhsde.Save(names=("x", "y"), n=2, paths=True),
        )
        return ens.paths[:, -1, :]

    def statistics_of(xy):
        yc = xy[:, 1] - jnp.mean(xy[:, 1])
        return jnp.stack([jnp.mean(xy[:, 0]), jnp.sum(yc**2) / (xy.shape[0] - 1)])

    def mc(eps, nu):
        return statistics_of(mc_paths(eps, nu))

    def moments(eps, nu):
        ens = normal_approximation(system(eps, nu), y0, t1=t1, dt=0.01, save=nhsde.Save(names=("x", "y"), n=2))
        return jnp.stack([ens.mean[-1, 0], ens.cov[-1, 1, 1]])

    eps, nu = jnp.float64(0.1), jnp.float64(0.003)
    rev = np.stack(jax.jacrev(mc, argnums=(0, 1))(eps, nu), axis=-1)  # (statistic, parameter)
    fwd = np.stack(jax.jacfwd(mc, argnums=(0, 1))(eps, nu), axis=-1)
    np.testing.assert_allclose(rev, fwd, rtol=1e-9, atol=1e-12)
    m_rev = np.stack(jax.jacrev(moments, argnums=(0, 1))(eps, nu), axis=-1)
    m_fwd = np.stack(jax.jacfwd(moments, argnums=(0, 1))(eps, nu), axis=-1)
    np.testing.assert_allclose(m_rev, m_fwd, rtol=1e-9, atol=1e-12)

    se = np.zeros_like(rev)
    for j, tangent in enumerate([(1.0, 0.0), (0.0, 1.0)]):
        xy, dxy = jax.jvp(mc_paths, (eps, nu), tuple(jnp.float64(v) for v in tangent))
        xy, dxy = np.asarray(xy), np.asarray(dxy)
        se[0, j] = dxy[:, 0].std() / math.sqrt(n)  # derivative of a mean: mean of the tangents
        yc, dyc = xy[:, 1] - xy[:, 1].mean(), dxy[:, 1] - dxy[:, 1].mean()
        se[1, j] = (2 * yc * dyc).std() / math.sqrt(n)  # derivative of a variance: 2/(n−1) Σ y° ẏ°
    for j, h in enumerate([1e-5, 1e-6]):
        step = (h, 0.0) if j == 0 else (0.0, h)
        fd_mc = (mc(eps + step[0], nu + step[1]) - mc(eps - step[0], nu - step[1])) / (2 * h)
        np.testing.assert_allclose(fd_mc, rev[:, j], rtol=1e-5, atol=1e-9)
        fd_m = (moments(eps + step[0], nu + step[1]) - moments(eps - step[0], nu - step[1])) / (2 * h)
        np.testing.assert_allclose(fd_m, m_rev[:, j], rtol=1e-6, atol=1e-9)
    assert np.all(np.abs(m_rev - rev) <= 4 * se), (m_rev, rev, se)


def test_stationary_drift_formulas_on_the_ball():
    """Stationary regime of u: Λ₀ = 0, L = I; K_xx(t) = 2(g/4ε)[t/(2ε) − (1 − e^{−2εt})/(4ε²)] from a stationary
    start, Green–Kubo D = g/(8ε²)."""
    eps, nu = 0.8, 1.4
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    g = nu * float(scene.params.delta) ** 2
    stat = stationary_drift(scene.build(), jnp.zeros(4), t_relax=6.0, dt=0.01)
    assert stat.names == ("x", "y") and stat.moments.names == ("u_x", "u_y")
    np.testing.assert_allclose(stat.moments.cov, g / (4 * eps) * np.eye(2), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(stat.rate, 0.0, atol=1e-15)
    np.testing.assert_allclose(stat.gain, np.eye(2), atol=1e-15)
    np.testing.assert_allclose(stat.diffusion, g / (8 * eps**2) * np.eye(2), rtol=1e-12, atol=1e-15)
    ts = jnp.linspace(0.0, 4.0, 9)
    np.testing.assert_allclose(
        stat.velocity_autocorrelation(ts)[:, 0, 0], g / (4 * eps) * np.exp(-2 * eps * ts), rtol=1e-12
    )
    exact = 2 * g / (4 * eps) * (ts / (2 * eps) - (1 - np.exp(-2 * eps * ts)) / (4 * eps**2))
    stats = stat.statistics(ts)
    assert isinstance(stats, DriftStatistics)
    np.testing.assert_allclose(stats.fluctuation[:, 0, 0], exact, rtol=1e-10, atol=1e-15)


def test_green_kubo_diffusion_is_the_slope_of_the_fluctuation_drift():
    """Ball: the moment method's Green–Kubo D = g/(8ε²) and the Monte-Carlo Green–Kubo integral of the velocity
    autocorrelation against the Monte-Carlo slope ½ dK_xx/dt, all within Monte-Carlo error."""
    eps, nu = 1.0, 1.0
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    system = scene.build()
    g = nu * float(scene.params.delta) ** 2
    exact = g / (8 * eps**2)
    d_gk = stationary_drift(system, jnp.zeros(4), t_relax=5.0, dt=0.01).diffusion
    np.testing.assert_allclose(d_gk, exact * np.eye(2), rtol=1e-12, atol=1e-15)
    ens = nhsde.simulate(
        system,
        jnp.zeros(4),
        jax.random.key(2),
        n_paths=2048,
        t1=8.0,
        dt=0.01,
        solver="sra1",
        save=nhsde.Save(n=81, paths=True),
    )
    slope, slope_se = _slope(ens, t_from=3.0, names=("x", "y"))
    assert np.all(np.abs(slope.mean(0) - exact) <= 4 * slope_se), (slope.mean(0), slope_se)
    np.testing.assert_allclose(np.diag(effective_diffusion(ens, t_from=3.0))[:2], slope.mean(0), rtol=1e-9)
    gk = green_kubo(system, ens, t_from=3.0, max_lag=2.5)  # C(τ) ∝ e^{−2ετ}: the tail beyond 2.5 is e^{−5}
    assert gk.names == ("x", "y")
    assert np.all(np.abs(np.diag(gk.diffusion) - exact) <= 4 * np.diag(gk.diffusion_se) + exact * np.exp(-5.0))


@pytest.mark.slow
def test_green_kubo_from_paths_on_the_nonlinear_sleigh():
    """The Monte-Carlo Green–Kubo integral of the velocity autocorrelation against the slope of K from the same
    paths, compared path by path (their difference has its own standard error)."""
    sleigh = ChaplyginSleigh(eps=0.5, nu=4.0)
    system = sleigh.build()
    ens = nhsde.simulate(
        system,
        sleigh.initial_state().astype(jnp.float64),
        jax.random.key(0),
        n_paths=1024,
        t1=40.0,
        dt=0.02,
        solver="sra1",
        save=nhsde.Save(n=201, paths=True),
    )
    gk = green_kubo(system, ens, t_from=8.0, max_lag=8.0)
    slope, _ = _slope(ens, t_from=8.0, names=("x", "y"))
    per_path_gk = _green_kubo_per_path(system, ens, t_from=8.0, max_lag=8.0)
    np.testing.assert_allclose(per_path_gk.mean(0), np.diag(gk.diffusion), rtol=1e-10)
    diff = per_path_gk.sum(1) - slope.sum(1)  # D_xx + D_yy, path by path
    assert abs(diff.mean()) <= 4 * diff.std() / math.sqrt(diff.size), (per_path_gk.mean(0), slope.mean(0))
    assert np.all(np.diag(gk.diffusion) > 10 * np.diag(gk.diffusion_se))


def _slope(ens, t_from, names):
    """Per-path terms of the least-squares slope of ½ K(t) over save times ≥ t_from, and its standard error."""
    ts = np.asarray(ens.ts)
    idx = [ens.names.index(n) for n in names]
    x = np.asarray(ens.paths)[:, :, idx]
    w = ts >= t_from
    c = (ts[w] - ts[w].mean()) / np.sum((ts[w] - ts[w].mean()) ** 2)
    xc = x[:, w] - x[:, w].mean(0)
    s = np.einsum("i,pik->pk", c, xc**2) * x.shape[0] / (x.shape[0] - 1) / 2
    return s, s.std(0) / math.sqrt(s.shape[0])


def _green_kubo_per_path(system, ens, t_from, max_lag):
    """Independent re-computation of each path's Green–Kubo integral (NumPy, trapezoid rule)."""
    ts = np.asarray(ens.ts)
    w = ts >= t_from
    y = np.asarray(ens.paths)[:, w]
    v = np.stack([y[..., 3] * np.cos(y[..., 2]), y[..., 3] * np.sin(y[..., 2])], -1)  # Λ = (v cos θ, v sin θ)
    v = v - v.mean(0)
    h = ts[1] - ts[0]
    n_lag = round(max_lag / h)
    n_origin = v.shape[1] - n_lag
    c = np.stack(
        [np.einsum("pnk,pnk->pk", v[:, j : j + n_origin], v[:, :n_origin]) / n_origin for j in range(n_lag + 1)]
    )
    weights = np.full(n_lag + 1, h)
    weights[[0, -1]] = h / 2
    return np.einsum("j,jpk->pk", weights, c)


def _free_particle():
    """q̇ = p, ṗ = −2p + V with q an independent coordinate: p is stationary, q is not."""
    return nhsde.StochasticSystem(
        drift_fn=lambda t, y, p: jnp.stack([y[1], -2 * y[1]]),
        diffusion_fn=lambda t, y, p: jnp.eye(2, 1, -1, dtype=y.dtype),
        params={},
        layout=nhsde.StateLayout(("q", "p"), ("independent_coordinate", "momentum")),
        noise_dim=1,
        additive_noise=True,
    )


@pytest.mark.parametrize(
    "call, exc, match",
    [
        (
            lambda: stationary_drift(_free_particle(), jnp.zeros(2), t_relax=1.0, dt=0.1),
            ValueError,
            r"no stationary regime",
        ),
        (
            lambda: normal_approximation(BallOnVibratingPlane().build(), jnp.zeros(4), -jnp.eye(4), t1=1.0, dt=0.1),
            ValueError,
            r"cov0 must be a finite, symmetric, positive semi-definite matrix",
        ),
        (
            lambda: normal_approximation(BallOnVibratingPlane().build(), jnp.zeros(3), t1=1.0, dt=0.1),
            ValueError,
            r"y0 has shape \(3,\); expected \(4,\)",
        ),
        (
            lambda: normal_approximation(BallOnVibratingPlane().build(), jnp.zeros(4), t1=1.0, dt=0.1, order=0),
            ValueError,
            r"order=0; must be ≥ 1",
        ),
        (
            lambda: normal_approximation(
                BallOnVibratingPlane(angular_velocity=True).build(),
                jnp.zeros(4),
                t1=1.0,
                dt=0.1,
                save=nhsde.Save(names=("omega_x",)),
            ),
            ValueError,
            r"'omega_x' is not a state component",
        ),
        (
            lambda: normal_approximation(BallOnVibratingPlane().build(), [0, 1j, 0, 0], t1=1.0, dt=0.1),
            TypeError,
            r"y0 has dtype complex128; expected real values",
        ),
        (
            lambda: normal_approximation(
                BallOnVibratingPlane().build(), jnp.zeros(4), cov0=np.eye(4) * (1 + 1j), t1=1.0, dt=0.1
            ),
            TypeError,
            r"cov0 has dtype complex\d+; expected real values",
        ),
        (
            lambda: normal_approximation(
                BallOnVibratingPlane().build(), jnp.zeros(4), t1=1.0, dt=0.1, save=nhsde.Save(paths=True)
            ),
            ValueError,
            r"moments only, no paths",
        ),
        (
            lambda: green_kubo(
                BallOnVibratingPlane().build(),
                nhsde.simulate(
                    BallOnVibratingPlane().build(), jnp.zeros(4), jax.random.key(0), n_paths=64, t1=1.0, dt=0.1
                ),
                t_from=0.5,
                max_lag=0.2,
            ),
            ValueError,
            r"Save\(paths=True\)",
        ),
    ],
)
def test_bad_input_is_refused(call, exc, match):
    with pytest.raises(exc, match=match):
        call()
