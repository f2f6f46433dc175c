"""The step loop's accelerator shape, run on the CPU: blocks of static trip count inside the loop whose trip count
is data (a GPU reads that loop's predicate back to the host at each iteration), and all paths in one chunk."""

import jax
import numpy as np
import pytest

import nhsde
import nhsde._simulate as simulate_module


@pytest.mark.parametrize("steps_per_save", [100, 31])  # 3 blocks of 32 and 4 steps; no whole block
def test_blocked_step_loop_gives_bitwise_the_same_statistics(monkeypatch, steps_per_save):
    scene = nhsde.scenes.ChaplyginSleigh(eps=0.5, nu=0.3)
    system, y0 = scene.build(), scene.initial_state()

    def run():
        ens = nhsde.simulate(
            system, y0, jax.random.key(3), n_paths=128, t1=2 * steps_per_save * 0.01, dt=0.01, save=nhsde.Save(n=3)
        )
        return np.asarray(ens.mean), np.asarray(ens.cov)

    plain = run()
    monkeypatch.setattr(simulate_module, "step_block", lambda platform: 32)
    blocked = run()
    for a, b in zip(plain, blocked):
        np.testing.assert_array_equal(a, b)


def test_default_chunk_on_an_accelerator_holds_every_path():
    assert simulate_module.default_chunk_size("cpu") == 8192
    assert simulate_module.default_chunk_size("gpu") >= 2**20
