"""One call to a requested accuracy: ``to_accuracy`` picks the cheapest estimator a pilot predicts; ``--rmse``.

Exact values are the ball's closed forms, S0 (3.1); tolerances come from the
requested RMSE and a stated confidence (χ² bound on the realised mean-square error).
"""

import dataclasses
import json
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from test_noise_ito_stratonovich import gbm_stratonovich
from test_qmc import euler_cov

import nhsde
from nhsde.noise import CompoundPoisson, NormalJumps
from nhsde.runs import ConfigError, RunConfig, main
from nhsde.scenes import BallOnVibratingPlane, ChaplyginBall, ball_covariances
from nhsde.statistics import (
    Multilevel,
    MultilevelEstimate,
    MultilevelQuasiMonteCarlo,
    PlainMonteCarlo,
    QuasiMonteCarlo,
    Richardson,
    multilevel_monte_carlo,
    to_accuracy,
)

DELTA = 1 / 1.4
BALL = BallOnVibratingPlane(eps=1.0, nu=1.0)
Y0 = jnp.zeros(4)
K_XX = float(ball_covariances(jnp.float64(1.0), 1.0, 1.0, DELTA)[0])
# Euler on plain paths only, so that the few compiled programs are shared by every test here (the CLI's pilot
# included); the control variate is exact on the linear ball and would make the accuracy test trivial.  Quasi-Monte
# Carlo has tests of its own (its pilot compiles programs of its own; off here so that these stay fast).
EULER = (PlainMonteCarlo("euler"), Richardson("euler"), Multilevel("euler"))
FAST: dict[str, Any] = dict(t1=1.0, statistic=("cov", "x", "x"), estimators=EULER)
QMC_ON = FAST | dict(estimators=EULER + (QuasiMonteCarlo(),))
QMC_ALONE = dict(estimators=(QuasiMonteCarlo(),))


def test_reaches_the_requested_rmse_on_the_ball():
    """Realised RMSE of K_xx(1) over 4 runs ≤ ε √(χ²_{4, 0.99}/4) (99 % if each run's MSE ≤ ε²); the report
    lists plain, extrapolated and multilevel Monte Carlo, each with a finite cost."""
    eps = 0.08 * K_XX
    runs = [to_accuracy(BALL.build(), Y0, jax.random.key(10 + r), rmse=eps, **FAST) for r in range(4)]
    errors = np.array([r.value()[0] - K_XX for r in runs])
    bound = math.sqrt(scipy.stats.chi2.ppf(0.99, len(runs)) / len(runs))
    assert np.sqrt(np.mean(errors**2)) <= bound * eps, (errors / eps, [r.choice for r in runs])
    r = runs[0]
    names = {a.name for a in r.alternatives}
    assert names == {"plain MC, euler", "extrapolation, euler", "multilevel, euler"}
    assert all(math.isfinite(a.cost) and a.cost > 0 for a in r.alternatives)
    chosen = next(a for a in r.alternatives if a.name == r.choice)
    assert chosen.cost == min(a.cost for a in r.alternatives)
    assert r.cost.path_steps > r.pilot_cost.path_steps > 0 and r.estimated_rmse <= 1.5 * eps
    # honest accounting: the work done is counted, within 2× of the prediction; compile time is part of the seconds
    cost, run, predicted = r.cost, r.run_cost, r.predicted
    assert cost.path_steps == r.pilot_cost.path_steps + run.path_steps
    assert predicted.path_steps / 2 <= run.path_steps <= 2 * predicted.path_steps
    assert (
        0 <= cost.compile_seconds <= cost.seconds and 0 < run.seconds <= cost.seconds and math.isnan(predicted.seconds)
    )
    pilot = r.pilot_cost  # the seconds before the run, compilation of the pilots included
    assert 0 <= pilot.compile_seconds <= pilot.seconds and pilot.seconds + run.seconds <= cost.seconds
    assert f"measured {run.path_steps:.3g} in " in r.report() and "s of it compiling" in r.report()
    text = str(r)
    assert "chosen: " + r.choice in text and "multilevel, euler" in text


