"""Runs from TOML files: strict validation, self-describing netCDF, resuming after an interruption."""

import copy
import json
import os
import re
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import xarray as xr

import nhsde
from nhsde.runs import ConfigError, RunConfig, load_config, load_run, main, run

BASE = {
    "scene": "ball-on-vibrating-plane",
    "seed": 5,
    "parameters": {"eps": 0.8, "nu": 1.5},
    "solver": {"name": "euler", "dt": 0.05, "t1": 1.0},
    "paths": {"n": 300, "chunk": 64},
    "statistics": {"save": ["x", "u_x"], "save_points": 5, "keep_paths": True},
}
BASE_TOML = """
scene = "ball-on-vibrating-plane"
seed = 5

[parameters]
eps = 0.8
nu = 1.5

[solver]
name = "euler"
dt = 0.05
t1 = 1.0

[paths]
n = 300
chunk = 64

[statistics]
save = ["x", "u_x"]
save_points = 5
keep_paths = true
"""


def changed(path, value):
    """BASE with the dotted key ``path`` set to ``value`` (``...`` deletes it)."""
    raw = copy.deepcopy(BASE)
    *parents, last = path.split(".")
    table = raw
    for p in parents:
        table = table.setdefault(p, {})
    if value is ...:
        del table[last]
    else:
        table[last] = value
    return raw


def test_base_config_is_valid_and_parses_from_toml(tmp_path):
    f = tmp_path / "run.toml"
    f.write_text(BASE_TOML)
    config = load_config(f)
    assert config.data == RunConfig.from_dict(BASE).data
    assert config.data["precision"] == "float64" and config.data["options"] == {}


@pytest.mark.parametrize(
    "path, value, message",
    [
        # unknown keys
        ("colour", "red", "colour: unknown key in the top level"),
        ("solver.rtol", 1e-3, "solver.rtol: unknown key in \\[solver\\]"),
        ("parameters.mass", 1.0, "parameters.mass: unknown parameter of ball-on-vibrating-plane"),
        ("options.spin", True, "options.spin: unknown option"),
        ("initial_state.z", 1.0, "initial_state.z: not a state component"),
        # wrong types
        ("paths.n", "300", "paths.n: expected an integer, got a string"),
        ("paths.n", 300.0, "paths.n: expected an integer, got a number"),
        ("solver.dt", True, "solver.dt: expected a number, got a boolean"),
        ("parameters.eps", "0.8", "parameters.eps: expected a number, got a string"),
        ("options.drift", 1, "options.drift: expected true or false"),
        ("statistics.save", "x", "statistics.save: expected an array of strings"),
        ("statistics.keep_paths", "yes", "statistics.keep_paths: expected true or false"),
        ("solver", 0.05, "solver: expected a table"),
        # out of range
        ("paths.n", 0, "paths.n = 0: must be ≥ 4"),
        ("paths.chunk", 100, "paths.chunk = 100: must be a multiple of 64"),
        ("seed", -1, "seed = -1: must be ≥ 0"),
        ("solver.dt", 0.0, "solver.dt = 0.0: must be > 0"),
        ("solver.dt", 0.03, "solver.dt = 0.03: must divide"),
        ("solver.t1", -1.0, "solver.t1 = -1.0: must be > solver.t0"),
        ("parameters.eps", -1.0, "parameters: .*eps=-1.0 is not allowed"),
        ("parameters.nu", float("nan"), "parameters.nu = nan: must be finite"),
        ("statistics.save_points", 1, "statistics.save_points = 1: must be ≥ 2"),
        ("precision", "float16", "precision = 'float16': allowed values are 'float32', 'float64'"),
        ("solver.name", "rk4", "solver.name = 'rk4': allowed values"),
        ("statistics.save", ["x", "q"], "statistics.save: 'q' is not offered"),
        # unknown scene, missing keys
        ("scene", "ball", "scene = 'ball': unknown scene; known scenes"),
        ("solver.t1", ..., "solver.t1: required key is missing"),
        ("scene", ..., "scene: required key is missing"),
    ],
)
def test_config_rejects_bad_input_naming_the_key(path, value, message):
    with pytest.raises(ConfigError, match=message):
        RunConfig.from_dict(changed(path, value))


