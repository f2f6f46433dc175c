"""Internals of the estimators: the bias and work model that plans them (``statistics/_cost.py``), and the keys of
runs beyond the paths one key indexes (``statistics/_paths.py``)."""

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde._options import RunOptions
from nhsde.scenes import BallOnVibratingPlane, ChaplyginBall
from nhsde.statistics import _paths
from nhsde.statistics._cost import best_single, level_cost, multilevel_plan

BALL = BallOnVibratingPlane(eps=1.0, nu=1.0)
Y0 = jnp.zeros(4)


@pytest.mark.parametrize("h0", [0.25, 2.5])
def test_the_bias_model_carries_the_coarsest_step(h0):
    """The bias of a plan at ``h = h₀ 2^{−k}`` is ``bound·h^p`` in time units (``h₀^p`` included), the samples
    keep ``V/N + bias² ≤ ε²``, and one step coarser would miss the target or cost more; so do the multilevel
    plan's samples with its finest level's bias."""
    variance, bound, eps, steps0 = 2.0, 0.3, 0.05, 4
    for order in (1, 2):
        cost, k, n, bias = best_single(variance, bound, order, eps, h0, steps0, 1.0)
        h = h0 / 2**k
        assert bias == bound * h**order and variance / n + bias**2 <= eps**2
        coarser = best_single(variance, bound, order, eps, 2 * h, steps0 // 2 or 1, 1.0)
        assert coarser[1] != 0 or coarser[0] >= cost
        v = [1.0, 0.1, 0.02]
        _, counts, _, levels = multilevel_plan(v, bound, order, eps, steps0, h0, False, 1024)
        v += [v[-1] * (v[-1] / v[-2]) ** (ell - 2) for ell in range(3, levels)]  # the pilot's decay beyond it
        finest_bias = bound * (h0 / 2 ** (levels - 1)) ** order
        assert len(counts) == levels >= 3
        assert sum(a / n for a, n in zip(v, counts)) + finest_bias**2 <= eps**2


@pytest.mark.parametrize(("bound", "order", "eps"), [(2.0, 1, 0.01), (1.0, 2, 0.002)])
def test_the_multilevel_plan_splits_the_error_where_it_costs_least(bound, order, eps):
    """Giles (2015) §2.3: with levels to ``h_L`` the least work for a mean square error ``ε²`` is
    ``(Σ_ℓ √(V_ℓ C_ℓ))² / (ε² − b_L²)``, ``b_L = bound·h_L^p``.  The plan chooses its number of levels by that
    (whole pieces included), so it costs at least 30 % less here than the rule ``b_L ≤ ε/√2`` with half of ``ε²``
    left to the variance (the first ``L`` meeting it, work ``2 (Σ √(V_ℓ C_ℓ))²/ε²`` before rounding), and its
    whole-piece counts keep ``Σ V_ℓ/N_ℓ + b_L² ≤ ε²``."""
    v, steps0, h0 = [1.0, 0.25, 0.0625], 4, 0.25
    cost, counts, _, levels = multilevel_plan(v, bound, order, eps, steps0, h0, False, 1024)
    v += [v[-1] * 4.0 ** -(ell - 2) for ell in range(3, 13)]  # the pilot's decay, 2^-2 per level, beyond it
    costs = [level_cost(steps0, ell, False) for ell in range(13)]
    finest_bias = bound * (h0 / 2 ** (levels - 1)) ** order
    assert sum(a / n for a, n in zip(v, counts)) + finest_bias**2 <= eps**2
    half = next(n for n in range(3, 13) if bound * (h0 / 2 ** (n - 1)) ** order <= eps / math.sqrt(2))
    half_split = 2 * sum(math.sqrt(a * c) for a, c in zip(v[:half], costs[:half])) ** 2 / eps**2
    assert cost < 0.7 * half_split
    assert levels != half


def test_runs_beyond_the_paths_of_one_key_draw_from_further_keys(monkeypatch):
    """Path ``i ≥ KEY_PATHS`` is path ``i mod KEY_PATHS`` of ``fold_in(key, i // KEY_PATHS)`` (made small here): a run
    across the boundary is the concatenation of the two keys' runs, and their paths differ."""
    monkeypatch.setattr(_paths, "KEY_PATHS", 128)
    system, key = BALL.build(), jax.random.key(7)
    save = nhsde.Save(names=("x",), n=2, paths=True)
    run = RunOptions(t0=0.0, t1=1.0, steps=nhsde.FixedSteps(0.25), solver="euler", save=save)
    args: dict[str, Any] = dict(dts=(0.25,), brownian_dt=0.25, antithetic=False)
    (both,), _ = _paths.coupled_paths(system, Y0, key, run, n_paths=128, first_path=64, **args)
    (first,), _ = _paths.coupled_paths(system, Y0, key, run, n_paths=64, first_path=64, **args)
    (second,), _ = _paths.coupled_paths(system, Y0, jax.random.fold_in(key, 1), run, n_paths=64, **args)
    np.testing.assert_array_equal(np.asarray(both), np.concatenate([first, second]))
    assert not np.any(np.asarray(first[:, -1]) == np.asarray(second[:, -1]))


def test_large_counts_run_in_large_runs_with_the_same_paths(monkeypatch):
    """From LARGE_RUNS_FROM paths on, whole large runs (one program, 8× the paths per call) then small runs cover
    the count: the per-path values are bitwise those of one plain ``simulate`` of the same paths."""
    monkeypatch.setattr(_paths, "LARGE_RUN_PATHS", 256)
    monkeypatch.setattr(_paths, "LARGE_RUNS_FROM", 512)
    monkeypatch.setattr(_paths, "RUN_PATHS", 128)
    assert _paths.runs(300) == [128, 128, 128]
    assert _paths.runs(700) == [256, 256, 128, 128]
    steps = nhsde.FixedSteps(0.125, brownian_dt=0.125)
    save = nhsde.Save(names=("x", "u_x"), n=2, paths=True)
    args: dict[str, Any] = dict(t0=0.0, t1=1.0, steps=steps, solver="euler", save=save, batching=None)
    got = _paths.solve_paths(BALL.build(), Y0, jax.random.key(5), RunOptions(**args), first_path=64, n_paths=700)
    ens = nhsde.simulate(BALL.build(), Y0, jax.random.key(5), n_paths=700, first_path=64, **args)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ens.paths))