def test_derivatives_with_standard_errors_on_the_ball():
    """``wrt=``: ∂K_xx(1)/∂(ε, ν) from the chosen estimator's per-path tangents are within 4 SE (99.99 %) of the
    closed form's derivatives (``jax.jacfwd`` of ``ball_covariances``), and the report prints them."""
    exact = jax.jacfwd(lambda th: ball_covariances(jnp.float64(1.0), th[0], th[1], DELTA)[0])(jnp.array([1.0, 1.0]))
    r = to_accuracy(BALL.build(), Y0, jax.random.key(20), rmse=0.08 * K_XX, wrt=("eps", "nu"), **FAST)
    d, d_se = r.derivative()
    assert r.wrt == ("eps", "nu") and d.shape == d_se.shape == (2,)
    assert np.all(d_se > 0) and np.all(np.abs(d - np.asarray(exact)) <= 4 * d_se), (d, d_se, exact)
    assert f"d/deps = {d[0]:.6g} ± " in r.report()


def test_quasi_monte_carlo_is_priced_and_reaches_the_target_on_the_ball():
    """The report lists quasi-Monte Carlo (Euler) with a finite predicted work, its cost ratio κ measured, its pilot
    counted.  Forced (quasi-Monte Carlo alone, which makes the same plan from the same key), K_xx(1) is within 3
    target RMSEs of the closed form (Chebyshev: ≥ 89 % if its MSE ≤ ε²), its standard error below the target, its
    work the path-steps it ran, within the plan's cap, and its derivatives in (ε, ν), from the same points' tangents,
    within 4 SE (99.99 %) of the Euler chain's at its step."""
    eps = 0.08 * K_XX
    wrt = ("eps", "nu")
    r = to_accuracy(BALL.build(), Y0, jax.random.key(20), rmse=eps, wrt=wrt, explore=True, **QMC_ON)
    qmc = next(a for a in r.alternatives if a.name == "quasi-Monte Carlo, euler")
    assert qmc.applies and qmc.cost > 0 and isinstance(qmc.estimator, QuasiMonteCarlo), r.report()
    assert "κ = " in qmc.note and qmc.pilot_work > 0 and r.pilot_cost.path_steps >= r.pilot[0].work + qmc.pilot_work
    assert qmc.n_paths[0] % 16 == 0 and qmc.n_paths[0] // 16 >= 64 and (qmc.n_paths[0] // 16).bit_count() == 1
    assert (1.0 / qmc.dt).is_integer() and int(1.0 / qmc.dt).bit_count() == 1
    assert "quasi-Monte Carlo, euler" in r.report()
    # forced: the same key and pilots with quasi-Monte Carlo alone make the same plan, and run it
    only = to_accuracy(BALL.build(), Y0, jax.random.key(20), rmse=eps, wrt=wrt, **(QMC_ON | QMC_ALONE))
    assert only.choice == qmc.name and only.bias == qmc.bias
    assert only.predicted.path_steps == pytest.approx(qmc.cost / qmc.kappa, rel=1e-12)
    result, bias = only.estimate, only.bias
    value, se = result.value(r.statistic)
    work = result.cost.path_steps
    assert isinstance(result, MultilevelEstimate) and result.n_paths_per_level[0] % 16 == 0
    # the work done is counted (its path-steps), at most the plan's cap, not the prediction (κ Euler path-steps each)
    assert work == int(result.n_paths) * round(1.0 / qmc.dt) <= qmc.n_paths[0] * round(1.0 / qmc.dt)
    assert work == only.run_cost.path_steps and bias == qmc.bias
    assert abs(float(value) - K_XX) <= 3 * eps and 0 < float(se) <= eps, (value, se, K_XX, eps)
    # unbiased for the scheme: the Euler chain's derivatives at its step (the target bounds the value's bias only)
    steps = round(1.0 / qmc.dt)
    exact = jax.jacfwd(lambda th: euler_cov(th[0], th[1], DELTA, qmc.dt, steps)[0, 0])(jnp.array([1.0, 1.0]))
    assert result.derivatives is not None and result.derivatives.wrt == wrt
    d, d_se = (np.asarray(a[:, -1, 0, 0]) for a in (result.derivatives.d_cov, result.derivatives.d_cov_se))
    assert d.shape == d_se.shape == (2,) and np.all(d_se > 0)
    assert np.all(np.abs(d - np.asarray(exact)) <= 4 * d_se), (d, d_se, exact)