def test_no_config_can_execute_code(tmp_path):
    marker = tmp_path / "pwned"
    payload = f"__import__('os').system('touch {marker}')"
    for path in ("scene", "solver.name", "precision", "parameters.eps", "options.drift"):
        with pytest.raises(ConfigError):
            RunConfig.from_dict(changed(path, payload))
    f = tmp_path / "evil.toml"
    f.write_text(BASE_TOML + f'\n[initial_state]\nx = "{payload}"\n')
    with pytest.raises(ConfigError, match="initial_state.x: expected a number"):
        load_config(f)
    f.write_text("scene = !!python/object:os.system\n")  # not TOML at all
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(f)
    assert not marker.exists()


def test_fit_config_schema():
    raw = {k: v for k, v in BASE.items() if k != "statistics"} | {"fit": {"data": "run.nc"}}
    with pytest.raises(ConfigError, match="solver.t1: unknown key"):
        RunConfig.from_dict(raw, "fit")
    raw["solver"] = {"name": "euler", "dt": 0.05}
    with pytest.raises(ConfigError, match="paths.chunk: unknown key"):
        RunConfig.from_dict(raw, "fit")
    raw["paths"] = {"n": 256}
    assert RunConfig.from_dict(raw, "fit").data["fit"] == {"data": "run.nc", "vary": ["eps", "nu"], "max_steps": 100}
    raw["fit"]["vary"] = ["eps", "mass"]
    with pytest.raises(ConfigError, match="fit.vary: 'mass' is not a parameter"):
        RunConfig.from_dict(raw, "fit")


def test_saved_run_reloads_identically_and_describes_itself(tmp_path):
    config = RunConfig.from_dict(changed("paths.chunk", 192))  # two pieces, 192 + 108 paths
    out = tmp_path / "run.nc"
    ds = run(config, out)
    again = load_run(out)
    xr.testing.assert_identical(ds, again)
    for name in ds.data_vars:
        assert ds[name].dtype == again[name].dtype
        np.testing.assert_array_equal(ds[name].values, again[name].values)
    assert ds.attrs.keys() == again.attrs.keys()
    for key, value in ds.attrs.items():
        np.testing.assert_array_equal(value, again.attrs[key], err_msg=key)

    a = again.attrs
    assert a["format"] == "nhsde-run" and a["complete"] == 1 and a["n_used"] == 300 and a["pieces_done"] == 2
    assert json.loads(a["parameters"]) == {"eps": 0.8, "nu": 1.5, "radius": 1.0, "inertia_ratio": 0.4}
    assert {"jax", "diffrax", "nhsde", "xarray"} <= set(json.loads(a["versions"]))
    assert re.fullmatch(r"[0-9a-f]{40}(\+dirty)?|unknown", a["git_revision"]), a["git_revision"]
    np.testing.assert_array_equal(a["key_data"], jax.random.key_data(jax.random.key(5)))
    # the stored configuration rebuilds the run
    assert RunConfig.from_dict(json.loads(a["config"])).to_json() == config.to_json()

    # statistics equal simulate's over the same 300 paths (other summation order: rounding only)
    system = nhsde.scenes.BallOnVibratingPlane(eps=0.8, nu=1.5).build()
    ens = nhsde.simulate(
        system,
        jnp.zeros(4),
        jax.random.key(5),
        n_paths=300,
        t1=1.0,
        dt=0.05,
        save=nhsde.Save(names=("x", "u_x"), n=5, paths=True),
    )
    np.testing.assert_array_equal(again["paths"].values, ens.paths)
    for name in ("mean", "cov", "mean_se", "cov_se"):
        np.testing.assert_allclose(again[name].values, getattr(ens, name), rtol=1e-10, atol=1e-14, err_msg=name)


class Interrupt(Exception):
    pass


