"""Several processes on ``jax.distributed`` (CPU collectives over gloo, coordinator on 127.0.0.1) give bitwise the
same statistics, failure flags and forward-mode gradients as one process: chunks are sharded over the global
devices, and the moment sums are added in path order whatever the device count."""

import json
import os
import socket
import subprocess
import sys

CHILD = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_cpu_collectives_implementation", "gloo")
process_id, n_processes, port = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
if n_processes > 1:
    jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=n_processes, process_id=process_id)
import jax.numpy as jnp, numpy as np, nhsde
from nhsde import StateLayout, StochasticSystem
from nhsde.scenes import BallOnVibratingPlane

assert len(jax.devices()) == n_processes and len(jax.local_devices()) == 1


def ball_k(eps, nu):
    scene = BallOnVibratingPlane(eps=eps, nu=nu)
    ens = nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=512, t1=1.0, dt=0.01,
                         batching=nhsde.Batching(chunk_size=128))
    return ens.mean[-1], ens.cov[-1]


# dy = y² dt + σ dW from y = 1 explodes before t = 1 on some paths: failures are flagged, excluded and counted
blow_up = StochasticSystem(
    drift_fn=lambda t, y, p: y**2, diffusion_fn=lambda t, y, p: p["sigma"] * jnp.ones((1, 1)),
    params={"sigma": jnp.float64(1.0)}, layout=StateLayout(("y",), ("independent_coordinate",)), noise_dim=1,
    additive_noise=True,
)
ens = nhsde.simulate(blow_up, jnp.array([0.5]), jax.random.key(1), n_paths=256, t1=1.0, dt=0.01,
                     batching=nhsde.Batching(chunk_size=64), on_failure="exclude", save=nhsde.Save(paths=True))
(mean, cov), (d_mean, d_cov) = ball_k(1.0, 1.0), jax.jacfwd(ball_k, argnums=(0, 1))(1.0, 1.0)
hexes = lambda a: [float(x).hex() for x in np.ravel(np.asarray(a))]
print(json.dumps(dict(
    mean=hexes(mean), cov=hexes(cov), d_mean=[hexes(d) for d in d_mean], d_cov=[hexes(d) for d in d_cov],
    blow_up_mean=hexes(ens.mean), blow_up_cov=hexes(ens.cov), failed=np.asarray(ens.failed).tolist(),
    n_used=int(ens.n_used),
)))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(n_processes: int) -> list[dict]:
    port = str(_free_port())
    env = dict(os.environ, XLA_FLAGS="", JAX_PLATFORMS="cpu")
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", CHILD, str(i), str(n_processes), port],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for i in range(n_processes)
    ]
    results = []
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-3000:]
        results.append(json.loads(out.strip().splitlines()[-1]))
    return results


def test_two_processes_equal_one_bitwise():
    (one,) = _run(1)
    two = _run(2)
    assert 0 < sum(one["failed"]) < len(one["failed"]), "the blow-up case should fail on some paths, not all"
    for result in two:  # every process holds the whole result
        assert result == one