def test_quasi_monte_carlo_stops_where_its_own_error_meets_the_target():
    """Without ``wrt`` quasi-Monte Carlo doubles its points until its standard error, with a margin of one standard
    error of the 16-scramblings variance estimate, meets the target beside the bias bound at its step
    (``SE² ≤ ε² − (|C| h^p)²``); its plan's count, at the Monte-Carlo rate, is the most it runs.  K_xx(1) of the
    ball is then within 3 target RMSEs (Chebyshev: ≥ 89 %), and the work done is what the report says it did."""
    eps = 0.05 * K_XX
    r = to_accuracy(BALL.build(), Y0, jax.random.key(21), rmse=eps, **(QMC_ON | QMC_ALONE))
    plan = next(a for a in r.alternatives if a.name == r.choice)
    value, se = r.value()
    bound = r.pilot[0].bias_bound * plan.dt
    assert se**2 * (1 + math.sqrt(2 / 15)) <= eps**2 - bound**2 and abs(value - K_XX) <= 3 * eps, r.report()
    steps = round(1.0 / plan.dt)
    assert r.run_cost.path_steps == r.estimate.cost.path_steps <= plan.n_paths[0] * steps, r.report()
    assert "points expected" in plan.note and "at most 16 × " in plan.note


def test_antithetic_quasi_monte_carlo_counts_both_solves_and_reaches_the_target():
    """``QuasiMonteCarlo(antithetic=True)``: each point with its reflection, priced at twice the path-steps per
    point; K_xx(1) of the ball within 3 target RMSEs (Chebyshev) and the work done two solves per point."""
    eps = 0.05 * K_XX
    estimators = (QuasiMonteCarlo(antithetic=True),)
    r = to_accuracy(BALL.build(), Y0, jax.random.key(22), rmse=eps, **(QMC_ON | dict(estimators=estimators)))
    plan = next(a for a in r.alternatives if a.name == r.choice)
    assert r.choice == "quasi-Monte Carlo, euler, antithetic", r.report()
    value, se = r.value()
    assert abs(value - K_XX) <= 3 * eps and 0 < se <= eps, r.report()
    steps = round(1.0 / plan.dt)
    assert r.run_cost.path_steps == 2 * int(r.estimate.n_paths) * steps, r.report()


def test_a_pilot_blown_up_at_the_default_step_is_run_again_from_smaller_steps():
    """Chaplygin's ball (stationary E[H] = 3ν/(8ε)), Euler from its default coarsest step h₀ = 1: at key 1003 the
    pilot's paths grew huge there without overflowing (and were priced from, until a retry from half the step); they
    are failed paths now (a blow-up: the state beyond 10⁴× its largest size two steps running), so the step is
    halved while pilot paths fail (to 1/8), and the answer is within 3 target RMSEs (Chebyshev: ≥ 89 %), the failed
    attempts' work counted."""
    scene = ChaplyginBall(eps=1.0, nu=2.0)
    eps = 0.01 * 3 * 2.0 / 8
    args: dict[str, Any] = dict(t1=4.0, statistic=("mean", "energy"), rmse=eps, estimators=(PlainMonteCarlo("euler"),))
    r = to_accuracy(scene.build(), scene.initial_state().astype(jnp.float64), jax.random.key(1003), **args)
    assert r.pilot[0].dts[0] == 0.125, r.report()
    assert abs(r.value()[0] - 0.75) <= 3 * eps and r.pilot_cost.path_steps > sum(p.work for p in r.pilot), r.report()


def test_quasi_monte_carlo_does_not_apply_off_a_power_of_two():
    """``(t1 − t0)/dt = 3`` steps: quasi-Monte Carlo is listed as not applying, with the reason, and another
    alternative reaches the target."""
    eps = 0.2 * K_XX
    r = to_accuracy(BALL.build(), Y0, jax.random.key(2), rmse=eps, dt=1 / 3, explore=True, **QMC_ON)
    qmc = next(a for a in r.alternatives if a.name == "quasi-Monte Carlo, euler")
    assert qmc.cost == math.inf and not qmc.applies and qmc.note.startswith("does not apply: "), qmc
    assert "not a power of two" in qmc.note and "does not apply" in r.report()
    assert r.choice != qmc.name and abs(r.value()[0] - K_XX) <= 3 * eps