def test_interrupted_run_resumes_to_the_uninterrupted_result(tmp_path):
    """Interrupt after piece 2 of 5 (a hook raising), resume, compare with a run never interrupted.

    The pieces are computed bitwise alike (simulate(first_path=…) of the same
    key) and summed in piece order from float64 sums stored exactly in the
    file, so the results agree bitwise: tolerance zero.
    """
    config = RunConfig.from_dict(BASE)
    whole = run(config, tmp_path / "whole.nc")

    out = tmp_path / "part.nc"

    def stop_after_two(k):
        if k == 2:
            raise Interrupt

    with pytest.raises(Interrupt):
        run(config, out, on_piece=stop_after_two)
    partial = load_run(out)
    assert partial.attrs["pieces_done"] == 3 and partial.attrs["complete"] == 0
    assert partial.sizes["path"] == 3 * 64 and partial.attrs["n_used"] == 192

    seen = []
    resumed = run(config, out, on_piece=seen.append)
    assert seen == [3, 4]  # only the missing pieces were computed
    for name in whole.data_vars:
        np.testing.assert_array_equal(resumed[name].values, whole[name].values, err_msg=name)
    for key in whole.attrs:
        if key not in ("created", "git_revision", "checksum"):  # when it started, information, and their hash
            np.testing.assert_array_equal(resumed.attrs[key], whole.attrs[key], err_msg=key)
    assert resumed.sizes["path"] == 300 and len(np.unique(resumed["paths"].values, axis=0)) == 300

    # a finished run is not recomputed; a different configuration is refused
    assert run(config, out, on_piece=seen.append).attrs["complete"] == 1 and seen == [3, 4]
    other = RunConfig.from_dict(changed("parameters.eps", 0.9))
    with pytest.raises(ConfigError, match="different configuration \\(differs in: parameters\\)"):
        run(other, out)


