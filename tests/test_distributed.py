"""Several processes on ``jax.distributed`` (CPU collectives over gloo, coordinator on 127.0.0.1) give bitwise the
same statistics, failure flags and forward-mode gradients as one process: chunks are sharded over the global
devices, and the moment sums are added in path order whatever the device count.  A run file computed, interrupted
and resumed in two processes (process 0 writes) equals the one-process file bitwise."""

import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest

from nhsde.runs import RunConfig, load_run, main, run

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


def _run(n_processes: int, child: str = CHILD, args=(), env_of=lambda i, n, port: {}) -> list[dict]:
    """Run ``child`` in ``n_processes`` processes (argv: process id, count, port, ``args``); their last JSON lines."""
    port = str(_free_port())
    env = dict(os.environ, XLA_FLAGS="", JAX_PLATFORMS="cpu")
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", child, str(i), str(n_processes), port, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env | env_of(i, n_processes, port),
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


RUN = {
    "scene": "ball-on-vibrating-plane",
    "seed": 5,
    "parameters": {"eps": 0.8, "nu": 1.5},
    "solver": {"name": "euler", "dt": 0.05, "t1": 0.5},
    "paths": {"n": 128, "chunk": 64},  # 2 pieces
    "statistics": {"save": ["x", "u_x"], "save_points": 3, "keep_paths": True},
}

RUN_CHILD = r"""
import json, sys
from pathlib import Path
import jax
jax.config.update("jax_enable_x64", True)
process_id, n_processes, port, folder = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], Path(sys.argv[4])
from nhsde.runs import ConfigError, RunConfig, load_run, main, run

raw = json.loads(sys.argv[5])
cfg = folder / "run.toml"
# the whole run through the command, jax.distributed from NHSDE_COORDINATOR, NHSDE_NUM_PROCESSES, NHSDE_PROCESS_ID
status = main(["simulate", "--config", str(cfg), "--out", str(folder / "whole.nc"), "--no-progress"])
assert len(jax.devices()) == n_processes


class Stop(Exception):
    pass


def stop(k):
    raise Stop  # in every process after the first piece: an interruption


try:
    run(RunConfig.from_dict(raw), folder / "partial.nc", on_piece=stop)
except Stop:
    pass
interrupted = load_run(folder / "partial.nc").attrs["pieces_done"]
resumed = main(["simulate", "--config", str(cfg), "--out", str(folder / "partial.nc"), "--no-progress",
                "--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n_processes),
                "--process-id", str(process_id)])
raw["seed"] += process_id  # process 1 runs another configuration: refused in both, before any work
try:
    run(RunConfig.from_dict(raw), folder / "other.nc")
    refusal = None
except ConfigError as e:
    refusal = str(e)
print(json.dumps(dict(status=status, interrupted=int(interrupted), resumed=resumed, refusal=refusal)))
"""


def test_a_run_file_in_two_processes_equals_one_process_bitwise(tmp_path):
    """Two processes run, interrupt and resume a run file (process 0 writes): bitwise the one-process file."""
    toml = "\n".join(
        [f"scene = {json.dumps(RUN['scene'])}", f"seed = {RUN['seed']}"]
        + [
            f"[{table}]\n" + "\n".join(f"{k} = {json.dumps(v)}" for k, v in RUN[table].items())
            for table in ("parameters", "solver", "paths", "statistics")
        ]
    )
    (tmp_path / "run.toml").write_text(toml)
    env = lambda i, n, port: {
        "NHSDE_COORDINATOR": f"127.0.0.1:{port}",
        "NHSDE_NUM_PROCESSES": str(n),
        "NHSDE_PROCESS_ID": str(i),
    }
    results = _run(2, RUN_CHILD, (str(tmp_path), json.dumps(RUN)), env)
    one = run(RunConfig.from_dict(RUN), tmp_path / "one.nc")
    for r in results:
        assert r["status"] == r["resumed"] == 0 and r["interrupted"] == 1
        assert "disagree" in r["refusal"] and "configuration" in r["refusal"], r["refusal"]
    for name in ("whole.nc", "partial.nc"):
        ds = load_run(tmp_path / name)
        assert ds.attrs["complete"] == 1 and ds.attrs["pieces_done"] == 2
        for var in one.data_vars:
            np.testing.assert_array_equal(ds[var].values, one[var].values, err_msg=f"{name}: {var}")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["one.nc", "partial.nc", "run.toml", "whole.nc"], left  # no lock, no partial, no other.nc


@pytest.mark.parametrize(
    "flags, env, named",
    [
        (["--num-processes", "2", "--process-id", "0"], {}, "--coordinator"),
        (["--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "2"], {}, "--process-id"),
        (["--coordinator", "127.0.0.1:1", "--process-id", "1"], {}, "--num-processes"),
        ([], {"NHSDE_COORDINATOR": "127.0.0.1:1", "NHSDE_NUM_PROCESSES": "two", "NHSDE_PROCESS_ID": "0"}, "NHSDE_NUM"),
    ],
)
def test_incomplete_process_settings_are_refused_naming_them(tmp_path, capsys, monkeypatch, flags, env, named):
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    assert main(["simulate", "--config", str(tmp_path / "run.toml"), *flags]) == 2
    err = capsys.readouterr().err
    assert named in err and err.count("\n") == 1, err