def test_relative_rmse_and_the_budget_guard():
    system = BALL.build()
    r = to_accuracy(system, Y0, jax.random.key(1), relative_rmse=0.1, **FAST)
    assert r.rmse == pytest.approx(0.1 * abs(r.pilot[0].values[-1]))
    assert r.wrt == () and r.derivative()[0].shape == r.derivative()[1].shape == (0,) and "d/d" not in r.report()
    with pytest.raises(ValueError, match="max_path_steps="):
        to_accuracy(system, Y0, jax.random.key(1), rmse=1e-4, max_path_steps=1e6, **FAST)
    with pytest.raises(ValueError, match="relative_rmse="):  # the mean of x is 0 from rest
        to_accuracy(system, Y0, jax.random.key(1), relative_rmse=0.1, **(FAST | dict(statistic=("mean", "x"))))


def test_bad_input_raises_naming_the_argument():
    system, key = BALL.build(), jax.random.key(0)
    base: dict[str, Any] = dict(t1=1.0, statistic=("cov", "x", "x"))
    for rmse in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rmse="):
            to_accuracy(system, Y0, key, rmse=rmse, **base)
        with pytest.raises(ValueError, match="relative_rmse="):
            to_accuracy(system, Y0, key, relative_rmse=rmse, **base)
    with pytest.raises(TypeError, match="exactly one"):
        to_accuracy(system, Y0, key, rmse=0.1, relative_rmse=0.1, **base)
    with pytest.raises(TypeError, match="exactly one"):
        to_accuracy(system, Y0, key, **base)
    for statistic in (("cov", "x", "q"), ("var", "x"), ("mean", "x", "x"), "cov x x"):
        with pytest.raises(ValueError, match="statistic="):
            to_accuracy(system, Y0, key, rmse=0.1, t1=1.0, statistic=statistic)
    with pytest.raises(ValueError, match="statistic="):  # a name the save does not keep
        to_accuracy(system, Y0, key, rmse=0.1, save=nhsde.Save(names=("u_x",)), **base)
    for wrt in (("delta_x",), ("eps", "eps")):
        with pytest.raises(ValueError, match="wrt="):
            to_accuracy(system, Y0, key, rmse=0.1, wrt=wrt, **base)
    with pytest.raises(TypeError, match="wrt="):
        to_accuracy(system, Y0, key, rmse=0.1, wrt=(), **base)
    with pytest.raises(ValueError, match="steps="):
        to_accuracy(system, Y0, key, rmse=0.1, steps=nhsde.AdaptiveSteps(0.25), **base)
    with pytest.raises(ValueError, match="dt="):
        to_accuracy(system, Y0, key, rmse=0.1, dt=0.3, **base)
    with pytest.raises(ValueError, match="solver="):  # three-point increments cannot be coupled
        to_accuracy(system, Y0, key, rmse=0.1, solver="weak2", **base)
    jumps = dataclasses.replace(system, noise=CompoundPoisson(law=NormalJumps(), intensity=1.0))
    with pytest.raises(ValueError, match="solver="):
        to_accuracy(jumps, Y0, key, rmse=0.1, solver=nhsde.PlatenWeak2(increments="gaussian"), **base)
    with pytest.raises(ValueError, match="antithetic=True"):
        to_accuracy(jumps, Y0, key, rmse=0.1, antithetic=True, **base)
    # the estimators: given once, each checked against the system before any solve
    with pytest.raises(TypeError, match="solver='euler' and estimators="):
        to_accuracy(system, Y0, key, rmse=0.1, solver="euler", estimators=EULER, **base)
    for estimators in ((), ("multilevel",), [PlainMonteCarlo, Richardson]):
        with pytest.raises(TypeError, match="estimators="):
            to_accuracy(system, Y0, key, rmse=0.1, estimators=estimators, **base)
    with pytest.raises(ValueError, match="solver='weak2'"):
        to_accuracy(system, Y0, key, rmse=0.1, estimators=(Multilevel("weak2"),), **base)
    with pytest.raises(ValueError, match="weak_order="):
        to_accuracy(system, Y0, key, rmse=0.1, estimators=(Richardson("euler", weak_order=0),), **base)
    with pytest.raises(ValueError, match=r"PlainMonteCarlo\(solver='euler', weak_order=None, antithetic=True\)"):
        to_accuracy(jumps, Y0, key, rmse=0.1, estimators=(PlainMonteCarlo("euler", antithetic=True),), **base)


