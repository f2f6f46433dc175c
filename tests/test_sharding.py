"""Sharded ensembles over 8 host devices give the single-device statistics bitwise."""

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np, nhsde
    from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh
    assert len(jax.devices()) == 8, jax.devices()
    for scene in (BallOnVibratingPlane(), ChaplyginSleigh()):
        for dtype in (jnp.float32, jnp.float64):
            kw = dict(n_paths=1000, t1=1.0, dt=0.01, save=nhsde.Save(paths=True), solver="euler")
            y0 = scene.initial_state().astype(dtype)
            one = nhsde.simulate(
                scene.build(), y0, jax.random.key(3), batching=nhsde.Batching(128, jax.devices()[:1]), **kw
            )
            for n in (2, 8):
                batching = nhsde.Batching(128, jax.devices()[:n])
                many = nhsde.simulate(scene.build(), y0, jax.random.key(3), batching=batching, **kw)
                for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(many)):
                    assert np.array_equal(a, b), (type(scene).__name__, dtype, n)
    # gradients through the sharded solve equal the single-device ones
    def k(eps, devices):
        s = BallOnVibratingPlane(eps=eps)
        e = nhsde.simulate(s.build(), s.initial_state(), jax.random.key(0), n_paths=512, t1=1.0, dt=0.01,
                           batching=nhsde.Batching(64, devices))
        return e.cov[-1, 0, 0]
    g1 = jax.grad(k)(jnp.float32(1.0), jax.devices()[:1])
    g8 = jax.grad(k)(jnp.float32(1.0), jax.devices())
    assert np.array_equal(g1, g8), (g1, g8)
    print("sharding ok")
    """
)


def test_sharded_statistics_equal_single_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=8", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-4000:]
    assert "sharding ok" in out.stdout