@pytest.mark.slow
def test_killed_process_resumes(tmp_path):
    """SIGKILL a CLI run once two pieces are on disk; resuming gives the uninterrupted statistics.

    (Slow: a second interpreter; the fast test interrupts through the hook.)
    """
    cfg = tmp_path / "run.toml"
    cfg.write_text(BASE_TOML.replace("n = 300", "n = 640"))
    out = tmp_path / "run.nc"
    proc = subprocess.Popen(
        [sys.executable, "-m", "nhsde.runs", "simulate", "--config", str(cfg), "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if out.exists() and load_run(out).attrs["pieces_done"] >= 2:
                break
            time.sleep(0.2)
        assert proc.poll() is None, f"the run ended before it could be killed:\n{proc.stdout.read()}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    done = load_run(out).attrs["pieces_done"]
    assert 2 <= done < 10
    assert main(["simulate", "--config", str(cfg), "--no-progress"]) == 0
    resumed = load_run(out)
    whole = run(load_config(cfg), tmp_path / "whole.nc")
    for name in whole.data_vars:
        np.testing.assert_array_equal(resumed[name].values, whole[name].values, err_msg=name)


def test_cli_simulate_config_then_fit(tmp_path, capsys):
    """The file-driven workflow: simulate synthetic data, then fit ε and ν to it through simulation."""
    data_cfg = tmp_path / "data.toml"
    data_cfg.write_text(
        BASE_TOML.replace("n = 300", "n = 1024").replace("chunk = 64", "chunk = 1024").replace("t1 = 1.0", "t1 = 4.0")
    )
    assert main(["simulate", "--config", str(data_cfg), "--no-progress"]) == 0
    assert (tmp_path / "data.nc").is_file()
    fit_cfg = tmp_path / "fit.toml"
    fit_cfg.write_text(
        'scene = "ball-on-vibrating-plane"\nseed = 99\n\n[parameters]\neps = 0.3\nnu = 0.5\n\n'
        '[solver]\nname = "euler"\ndt = 0.05\n\n[paths]\nn = 1024\n\n[fit]\ndata = "data.nc"\nvary = ["eps", "nu"]\n'
    )
    assert main(["fit", "--config", str(fit_cfg)]) == 0
    text = capsys.readouterr().out
    assert "chi2" in text and "eps" in text
    res = load_run(tmp_path / "fit.nc")
    assert res.attrs["format"] == "nhsde-fit" and res.attrs["converged"] == 1
    assert res.attrs["observed_from_trajectories"] == 1
    z = (res["estimate"].values - np.array([0.8, 1.5])) / res["se"].values
    assert np.all((res["jacobian_relative_se"].values > 0) & (res["jacobian_relative_se"].values < 0.3))
    assert np.all(np.abs(z) <= 2), z
    assert json.loads(res.attrs["data_config"])["seed"] == 5


def test_cli_config_errors(tmp_path, capsys):
    """Bad input ends the command with exit status 2 and one line on stderr naming what is wrong."""
    cfg = tmp_path / "run.toml"
    cfg.write_text(BASE_TOML.replace("nu = 1.5", "nu = -1.5"))
    for argv, message in [
        (["simulate", "--config", str(cfg)], "run.toml: parameters: .*nu=-1.5 is not allowed"),
        (["simulate", "--config", str(cfg), "--paths", "10"], "--paths cannot be combined with --config"),
        (["simulate", "ball-on-vibrating-plane", "--config", str(cfg)], "SCENE cannot be combined with --config"),
        (["simulate"], "give a SCENE"),
        (["fit", "--config", str(tmp_path / "missing.toml")], "missing.toml: cannot read the file"),
    ]:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert re.fullmatch(f"nhsde {argv[0]}: .*{message}.*\n", err), err


def test_run_needs_x64_for_its_sums(tmp_path):
    with jax.enable_x64(False), pytest.raises(RuntimeError, match="jax_enable_x64"):
        run(RunConfig.from_dict(BASE), tmp_path / "run.nc")


def test_the_example_in_the_help_is_a_valid_run_file(capsys):
    import textwrap
    import tomllib

    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    example = capsys.readouterr().out.split("a run file (TOML", 1)[1]
    body = example.split("\n\n", 1)[1].rsplit("\n\n", 1)[0]
    config = RunConfig.from_dict(tomllib.loads(textwrap.dedent(body)))
    assert config.data["solver"]["name"] == "sra1" and config.data["statistics"]["save"] == ["x", "y"]


def test_float32_run_keeps_float64_sums(tmp_path):
    """precision = "float32" simulates in float32 (the paths are simulate's) and sums them in float64.

    float32 and float64 draw different normals from one key, so the check is against
    simulate in float32: the same paths bitwise, its float32 moments to float32 rounding.
    """
    single = run(RunConfig.from_dict(changed("paths.n", 128) | {"precision": "float32"}), tmp_path / "single.nc")
    assert single["paths"].dtype == np.float32 and single["cov"].dtype == np.float64
    system = nhsde.scenes.BallOnVibratingPlane(eps=0.8, nu=1.5).build()
    ens = nhsde.simulate(
        system,
        jnp.zeros(4, jnp.float32),
        jax.random.key(5),
        n_paths=128,
        t1=1.0,
        dt=0.05,
        save=nhsde.Save(names=("x", "u_x"), n=5, paths=True),
    )
    np.testing.assert_array_equal(single["paths"].values, ens.paths)
    for name in ("mean", "cov"):
        np.testing.assert_allclose(single[name].values, getattr(ens, name), rtol=1e-5, atol=1e-6, err_msg=name)


def test_cli_scene_file_is_a_run_file_its_config_reruns(tmp_path, capsys):
    """``nhsde simulate SCENE --out`` writes the run-file layout (plus the derivatives); its stored
    configuration, run as a run file, gives the same statistics."""
    out = tmp_path / "scene.nc"
    argv = ["simulate", "ball-on-vibrating-plane", "--paths", "128", "--t1", "1", "--dt", "0.05", "--save-points", "5"]
    assert main([*argv, "--seed", "3", "--set", "eps=0.8", "--x64", "--no-progress", "--out", str(out)]) == 0
    assert f"saved {out} (netCDF)" in capsys.readouterr().out
    scene = load_run(out)
    config = RunConfig.from_dict(json.loads(scene.attrs["config"]))
    again = run(config, tmp_path / "again.nc")
    derivatives = {f"d_{s}_d_{q}{se}" for s in ("mean", "cov") for q in ("eps", "nu") for se in ("", "_se")}
    assert set(scene.data_vars) == set(again.data_vars) | derivatives
    assert scene.attrs.keys() == again.attrs.keys() and scene.attrs["precision"] == "float64"
    assert scene.attrs["pieces_done"] == 1 and scene.attrs["complete"] == 1
    for name in again.data_vars:
        np.testing.assert_allclose(scene[name].values, again[name].values, rtol=1e-12, atol=1e-15, err_msg=name)


def test_a_run_builds_its_scene_once(tmp_path, monkeypatch):
    """Validation builds the scene; the five pieces of the run reuse it."""
    built = []
    build = nhsde.scenes.BallOnVibratingPlane.build
    monkeypatch.setattr(nhsde.scenes.BallOnVibratingPlane, "build", lambda self: built.append(1) or build(self))
    f = tmp_path / "run.toml"
    f.write_text(BASE_TOML.replace("keep_paths = true", "keep_paths = false"))
    ds = run(load_config(f), tmp_path / "run.nc")
    assert ds.attrs["pieces_done"] == 5 and "paths" not in ds and len(built) == 1