def test_run_file_accuracy_table_is_checked():
    raw = dict(scene="ball-on-vibrating-plane", solver=dict(dt=0.25, t1=1.0), statistics=dict(save_points=2))
    config = RunConfig.from_dict(raw | dict(accuracy=dict(rmse=0.01)))
    assert config.data["accuracy"]["statistic"] is None and config.data["paths"]["n"] == 4096
    assert "accuracy" not in RunConfig.from_dict(raw | dict(paths=dict(n=64))).data  # plain runs unchanged
    for accuracy, key in [
        (dict(rmse=0.01, relative_rmse=0.1), "accuracy.rmse"),
        (dict(), "accuracy.rmse"),
        (dict(rmse=-1.0), "accuracy.rmse"),
        (dict(rmse=0.01, statistic="cov x q"), "accuracy.statistic"),
        (dict(rmse=0.01, statistic="var x"), "accuracy.statistic"),
        (dict(rmse=0.01, solver="rk4"), "accuracy.solver"),
    ]:
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            RunConfig.from_dict(raw | dict(accuracy=accuracy))


def test_cli_rmse_prints_the_choice_and_value(capsys, tmp_path):
    argv = ["simulate", "ball-on-vibrating-plane", "--t1", "1", "--x64", "--solver", "euler"]
    assert main(argv + ["--rmse", "0.004"]) == 0
    out = capsys.readouterr().out
    assert "K[x,x] = " in out and "±" in out and "chosen: " in out and "path-steps" in out, out
    for method in ("plain MC", "extrapolation", "multilevel"):  # each also with antithetic pairs
        assert f"{method}, euler, antithetic " in out, out
    assert "control variate, euler" in out, out
    value = float(out.split("\nK[x,x] = ")[1].split("±")[0])
    assert abs(value - K_XX) < 5 * 0.004  # 5 target RMSEs: Chebyshev, ≥ 96 %
    # derivatives in eps and nu with their standard errors, within 4 SE (and rounding) of the closed form's
    exact = jax.jacfwd(lambda th: ball_covariances(jnp.float64(1.0), th[0], th[1], DELTA)[0])(jnp.array([1.0, 1.0]))
    for q, want in zip(("eps", "nu"), np.asarray(exact)):
        d, se = (float(x) for x in out.split(f"dK[x,x]/d{q} = ")[1].split("(")[0].split("±"))
        assert abs(d - want) <= 4 * se + 1e-6 * abs(want), (q, d, se, want, out)
    run = tmp_path / "run.toml"
    run.write_text(
        'scene = "ball-on-vibrating-plane"\n[solver]\ndt = 0.25\nt1 = 1.0\n[statistics]\nsave_points = 2\n'
        '[accuracy]\nrmse = 0.004\nsolver = "euler"\n'
    )
    assert main(["simulate", "--config", str(run), "--out", str(tmp_path / "estimate.json")]) == 0
    out = capsys.readouterr().out
    assert "K[x,x] = " in out and "dK[x,x]/deps = " in out and "dK[x,x]/dnu = " in out, out
    stored = json.loads((tmp_path / "estimate.json").read_text())  # --out: the estimate as JSON, as printed
    value, se = (float(x) for x in out.split("\nK[x,x] = ")[1].split("(")[0].split("±"))
    assert stored["format"] == "nhsde-estimate" and stored["statistic"] == "cov x x" and stored["t"] == 1.0
    assert f"{stored['value']: .6g} ± {stored['se']:.2g}" == f"{value: .6g} ± {se:.2g}"
    assert set(stored["derivatives"]) == {"eps", "nu"} and stored["rmse_target"] == 0.004
    for extra, match in [
        (["--rmse", "0"], "--rmse 0"),
        (["--rmse", "0.01", "--relative-rmse", "0.1"], "exactly one"),
        (["--rmse", "0.01", "--statistic", "cov x q"], "--statistic"),
        (["--rmse", "0.01", "--paths", "100"], "--paths cannot be combined"),
        (["--statistic", "cov x x"], "--statistic needs --rmse"),
    ]:
        assert main(argv + extra) == 2, extra
        err = capsys.readouterr().err
        assert match in err, err


@pytest.mark.slow
def test_every_alternative_on_the_ball():
    """The default set: Euler and weak2 (Gaussian), plain, extrapolated, multilevel, antithetic, quasi-Monte Carlo and
    the control variate, which is exact on the linear ball; the estimate is within 3 target RMSEs (Chebyshev:
    ≥ 89 %)."""
    eps = 0.05 * K_XX
    r = to_accuracy(BALL.build(), Y0, jax.random.key(3), t1=1.0, statistic=("cov", "x", "x"), rmse=eps, explore=True)
    assert len(r.alternatives) == 15 and all(math.isfinite(a.cost) for a in r.alternatives), r.report()
    assert {p.solver for p in r.pilot} == {"euler", "weak2-gaussian"}
    assert r.choice == "control variate, euler" and abs(r.value()[0] - K_XX) <= 3 * eps


