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


def test_the_default_chunk_is_each_devices_share_up_to_the_platforms_cap():
    """One device: all paths up to 8192 (CPU) or 2²⁰ (accelerator); several: each device's share, so that no device
    simulates padding beyond a block (32768 paths on 8 devices ran 65536 in chunks of 8192)."""
    chunk = simulate_module.default_chunk_size
    assert (chunk(100, 1, "cpu"), chunk(20000, 1, "cpu"), chunk(65536, 1, "gpu")) == (128, 8192, 65536)
    assert chunk(2**24, 1, "gpu") == 2**20
    assert (chunk(32768, 8, "cpu"), chunk(256, 8, "cpu"), chunk(2**21, 8, "gpu")) == (4096, 64, 2**18)