def test_runs_of_whole_pieces_keep_the_paths_and_their_initial_states():
    """Estimator solves go in runs of RUN_PATHS paths, the surplus of the last run dropped: a count that is not a
    multiple, with one initial state per path, gives the per-path values of one plain ``simulate`` of those paths
    (the same key, step and base step) bitwise, and a ``y0`` with the wrong number of rows is refused naming it."""
    n = _paths.RUN_PATHS + 76
    y0 = jnp.zeros((n, 4)).at[:, 0].set(jnp.linspace(0.0, 1.0, n))
    steps = nhsde.FixedSteps(0.125, brownian_dt=0.125)
    save = nhsde.Save(names=("x", "u_x"), n=2, paths=True)
    run = RunOptions(t0=0.0, t1=1.0, steps=steps, solver="euler", save=save)
    got = _paths.solve_paths(BALL.build(), y0, jax.random.key(5), run, first_path=0, n_paths=n)
    ens = nhsde.simulate(BALL.build(), y0, jax.random.key(5), n_paths=n, t1=1.0, steps=steps, save=save)
    assert got.shape == (n, 2, 2)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ens.paths))
    with pytest.raises(ValueError, match=r"y0 has shape \(5, 4\); expected"):
        _paths.solve_paths(BALL.build(), y0[:5], jax.random.key(5), run, first_path=0, n_paths=n)


def test_the_work_done_is_counted_solve_by_solve_failed_runs_included():
    """``solved_path_steps``: every run started, its surplus paths and a run that fails included (``to_accuracy``
    counts a failed attempt's work with it, not its plan): 1000 paths are one run of 1024 paths × 8 steps; on
    Chaplygin's ball Euler at h = 1 in float32 loses 2 of 1024 paths (overflow), after its run of 4 steps."""
    before = _paths.solved_path_steps()
    est = nhsde.statistics.multilevel_monte_carlo(
        BALL.build(), Y0, jax.random.key(0), t1=1.0, dt=1 / 8, statistic=("mean", "x"), n_paths=(1000,)
    )
    assert _paths.solved_path_steps() - before == _paths.RUN_PATHS * 8 and est.cost.path_steps == 1000 * 8
    ball = ChaplyginBall(eps=1.0, nu=2.0)
    with pytest.raises(nhsde.SimulationError, match="2 of 1024 paths failed"):
        nhsde.statistics.multilevel_monte_carlo(
            ball.build(),
            ball.initial_state().astype(jnp.float32),
            jax.random.key(0),
            t1=4.0,
            dt=1.0,
            statistic=("mean", "energy"),
            n_paths=(1000,),
        )
    assert _paths.solved_path_steps() - before == _paths.RUN_PATHS * (8 + 4)