def test_alternatives_of_several_solvers_are_ranked_by_seconds():
    """Two solvers priced: ``cost='auto'`` ranks by seconds, each alternative's path-steps times its solver's
    seconds per path-step, from one more (timed, counted) run of each solver's pilot; one solver: by path-steps,
    no pilot timed (``test_reaches_the_requested_rmse_on_the_ball``)."""
    eps = 0.1 * K_XX
    both = dict(estimators=(PlainMonteCarlo("euler"), PlainMonteCarlo(nhsde.PlatenWeak2(increments="gaussian"))))
    r = to_accuracy(BALL.build(), Y0, jax.random.key(3), rmse=eps, explore=True, **(FAST | both))
    assert {p.solver for p in r.pilot} == {"euler", "weak2-gaussian"}, r.report()
    rates = {p.solver: p.seconds_per_path_step for p in r.pilot}
    assert all(rate > 0 for rate in rates.values()), rates
    for a in r.alternatives:
        assert a.seconds == pytest.approx(a.cost * rates[a.estimator.candidate.label], rel=1e-12), a
    chosen = next(a for a in r.alternatives if a.name == r.choice)
    assert chosen.seconds == min(a.seconds for a in r.alternatives) and r.predicted.seconds == chosen.seconds
    # each timed pilot ran twice: its work is twice one run's (1024 paths at 4 + 8 + 16 steps)
    assert all(p.work == 2 * 1024 * 28 for p in r.pilot), [p.work for p in r.pilot]
    assert r.pilot_cost.path_steps == sum(p.work for p in r.pilot) and "s), " in r.reason


def test_a_loose_target_is_answered_after_one_compiled_program():
    """By default a further pilot runs only for a run predicted far longer than the first pilot (EXPLORE_ABOVE × its
    path-steps): at a loose target on the ball only the weak-order-2 pilot runs; the other solver's estimators, the
    control variate and quasi-Monte Carlo are listed as not priced with the reason, and the answer is within 3
    target RMSEs (Chebyshev: ≥ 89 %); the rule counts work, so the same key gives the same choice again."""
    eps = 0.1 * K_XX
    r = to_accuracy(BALL.build(), Y0, jax.random.key(4), t1=1.0, statistic=("cov", "x", "x"), rmse=eps)
    assert [p.solver for p in r.pilot] == ["weak2-gaussian"], r.report()
    skipped = {a.name for a in r.alternatives if a.note.startswith("not priced: ")}
    euler = {
        f"{method}, euler{anti}"
        for method in ("plain MC", "extrapolation", "multilevel")
        for anti in ("", ", antithetic")
    }
    own = {"control variate, euler", "quasi-Monte Carlo, euler", "quasi-Monte Carlo, weak2-gaussian"}
    assert skipped == euler | own, r.report()
    assert "explore=True prices it" in r.report() and abs(r.value()[0] - K_XX) <= 3 * eps
    again = to_accuracy(BALL.build(), Y0, jax.random.key(4), t1=1.0, statistic=("cov", "x", "x"), rmse=eps)
    assert again.choice == r.choice and again.value() == r.value()


def test_huge_targets_get_an_answer_and_impossible_ones_a_clear_refusal():
    """``rmse = 1e300``: the smallest run answers (no overflow); a target whose per-path values would not fit in
    memory is refused before it runs, with the size, by ``to_accuracy`` and ``multilevel_monte_carlo``."""
    system, key = BALL.build(), jax.random.key(4)
    r = to_accuracy(system, Y0, key, rmse=1e300, **FAST)
    assert math.isfinite(r.value()[0]) and r.run_cost.path_steps <= 64 * 4 * 3, r.report()
    m = multilevel_monte_carlo(system, Y0, key, rmse=1e300, t1=1.0, dt=0.25, statistic=("cov", "x", "x"))
    assert math.isfinite(float(m.value()[0])) and len(m.n_paths_per_level) == 3
    with pytest.raises(ValueError, match=r"^rmse=1e-08: the cheapest way, .* GiB at their peak, more than the"):
        to_accuracy(system, Y0, key, rmse=1e-8, **FAST)
    with pytest.raises(ValueError, match=r"^rmse=1e-08: the samples per level .* GiB at their peak"):
        multilevel_monte_carlo(system, Y0, key, rmse=1e-8, t1=1.0, dt=0.25, statistic=("cov", "x", "x"))
    with pytest.raises(ValueError, match=r"^n_paths=\(1000000000000,\) keeps per-path values of"):
        multilevel_monte_carlo(system, Y0, key, n_paths=(10**12,), t1=1.0, dt=0.25, statistic=("cov", "x", "x"))
    config = RunConfig.from_dict(
        dict(
            scene="ball-on-vibrating-plane",
            solver=dict(dt=0.25, t1=1.0),
            statistics=dict(save_points=2),
            accuracy=dict(rmse=1e300),
        )
    )
    assert config.data["accuracy"]["rmse"] == 1e300


