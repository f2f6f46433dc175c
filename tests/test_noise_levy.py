"""Jump drivers (S0 (1.3)–(1.4)): exact compound-Poisson increments, Poisson- and Lévy-driven balls, bad input."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import nhsde
from nhsde.noise import CompoundPoisson, Levy, NormalJumps, ParetoJumps, Wiener, driver_intensity
from nhsde.scenes import BallOnVibratingPlane, ball_covariances
from nhsde.statistics import normal_approximation

LAWS = {
    "normal": NormalJumps(mean=0.4, std=0.3),  # closed-form sums; E c ≠ 0 tests the compensator
    "pareto": ParetoJumps(scale=0.5, tail=12.0),  # masked sums of max_jumps draws; heavy tail
}


@eqx.filter_jit
def _block_increments(driver, keys, step, dt, substeps):
    return jax.vmap(lambda k: driver.block_increment(k, jnp.int32(0), step, dt, (2,), substeps, None))(keys)


def increments(driver, n_blocks, dt=0.05, substeps=4, step=3):
    """Increments of ``n_blocks × BLOCK`` lanes × 2 channels over fixed step ``step`` of ``substeps`` base steps."""
    keys = jax.vmap(lambda b: jax.random.fold_in(jax.random.key(0), b))(jnp.arange(n_blocks))
    return np.asarray(_block_increments(driver, keys, jnp.int32(step), jnp.float64(dt), substeps)).reshape(-1)


@pytest.mark.parametrize("name", list(LAWS))
def test_increments_have_the_exact_compound_poisson_law(name):
    """Raw moments 1–4 of the centred increment: κ_j = λh E[c^j] (j ≥ 2), κ₁ = 0; the no-jump atom e^{−λh}."""
    law, lam, h = LAWS[name], 3.0, 0.2
    x = increments(CompoundPoisson(law=law, intensity=lam), n_blocks=2048)
    c = [float(law.moment(j)) for j in range(1, 5)]
    k2, k3, k4 = (lam * h * c[j] for j in (1, 2, 3))
    exact = {1: 0.0, 2: k2, 3: k3, 4: k4 + 3 * k2**2}
    for j, value in exact.items():
        se = np.std(x**j) / math.sqrt(x.size)
        assert abs(np.mean(x**j) - value) <= 4 * se, (name, j, np.mean(x**j), value, se)
    # no jump in the step: the increment is exactly minus the compensator
    atom = np.mean(np.isclose(x, -lam * h * c[0], rtol=0, atol=1e-12))
    p = math.exp(-lam * h)
    assert abs(atom - p) <= 4 * math.sqrt(p * (1 - p) / x.size)
    # a pure function of (block key, step): what makes simulate's paths deterministic and chunk-independent
    driver = CompoundPoisson(law=law, intensity=lam)
    assert np.array_equal(increments(driver, 2048), x)
    assert not np.array_equal(increments(driver, 2048, step=4), x)


def test_levy_is_the_wiener_path_plus_the_jumps_of_the_same_key():
    jumps = CompoundPoisson(law=LAWS["normal"], intensity=2.0)
    w = increments(Wiener(), 4)
    np.testing.assert_allclose(increments(Levy(jumps), 4), w + increments(jumps, 4), rtol=0, atol=1e-15)
    assert np.array_equal(increments(Levy(CompoundPoisson(law=LAWS["normal"], intensity=0.0)), 4), w)
    # a coarse step (4 base steps) is the sum of its base steps: coarse and fine solves share one path
    fine = sum(increments(jumps, 4, substeps=1, step=k) for k in range(12, 16))
    np.testing.assert_allclose(increments(jumps, 4), fine, rtol=0, atol=1e-14)
    assert np.mean(increments(jumps, 4) != -2.0 * 0.2 * 0.4) > 0.2  # jumps do occur


def test_count_truncation_is_explicit_and_enforced():
    driver = CompoundPoisson(law=LAWS["normal"], intensity=5.0, max_jumps=6)
    for dt in (0.01, 0.1):
        np.testing.assert_allclose(driver.neglected_probability(dt), scipy.stats.poisson.sf(6, 5.0 * dt), rtol=1e-10)
    increments(driver, 1, dt=0.01)  # P(N > 6) ≈ 2e-12·… per step: allowed
    with pytest.raises(
        (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError),
        match=r"more than max_jumps=6 jumps in one step has probability",
    ):
        increments(driver, 1, dt=0.1)


def poisson_ball(driver, eps=1.0, nu=0.5):
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    return scene, dataclasses.replace(scene.build(), noise=driver)


@pytest.mark.parametrize("kind", ["poisson", "levy"])
def test_jump_driven_ball_covariances_grow_with_the_intensity_of_1_4(kind):
    """Linear system: second moments depend on W only through ν = ν₀ + λE[c²] (1.4), so the closed forms hold
    with ν·(λE[c²]) (Poisson) or ν·(1 + λE[c²]) (Lévy); the moment equations (Poisson) reproduce them to 1e-10."""
    law, lam = LAWS["normal"], 3.0
    jumps = CompoundPoisson(law=law, intensity=lam)
    driver = jumps if kind == "poisson" else Levy(jumps)
    rate = lam * float(law.moment(2)) + (kind == "levy")
    np.testing.assert_allclose(driver_intensity(driver, 2), [rate, rate], rtol=1e-15)
    scene, system = poisson_ball(driver)
    y0 = scene.initial_state().astype(jnp.float64)
    ens = nhsde.simulate(system, y0, jax.random.key(1), n_paths=4096, t1=2.0, dt=0.004, save=nhsde.Save(n=5))
    delta = float(scene.params.delta)
    k_xx, k_xu, k_uu = ball_covariances(ens.ts, 1.0, 0.5 * rate, delta)
    for (i, j), exact in [((0, 0), k_xx), ((0, 2), k_xu), ((2, 2), k_uu), ((3, 3), k_uu)]:
        err = np.abs(np.asarray(ens.cov[1:, i, j]) - np.asarray(exact[1:]))
        assert np.all(err <= 4 * np.asarray(ens.cov_se[1:, i, j])), (kind, i, j, err, ens.cov_se[1:, i, j])
    assert np.all(np.abs(ens.mean[1:]) <= 4 * ens.mean_se[1:])  # centred although E c ≠ 0
    if kind == "poisson":
        moments = normal_approximation(system, y0, t1=2.0, dt=0.01, save=nhsde.Save(n=5))
        for (i, j), exact in [((0, 0), k_xx), ((0, 2), k_xu), ((2, 2), k_uu)]:
            np.testing.assert_allclose(moments.cov[:, i, j], exact, rtol=1e-10, atol=1e-14)


def test_poisson_ball_is_not_gaussian():
    """Fourth cumulant of u(t): κ₄ = λ E[c⁴] (√ν δ)⁴ (1 − e^{−8εt})/(8ε); Gaussian noise would give 0."""
    law, lam, eps, nu, t1 = NormalJumps(std=0.8), 2.0, 1.0, 0.5, 1.0
    scene, system = poisson_ball(CompoundPoisson(law=law, intensity=lam), eps, nu)
    ens = nhsde.simulate(
        system,
        scene.initial_state().astype(jnp.float64),
        jax.random.key(2),
        n_paths=8192,
        t1=t1,
        dt=0.002,
        save=nhsde.Save(names=("u_x", "u_y"), n=2, paths=True),
    )
    u = np.asarray(ens.paths[:, -1, :]).reshape(-1)  # the two axes are independent copies
    m2, m4 = np.mean(u**2), np.mean(u**4)
    k4 = m4 - 3 * m2**2
    influence = u**4 - 6 * m2 * u**2  # delta method for m4 − 3 m2²
    se = np.std(influence) / math.sqrt(u.size)
    g = math.sqrt(nu) * float(scene.params.delta)
    exact = lam * float(law.moment(4)) * g**4 * (1 - math.exp(-8 * eps * t1)) / (8 * eps)
    assert abs(k4 - exact) <= 4 * se, (k4, exact, se)
    assert exact > 10 * se


def test_gradients_through_jump_paths():
    """Pathwise derivatives in ε and ν (the jumps do not depend on them): ∂k_uu/∂ν = k_uu/ν, ∂k_uu/∂ε < 0."""
    law = NormalJumps(std=0.5)

    def k_uu(eps, nu):
        scene = BallOnVibratingPlane(eps=eps, nu=nu, drift=False)
        system = dataclasses.replace(scene.build(), noise=Levy(CompoundPoisson(law=law, intensity=4.0)))
        k = nhsde.simulate(system, jnp.zeros(2), jax.random.key(3), n_paths=128, t1=0.5, dt=0.01).cov[-1, 0, 0]
        return k, k

    (d_eps, d_nu), k = jax.jacfwd(k_uu, argnums=(0, 1), has_aux=True)(jnp.float64(1.0), jnp.float64(0.7))
    np.testing.assert_allclose(d_nu, k / 0.7, rtol=1e-10)
    assert d_eps < 0


@pytest.mark.parametrize(
    "make, exc, match",
    [
        (lambda: CompoundPoisson(law=NormalJumps(), intensity=-1.0), ValueError, r"intensity=-1.0 .*≥ 0"),
        (lambda: CompoundPoisson(law=NormalJumps(), intensity=math.nan), ValueError, r"intensity=nan .*finite"),
        (lambda: ParetoJumps(tail=2.0), ValueError, r"tail=2.0 gives a jump law without finite variance"),
        (lambda: ParetoJumps(tail=1.5), ValueError, r"without finite variance"),
        (lambda: NormalJumps(std=-0.1), ValueError, r"std=-0.1 .*≥ 0"),
        (lambda: CompoundPoisson(law=0.5), TypeError, r"law=0.5; expected a jump law"),
        (
            lambda: CompoundPoisson(law=NormalJumps(), max_jumps=0),
            ValueError,
            r"max_jumps=0; must be a whole number ≥ 1",
        ),
        (lambda: Levy(NormalJumps()), TypeError, r"expected nhsde.noise.CompoundPoisson"),
    ],
)
def test_bad_jump_drivers_are_refused(make, exc, match):
    with pytest.raises(exc, match=match):
        make()


def test_traced_negative_intensity_fails_at_run_time():
    def f(lam):
        _, system = poisson_ball(CompoundPoisson(law=NormalJumps(), intensity=lam))
        return nhsde.simulate(system, jnp.zeros(4), jax.random.key(0), n_paths=64, t1=0.1, dt=0.01).cov[-1, 0, 0]

    with pytest.raises((eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError), match="intensity must be finite and ≥ 0"):
        jax.jit(f)(-1.0)


@pytest.mark.parametrize("solver", ["heun", "milstein", "sra1", "exponential"])
def test_jump_systems_take_only_euler(solver):
    """S0 §2, Remark: with jumps the Stratonovich shortcut (and higher-order schemes) fail."""
    _, system = poisson_ball(CompoundPoisson(law=NormalJumps(), intensity=1.0))
    with pytest.raises(ValueError, match=rf"solver='{solver}' does not apply to a system driven by jumps; use 'euler'"):
        nhsde.simulate(system, jnp.zeros(4), jax.random.key(0), n_paths=64, t1=0.1, dt=0.01, solver=solver)
    with pytest.raises(ValueError, match="no Stratonovich form"):
        system.converted("stratonovich")
    stratonovich = dataclasses.replace(system, interpretation="stratonovich")
    with pytest.raises(ValueError, match="no Stratonovich form"):
        nhsde.simulate(stratonovich, jnp.zeros(4), jax.random.key(0), n_paths=64, t1=0.1, dt=0.01)
