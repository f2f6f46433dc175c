"""Solvers: strong order on the ball, Itô/Stratonovich, adaptive steps, determinism, chunking."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import StateLayout, StochasticSystem
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances

BALL = BallOnVibratingPlane(eps=1.0, nu=1.0)


def strong_slope(system, y0, solver, t1=1.0, n_paths=512):
    """Log–log slope of the RMS error at t1 against a fine SRA1 solve on the same Brownian path."""
    fine = 2.0**-11

    def final(name, dt):
        ens = nhsde.simulate(
            system,
            y0,
            jax.random.key(3),
            n_paths=n_paths,
            t1=t1,
            steps=nhsde.FixedSteps(dt, brownian_dt=fine),
            solver=name,
            save=nhsde.Save(n=2, paths=True),
        )
        return np.asarray(ens.paths[:, -1])

    reference = final("sra1", fine)
    dts = [2.0**-k for k in range(3, 8)]
    errors = [np.sqrt(np.mean(np.sum((final(solver, h) - reference) ** 2, -1))) for h in dts]
    return np.polyfit(np.log(dts), np.log(errors), 1)[0]


# Additive noise: Euler, Milstein and both Heuns have strong order 1.  SRA1 has order 1.5
# in general; with a *linear* drift every Itô–Taylor term it leaves out is of
# mean-square local order ≥ 2.5 (e.g. I_(1,0,0) A²b), so on the ball it is order 2.
# PlatenWeak2 ("weak2") is a weak scheme: its three-point increments make no path converge (tests/test_weak_solver.py).
BALL_ORDER = {"euler": 1.0, "milstein": 1.0, "heun": 1.0, "heun2": 1.0, "sra1": 2.0, "exponential": 1.0}


def test_every_strong_solver_has_its_order_checked():
    assert set(nhsde.SOLVERS) - set(BALL_ORDER) == {"weak2"}


@pytest.mark.parametrize("solver", list(BALL_ORDER))
def test_strong_order_on_the_ball(solver):
    y0 = jnp.array([0.0, 0.0, 1.0, -0.5], jnp.float64)
    slope = strong_slope(BALL.build(), y0, solver)
    assert abs(slope - BALL_ORDER[solver]) <= 0.15, (solver, slope)


@pytest.mark.parametrize("solver", ["euler", "sra1", "exponential"])
def test_strong_order_on_the_nonlinear_sleigh(solver):
    """Nonlinear drift, additive noise: the general orders 1 (Euler) and 1.5 (SRA1)."""
    scene = ChaplyginSleigh(eps=0.1, nu=1.0)
    slope = strong_slope(scene.build(), scene.initial_state().astype(jnp.float64), solver, t1=2.0)
    additive_order = {"euler": 1.0, "sra1": 1.5, "exponential": 1.0}[solver]
    assert abs(slope - additive_order) <= 0.15, (solver, slope)


def gbm(mu=0.3, sigma=0.8):
    """dX = μX dt + σX dW (Itô): E X(t) = X0 e^{μt}; Stratonovich drift (μ − σ²/2) X."""
    return StochasticSystem(
        drift_fn=lambda t, y, p: p["mu"] * y,
        diffusion_fn=lambda t, y, p: p["sigma"] * y[:, None],
        params={"mu": jnp.float64(mu), "sigma": jnp.float64(sigma)},
        layout=StateLayout(("x",), ("independent_coordinate",)),
        noise_dim=1,
    )


def test_ito_stratonovich_conversion_is_the_drift_correction():
    system = gbm()
    strat = system.converted("stratonovich")
    y = jnp.array([1.7])
    np.testing.assert_allclose(strat.drift(0.0, y, system.params), (0.3 - 0.8**2 / 2) * y, rtol=1e-14)
    back = strat.converted("ito")
    np.testing.assert_allclose(back.drift(0.0, y, system.params), 0.3 * y, rtol=1e-14)
    assert system.converted("ito") is system


@pytest.mark.parametrize("solver", ["euler", "milstein", "heun", "heun2"])
def test_every_solver_converges_to_the_ito_solution(solver):
    """The Heun solvers are Stratonovich solvers: simulate converts the Itô system before using it."""
    ens = nhsde.simulate(gbm(), jnp.array([1.0]), jax.random.key(5), n_paths=8192, t1=1.0, dt=2.0**-8, solver=solver)
    err = abs(float(ens.mean[-1, 0]) - np.exp(0.3))
    assert err <= 4 * float(ens.mean_se[-1, 0]), (solver, float(ens.mean[-1, 0]), float(ens.mean_se[-1, 0]))


def test_sra1_refuses_state_dependent_noise():
    with pytest.raises(ValueError, match="additive noise"):
        nhsde.simulate(gbm(), jnp.array([1.0]), jax.random.key(0), n_paths=8, t1=1.0, dt=0.1, solver="sra1")


def test_adaptive_steps_match_closed_form():
    ens = nhsde.simulate(
        BALL.build(),
        BALL.initial_state().astype(jnp.float64),
        jax.random.key(4),
        n_paths=1024,
        t1=2.0,
        steps=nhsde.AdaptiveSteps(0.05, rtol=1e-3, atol=1e-4),
        solver="sra1",
        save=nhsde.Save(n=3),
    )
    k_xx, _, k_uu = ball_covariances(ens.ts, 1.0, 1.0, 1 / 1.4)
    assert np.all(np.abs(ens.cov[1:, 0, 0] - k_xx[1:]) <= 4 * ens.cov_se[1:, 0, 0])
    assert np.all(np.abs(ens.cov[1:, 2, 2] - k_uu[1:]) <= 4 * ens.cov_se[1:, 2, 2])


def run(key=jax.random.key(11), chunk_size=None, n_paths=300, paths=True):
    return nhsde.simulate(
        BALL.build(),
        BALL.initial_state(),
        key,
        n_paths=n_paths,
        t1=1.0,
        dt=0.01,
        batching=nhsde.Batching(chunk_size),
        save=nhsde.Save(paths=paths),
    )


def test_same_key_gives_bitwise_identical_results():
    a, b = run(), run()
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        assert np.array_equal(x, y)
    c = run(key=jax.random.key(12))
    assert not np.array_equal(a.paths, c.paths)


def test_results_independent_of_chunk_size():
    ref = run(chunk_size=64)
    for chunk in (128, 320, 4096):
        other = run(chunk_size=chunk)
        for x, y in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(other)):
            assert np.array_equal(x, y), chunk
    # the first paths do not depend on how many paths are asked for
    more = run(n_paths=700)
    assert np.array_equal(more.paths[:300], ref.paths)
    # and a later piece of the ensemble can be computed on its own
    piece = nhsde.simulate(
        BALL.build(),
        BALL.initial_state(),
        jax.random.key(11),
        n_paths=300,
        t1=1.0,
        dt=0.01,
        save=nhsde.Save(paths=True),
        first_path=128,
    )
    assert np.array_equal(piece.paths[:172], ref.paths[128:])


def test_paths_are_independent():
    ens = run(n_paths=2048, paths=True)
    u = np.asarray(ens.paths[:, -1, 2], np.float64)
    rho = np.corrcoef(u[:-1], u[1:])[0, 1]  # neighbouring lanes share a random block
    assert abs(rho) < 4 / np.sqrt(2048)


class CountingMeter(diffrax.AbstractProgressMeter):
    """Records every tick it receives, from inside the compiled program (as diffrax's meters do)."""

    def init(self):
        return jnp.zeros((), jnp.int32)

    def step(self, state, progress):
        jax.debug.callback(TICKS.append, progress)
        return state + 1

    def close(self, state):
        jax.debug.callback(lambda n: CLOSED.append(int(n)), state)


TICKS: list = []
CLOSED: list = []


@pytest.mark.parametrize("transform", ["none", "jit", "jacfwd"])
def test_progress_meter_receives_every_tick(transform):
    """2 chunks × 5 save intervals = 10 ticks reaching 1, under an outer jit and under jacfwd; reusable."""

    def k_uu(eps):
        scene = BallOnVibratingPlane(eps=eps, drift=False)
        ens = nhsde.simulate(
            scene.build(),
            scene.initial_state(),
            jax.random.key(0),
            n_paths=128,
            t1=0.5,
            dt=0.01,
            save=nhsde.Save(n=6),
            batching=nhsde.Batching(chunk_size=64, devices=jax.devices()[:1]),
            progress_meter=CountingMeter(),
        )
        return ens.cov[-1, 0, 0]

    run = {"none": k_uu, "jit": jax.jit(k_uu), "jacfwd": jax.jacfwd(k_uu)}[transform]
    for _ in range(2):  # the same meter object, twice
        TICKS.clear()
        CLOSED.clear()
        jax.block_until_ready(run(jnp.float64(1.0)))
        jax.effects_barrier()
        progress = np.ravel(np.asarray(TICKS, np.float64))
        assert len(TICKS) == 10, TICKS
        np.testing.assert_allclose(np.unique(progress), np.arange(1, 11) / 10)
        assert CLOSED == [10]


def test_tqdm_progress_meter_runs(capsys):
    ens = nhsde.simulate(
        BALL.build(),
        BALL.initial_state(),
        jax.random.key(0),
        n_paths=64,
        t1=0.5,
        dt=0.01,
        progress_meter=diffrax.TqdmProgressMeter(refresh_steps=1),
    )
    assert int(ens.n_failed) == 0
    assert "100.00%" in capsys.readouterr().err


@pytest.mark.parametrize("solver", [diffrax.ShARK(), diffrax.SlowRK(), diffrax.SEA(), diffrax.StratonovichMilstein()])
def test_any_diffrax_sde_solver_object_converges_to_the_same_statistics(solver):
    """Solvers nhsde never listed, as objects: the ball's exact K_xx, K_uu within 4 SE; needs read from their types."""
    ens = nhsde.simulate(
        BALL.build(),
        BALL.initial_state().astype(jnp.float64),
        jax.random.key(4),
        n_paths=4096,
        t1=2.0,
        dt=0.02,
        solver=solver,
        save=nhsde.Save(n=3),
    )
    assert ens.solver == type(solver).__name__
    k_xx, _, k_uu = ball_covariances(ens.ts, 1.0, 1.0, 1 / 1.4)
    assert np.all(np.abs(ens.cov[1:, 0, 0] - k_xx[1:]) <= 4 * ens.cov_se[1:, 0, 0])
    assert np.all(np.abs(ens.cov[1:, 2, 2] - k_uu[1:]) <= 4 * ens.cov_se[1:, 2, 2])


def test_string_aliases_are_the_solver_objects():
    """'sra1' and diffrax.SRA1() give bitwise the same ensemble; 'euler' and diffrax.Euler() too."""
    for alias, obj in (("sra1", diffrax.SRA1()), ("euler", diffrax.Euler())):
        a, b = (
            nhsde.simulate(BALL.build(), BALL.initial_state(), jax.random.key(1), n_paths=64, t1=0.5, dt=0.05, solver=s)
            for s in (alias, obj)
        )
        assert np.array_equal(a.cov, b.cov) and np.array_equal(a.mean, b.mean)


def test_milstein_steps_a_float32_state_in_float32():
    """diffrax's Milstein built its ``h I`` in float64 (x64 on): a float32 state failed under strict promotion, by
    alias, as an object, and in the warning that lists the solvers fit for a step (Euler at ε·dt = 0.2)."""
    y0 = BALL.initial_state().astype(jnp.float32)

    def run(solver):
        return nhsde.simulate(BALL.build(), y0, jax.random.key(1), n_paths=64, t1=0.4, dt=0.2, solver=solver)

    with pytest.warns(nhsde.StationaryVarianceWarning, match=r"1\.25× the exact one .* or solver='heun2' / "):
        alias, obj, euler = run("milstein"), run(diffrax.ItoMilstein()), run("euler")
    assert alias.mean.dtype == jnp.float32 and np.array_equal(alias.cov, obj.cov)
    # additive noise: Milstein's correction vanishes, so it is Euler–Maruyama up to float32 rounding
    np.testing.assert_allclose(alias.cov, euler.cov, rtol=1e-5, atol=1e-7)


def test_standard_errors_match_the_sample_of_paths():
    """mean_se and cov_se agree with the standard errors computed from the saved paths."""
    ens = nhsde.simulate(
        BALL.build(),
        BALL.initial_state().astype(jnp.float64),
        jax.random.key(9),
        n_paths=4096,
        t1=3.0,
        dt=0.01,
        save=nhsde.Save(n=4, paths=True),
    )
    y = np.asarray(ens.paths, np.float64)  # (paths, n, k)
    d = y - y.mean(0)
    n = y.shape[0]
    np.testing.assert_allclose(ens.mean_se, d.std(0, ddof=1) / np.sqrt(n), rtol=1e-9, atol=1e-15)
    prod = d[:, :, :, None] * d[:, :, None, :]
    np.testing.assert_allclose(ens.cov_se, prod.std(0) / np.sqrt(n), rtol=1e-3, atol=1e-15)
    np.testing.assert_allclose(ens.cov, prod.sum(0) / (n - 1), rtol=1e-9, atol=1e-15)