@pytest.mark.slow
def test_reaches_the_target_from_a_coarsest_step_above_one():
    """h₀ = 2.5 (t1 = 10, the default (t1 − t0)/4), where the bias model's ``h₀^p`` matters (6.25× for weak order
    2): over 20 keys the realised RMSE of K_xx(10) relative to each run's target is within √(χ²_{20, 0.99}/20)
    (99 % if each run's MSE ≤ ε²).  ε = 0.1 keeps Euler stable at h₀ (ε h₀ = 0.25); the closed form is S0 (3.1)."""
    scene = BallOnVibratingPlane(eps=0.1, nu=1.0)
    exact = float(ball_covariances(jnp.float64(10.0), 0.1, 1.0, DELTA)[0])
    solvers = ("euler", nhsde.PlatenWeak2(increments="gaussian"))
    kinds = (PlainMonteCarlo, Richardson, Multilevel)
    plans = tuple(kind(s, antithetic=a) for s in solvers for a in (False, True) for kind in kinds)
    args: dict[str, Any] = dict(t1=10.0, statistic=("cov", "x", "x"), relative_rmse=0.05, estimators=plans)
    runs = [to_accuracy(scene.build(), Y0, jax.random.key(100 + r), **args) for r in range(20)]
    errors = np.array([(r.value()[0] - exact) / r.rmse for r in runs])
    assert all(r.pilot[0].dts[0] == 2.5 for r in runs)
    assert np.sqrt(np.mean(errors**2)) <= math.sqrt(scipy.stats.chi2.ppf(0.99, 20) / 20), (errors, runs[0].report())


def test_the_default_coarsest_step_is_halved_while_the_pilot_blows_up():
    """dy = −y³ dt + dW from y0 = 3 to t1 = 4: Euler (and weak order 2) at the default h₀ = 1, ½ and ¼ overflow within
    a few steps (3 − 27h, then the cube of that), at ⅛ they contract.  The pilot halves h₀ until its paths survive,
    its failed attempts are counted in the work, and the answer meets the target by its own estimate."""
    cubic = nhsde.StochasticSystem(
        drift_fn=lambda t, y, p: -(y**3),
        diffusion_fn=lambda t, y, p: p * jnp.ones((1, 1), y.dtype),
        params=jnp.float32(1.0),
        layout=nhsde.StateLayout(("y",), ("independent_coordinate",)),
        noise_dim=1,
        additive_noise=True,
    )
    eps = 0.05
    r = to_accuracy(cubic, jnp.full(1, 3.0), jax.random.key(6), t1=4.0, statistic=nhsde.statistics.Mean("y"), rmse=eps)
    assert r.pilot[0].dts[0] == 0.125, r.report()
    assert r.pilot_cost.path_steps > sum(p.work for p in r.pilot) and r.estimated_rmse <= 1.5 * eps, r.report()


