"""Extremes matrix: ε ∈ {0, 1e-6, 1, 1e3} × ν ∈ {0, 1e-8, 1, 1e4}, long horizons, float32 and float64.

Expected behaviour, asserted below for the ball on the vibrating plane (S0 (3.1)),
from rest with velocity u0 = (1, −1):
- ν = 0: every path is the deterministic solution u = u0 e^{−2εt},
  x = u0 t (1 − e^{−2εt})/(2εt); covariances are exactly 0; ∂/∂ε is finite and
  analytic; ∂/∂ν at ν = 0 is singular per path and raises a clear error.
- ν > 0: covariances equal the closed forms (linear in ν: the same relative
  accuracy at ν = 1e-8 and 1e4) within 4 Monte-Carlo standard errors.
- ε = 0: energy E|u|² grows at the rate the noise predicts, 2νδ² per unit
  time (k_uu = νδ²t per axis); ε = 1e-6 is indistinguishable from it.
- ε = 1e3: stiff; the exponential solver is stable at ε·dt = 10 and the
  ensemble is checked at εdt = 0.01 where its bias (≤ (εdt)²/3) is negligible.
- float32: the deterministic part is exact up to rounding accumulated over the
  steps (≤ 10·steps·2⁻²⁴ relative); a position covariance is asserted only where
  its fluctuation exceeds the rounding walk of the position itself
  (√k_xx > 100·√steps·2⁻²⁴·|x|) — at ε = 1e3, ν = 1e-8 it does not (fluctuations
  are 1e-5 of the mean position), and float64 is the precision to use there.
- Long horizon: 1e6 steps run in memory independent of the number of steps.
Every cell of the matrix (32) runs in the default suite with 4096 paths; ε and ν
are parameter leaves, so the cells of one dtype and one step share a compiled program.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ball_covariances

EPS = [0.0, 1e-6, 1.0, 1e3]
NU = [0.0, 1e-8, 1.0, 1e4]
U0 = np.array([1.0, -1.0])


def horizon(eps):
    """Up to 20 relaxation times 1/(2ε), at most t = 1; 100 steps with εdt ≤ 0.01."""
    t1 = 1.0 if eps <= 1.0 else 20.0 / eps
    steps = max(100, int(round(t1 * eps / 0.01)))
    return t1, t1 / steps


def run(eps, nu, dtype, n_paths=4096):
    t1, dt = horizon(eps)
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    y0 = jnp.array([0.0, 0.0, *U0], dtype)
    return nhsde.simulate(
        scene.build(),
        y0,
        jax.random.key(5),
        n_paths=n_paths,
        t1=t1,
        dt=dt,
        solver="exponential",
        save=nhsde.Save(n=5),
    )


def deterministic(eps, t):
    s = 2 * eps * t
    phi = np.where(s > 0, -np.expm1(-s) / np.where(s > 0, s, 1.0), 1.0)
    return np.outer(t * phi, U0), np.outer(np.exp(-s), U0)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("nu", NU)
@pytest.mark.parametrize("eps", EPS)
def test_extremes_matrix(eps, nu, dtype):
    ens = run(eps, nu, dtype)
    assert int(ens.n_failed) == 0
    ts = np.asarray(ens.ts, np.float64)
    x, u = deterministic(eps, ts)
    t1, dt = horizon(eps)
    steps = round(t1 / dt)
    unit = 2.0**-24 if dtype == jnp.float32 else 2.0**-53
    rtol = max(10 * steps * unit, 1e-10)
    if nu == 0.0:
        np.testing.assert_allclose(ens.mean[:, :2], x, rtol=rtol, atol=rtol)
        np.testing.assert_allclose(ens.mean[:, 2:], u, rtol=rtol, atol=1e-30)
        assert float(jnp.max(jnp.abs(ens.cov))) == 0.0
        return
    k_xx, k_xu, k_uu = ball_covariances(ts, eps, nu, 1 / 1.4)
    entries = [((2, 2), k_uu), ((3, 3), k_uu)]
    if np.sqrt(k_xx[-1]) > 100 * np.sqrt(steps) * unit * abs(x[-1, 0]):
        entries += [((0, 0), k_xx), ((0, 2), k_xu)]
    for (i, j), exact in entries:
        err = np.abs(np.asarray(ens.cov[1:, i, j], np.float64) - np.asarray(exact)[1:])
        assert np.all(err <= 4 * np.asarray(ens.cov_se[1:, i, j], np.float64)), (eps, nu, i, j, err / exact[1:])
    # the mean follows the deterministic solution within its error
    mean_err = np.abs(np.asarray(ens.mean[1:, 2:], np.float64) - u[1:])
    assert np.all(mean_err <= 4 * np.asarray(ens.mean_se[1:, 2:], np.float64) + rtol)


def test_zero_friction_energy_grows_at_the_noise_rate():
    """ε = 0: E|u|²(t) = |u0|² + 2νδ² t (Itô), to within Monte-Carlo error."""
    nu = 1.0
    ens = run(0.0, nu, jnp.float64)
    energy = np.sum(np.diagonal(ens.cov, axis1=1, axis2=2)[:, 2:] + ens.mean[:, 2:] ** 2, axis=1)
    ts = np.asarray(ens.ts)
    expected = np.sum(U0**2) + 2 * nu * (1 / 1.4) ** 2 * ts
    se = np.sqrt(
        np.sum(np.diagonal(ens.cov_se, axis1=1, axis2=2)[:, 2:] ** 2, axis=1)
        + 4 * np.sum((ens.mean[:, 2:] * ens.mean_se[:, 2:]) ** 2, axis=1)
    )
    assert np.all(np.abs(energy - expected)[1:] <= 4 * se[1:])


def test_gradients_at_zero_noise():
    """∂/∂ε at ν = 0 is the deterministic sensitivity; ∂/∂ν at ν = 0 raises (paths ∝ √ν)."""

    def mean_x(eps, nu):
        return run(eps, nu, jnp.float64, n_paths=64).mean[-1, 0]

    t = 1.0
    # x(t) = u0 (1 − e^{−2εt})/(2ε);  ∂x/∂ε = u0 [2t e^{−2εt}·2ε − 2(1 − e^{−2εt})]/(4ε²) at ε = 1
    eps = 1.0
    exact = U0[0] * (4 * eps * t * np.exp(-2 * eps * t) - 2 * (1 - np.exp(-2 * eps * t))) / (4 * eps**2)
    np.testing.assert_allclose(jax.grad(mean_x)(eps, 0.0), exact, rtol=1e-9)
    np.testing.assert_allclose(jax.jacfwd(mean_x)(eps, 0.0), exact, rtol=1e-9)
    with pytest.raises(Exception, match="at nu = 0 is singular"):
        jax.grad(mean_x, argnums=1)(eps, 0.0)

    def k_xx(nu):  # 64 paths, as above: the reverse program of the ν tangent compiled for the refusal is reused
        return run(1.0, nu, jnp.float64, n_paths=64).cov[-1, 0, 0]

    # just above zero the derivative is finite and equals k/ν (covariances are linear in ν, path by path)
    np.testing.assert_allclose(jax.grad(k_xx)(1e-8), k_xx(1e-8) / 1e-8, rtol=1e-8)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_long_horizon_bounded_memory(dtype):
    """1e6 steps: finite, stationary k_uu = νδ²/(4ε) within MC error, memory independent of steps."""
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0, drift=False)
    system, y0 = scene.build(), scene.initial_state().astype(dtype)
    ens = nhsde.simulate(system, y0, jax.random.key(8), n_paths=64, t1=1e4, dt=0.01, save=nhsde.Save(n=11))
    assert int(ens.n_failed) == 0
    # Euler–Maruyama's own stationary variance: σ²h/(1 − (1 − 2εh)²) = σ²/(4ε(1 − εh))
    exact = (1 / 1.4) ** 2 / (4 * (1 - 1.0 * 0.01))
    pooled = np.mean(np.asarray(ens.cov[1:, 0, 0], np.float64))
    se = np.mean(np.asarray(ens.cov_se[1:, 0, 0], np.float64)) / np.sqrt(
        10
    )  # 10 save times ~1000 relaxation times apart
    assert abs(pooled - exact) <= 4 * se

    def temp_bytes(n_steps):
        def run(y):
            ens = nhsde.simulate(
                system,
                y,
                jax.random.key(0),
                n_paths=64,
                t1=n_steps * 0.01,
                dt=0.01,
                save=nhsde.Save(n=11),
                batching=nhsde.Batching(devices=jax.devices()[:1], checkpoint=True),
            )
            return ens.mean

        return jax.jit(run).lower(y0).compile().memory_analysis().temp_size_in_bytes

    # both poll for Ctrl-C in groups of 1024 steps (10⁴ and 10⁵ steps per save interval); a run with fewer steps
    # per interval than a group has no group loop at all, a constant 416 bytes less, not a growth with the steps
    assert temp_bytes(1_000_000) == temp_bytes(100_000)