def test_a_stratonovich_system_is_priced_first_with_heun_which_needs_no_ito_conversion():
    """dX = μX dt + σX ∘ dW (state-dependent noise, Stratonovich form): Euler and weak order 2 step its Itô form (a
    Jacobian of the diffusion per step), Heun's method the system as written, so the default set adds ``heun2``
    and prices its estimators first.  Over 4 keys the realised RMSE of E X(1) against the closed form
    ``e^{(μ + σ²/2)}`` (not the Itô ``e^μ``) is within √(χ²_{4, 0.99}/4) of the target (99 % if each run's
    MSE ≤ ε²)."""
    mu, sigma = -0.5, 0.5
    exact = math.exp(mu + sigma**2 / 2)
    system = gbm_stratonovich(mu, sigma)
    args: dict[str, Any] = dict(t1=1.0, statistic=nhsde.statistics.Mean("x"), relative_rmse=0.02)
    runs = [to_accuracy(system, jnp.ones(1), jax.random.key(40 + r), **args) for r in range(4)]
    assert all(r.pilot[0].solver == "heun2" for r in runs), runs[0].report()
    names = {a.name for a in runs[0].alternatives}
    assert {"plain MC, heun2", "multilevel, heun2", "quasi-Monte Carlo, heun2", "plain MC, euler"} <= names
    errors = np.array([(r.value()[0] - exact) / r.rmse for r in runs])
    assert np.sqrt(np.mean(errors**2)) <= math.sqrt(scipy.stats.chi2.ppf(0.99, 4) / 4), (errors, runs[0].report())
    assert abs(exact - math.exp(mu)) > 5 * runs[0].rmse  # the two calculi are told apart at this target


def test_multilevel_quasi_monte_carlo_is_priced_from_its_pilot_and_reaches_the_target():
    """``MultilevelQuasiMonteCarlo``: its pilot (every pilot level at two point counts) predicts levels and points;
    the run doubles points until its standard error meets the budget left by the bias bound at its finest step.
    K_xx(1) of the ball within 3 target RMSEs (Chebyshev), the levels those planned, each level's points at most the
    planned cap (some doubled beyond the first 64), and the work done within 2× of the predicted."""
    eps = 0.004 * K_XX
    r = to_accuracy(
        BALL.build(), Y0, jax.random.key(23), rmse=eps, **(FAST | dict(estimators=(MultilevelQuasiMonteCarlo(),)))
    )
    plan = next(a for a in r.alternatives if a.name == r.choice)
    assert r.choice == "multilevel quasi-Monte Carlo, euler" and "levels, 16 × [" in plan.note, r.report()
    value, se = r.value()
    assert abs(value - K_XX) <= 3 * eps and 0 < se <= eps, r.report()
    counts = r.estimate.n_paths_per_level
    assert len(counts) == len(plan.n_paths) >= 2 and all(n <= cap for n, cap in zip(counts, plan.n_paths)), r.report()
    assert max(counts) > 16 * 64, counts
    assert r.predicted.path_steps / 2 <= r.run_cost.path_steps <= 2 * r.predicted.path_steps, r.report()


def oscillator(a=1.0, b=4.0, sigma=0.2):
    """dz = A z dt + σ dW with A = [[−a, b], [−b, −a]] (eigenvalues −a ± ib), declared as its linear drift."""
    matrix = lambda p: jnp.array([[-p[0], p[1]], [-p[1], -p[0]]])  # noqa: E731
    return nhsde.StochasticSystem(
        drift_fn=lambda t, z, p: matrix(p) @ z,
        diffusion_fn=lambda t, z, p: p[2] * jnp.eye(2, dtype=z.dtype),
        params=jnp.array([a, b, sigma]),
        layout=nhsde.StateLayout(("x", "y"), ("independent_coordinate",) * 2),
        noise_dim=2,
        additive_noise=True,
        linear_drift=matrix,
    )


def test_a_solver_unstable_at_the_first_pilots_step_does_not_apply():
    """On ż = A z + σẆ with eigenvalues −1 ± 4i at the default h₀ = 1/4: Euler's |1 + λh|² = 1.5625 (unstable),
    weak order 2's (Heun's) |1 + λh + (λh)²/2|² = 0.64.  h₀ stays 1/4 (it was halved to 1/16 for Euler), Euler's
    alternatives are listed as not applying with the stability limit, and E[x(1)] = e^{−1} cos 4 is met."""
    r = to_accuracy(
        oscillator(), jnp.array([1.0, 0.0]), jax.random.key(3), t1=1.0, statistic=("mean", "x"), rmse=0.01, explore=True
    )
    euler = [a for a in r.alternatives if "euler" in a.name and "exponential" not in a.name]
    assert euler and all(
        not a.applies and "does not apply at dt=0.25" in a.note and "unstable" in a.note for a in euler
    )
    assert any(a.applies and a.dt == 0.25 for a in r.alternatives if "weak2" in a.name)
    value, se = r.value()
    assert abs(value - math.exp(-1.0) * math.cos(4.0)) < 4 * math.hypot(se, r.bias), (value, se, r.bias)
