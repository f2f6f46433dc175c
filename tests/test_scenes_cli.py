"""Scenes model only what they need; the sleigh against its energy balance; the CLI."""

import json
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import nhsde
from nhsde.runs import load_run, main
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh


def test_ball_state_holds_only_what_is_asked_for():
    full = BallOnVibratingPlane(drift=True).build()
    assert full.layout.names == ("x", "y", "u_x", "u_y")
    assert full.layout.indices("dependent_coordinate") == (0, 1)
    small = BallOnVibratingPlane(drift=False).build()
    assert small.layout.names == ("u_x", "u_y")
    assert small.observable_names() == ("u_x", "u_y")
    assert "omega_x" in BallOnVibratingPlane(angular_velocity=True).build().observable_names()
    assert ChaplyginSleigh(drift=False).build().layout.names == ("v", "omega")


def test_ball_angular_velocity_from_the_rolling_constraint():
    scene = BallOnVibratingPlane(radius=0.5, angular_velocity=True)
    ens = nhsde.simulate(
        scene.build(),
        scene.initial_state(),
        jax.random.key(0),
        n_paths=64,
        t1=1.0,
        dt=0.01,
        save=nhsde.Save(names=("u_x", "u_y", "omega_x", "omega_y"), paths=True),
    )
    u_x, u_y, w_x, w_y = np.moveaxis(np.asarray(ens.paths), -1, 0)
    np.testing.assert_allclose(w_y, u_x / 0.5, rtol=1e-6)  # u_x = r ω_y
    np.testing.assert_allclose(w_x, -u_y / 0.5, rtol=1e-6)  # u_y = −r ω_x


def test_reduced_and_full_ball_agree():
    """The velocity-only state gives the same velocities (same key, same noise channels)."""
    kw: dict[str, Any] = dict(n_paths=128, t1=1.0, dt=0.01, save=nhsde.Save(names=("u_x", "u_y"), paths=True))
    a = nhsde.simulate(BallOnVibratingPlane().build(), jnp.zeros(4), jax.random.key(1), **kw)
    b = nhsde.simulate(BallOnVibratingPlane(drift=False).build(), jnp.zeros(2), jax.random.key(1), **kw)
    np.testing.assert_allclose(a.paths, b.paths, rtol=1e-6, atol=1e-7)


def test_sleigh_conserves_energy_without_friction_and_noise():
    scene = ChaplyginSleigh(eps=0.0, nu=0.0, mass=2.0, inertia=0.5, offset=0.7)
    system, p = scene.build(), scene.params

    def energy_rate(y):
        grad_h = jax.grad(lambda y: 0.5 * (p.mass * y[3] ** 2 + (p.inertia + p.mass * p.offset**2) * y[4] ** 2))(y)
        return grad_h @ system.drift(0.0, y, p)

    ys = jax.random.normal(jax.random.key(0), (100, 5), jnp.float64)
    assert float(jnp.max(jnp.abs(jax.vmap(energy_rate)(ys)))) < 1e-12


def test_sleigh_mean_energy_follows_its_balance():
    """Itô: dE[H]/dt = −4ε E[H] + ν, so E[H](t) = H0 e^{−4εt} + ν(1 − e^{−4εt})/(4ε)."""
    eps, nu, t1 = 0.5, 0.8, 2.0
    scene = ChaplyginSleigh(eps=eps, nu=nu, drift=False)
    p = scene.params
    j = float(p.inertia + p.mass * p.offset**2)
    y0 = jnp.array([1.0, 0.5], jnp.float64)
    ens = nhsde.simulate(
        scene.build(),
        y0,
        jax.random.key(2),
        n_paths=8192,
        t1=t1,
        dt=0.002,
        solver="sra1",
        save=nhsde.Save(n=5, paths=True),
    )
    y = np.asarray(ens.paths, np.float64)
    h = 0.5 * (float(p.mass) * y[..., 0] ** 2 + j * y[..., 1] ** 2)
    h0 = 0.5 * (1.0 + j * 0.25)
    t = np.asarray(ens.ts, np.float64)
    exact = h0 * np.exp(-4 * eps * t) + nu * (1 - np.exp(-4 * eps * t)) / (4 * eps)
    se = h.std(0) / np.sqrt(h.shape[0])
    assert np.all(np.abs(h.mean(0) - exact)[1:] <= 4 * se[1:]), (h.mean(0), exact, se)


def test_cli_lists_scenes(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    assert "ball-on-vibrating-plane" in out and "chaplygin-sleigh" in out and "eps" in out


def test_cli_simulate_prints_and_saves(tmp_path, capsys):
    out_file = tmp_path / "run.nc"
    code = main(
        [
            "simulate",
            "ball-on-vibrating-plane",
            "--paths",
            "256",
            "--t1",
            "1",
            "--dt",
            "0.01",
            "--set",
            "eps=2",
            "--no-progress",
            "--out",
            str(out_file),
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "systematic drift" in text and "d/d eps" in text and "closed form" in text
    assert f"saved {out_file} (netCDF)" in text
    data = load_run(out_file)
    assert data.attrs["format"] == "nhsde-run" and data.attrs["complete"] == 1 and data.attrs["n_used"] == 256
    assert data.attrs["scene"] == "ball-on-vibrating-plane" and json.loads(data.attrs["parameters"])["eps"] == 2.0
    assert list(data["name"].values) == ["x", "y", "u_x", "u_y"]
    assert data["cov"].shape == (11, 4, 4) and data["d_cov_d_nu"].shape == (11, 4, 4)
    # K is linear in ν: ∂K/∂ν = K/ν
    np.testing.assert_allclose(data["d_cov_d_nu"][-1], data["cov"][-1] / 1.0, rtol=1e-4, atol=1e-7)
    # and so is its standard error (paths ∝ √ν from rest: the per-path influence terms are those of K, over ν)
    np.testing.assert_allclose(data["d_cov_d_nu_se"][-1], data["cov_se"][-1] / 1.0, rtol=0.05)


def test_cli_rejects_bad_input(capsys):
    import re

    for argv, match in [
        (["simulate", "ball"], "scene 'ball': unknown scene"),
        (["simulate", "ball-on-vibrating-plane", "--set", "eps=-1"], "eps=-1.0 is not allowed"),
        (["simulate", "ball-on-vibrating-plane", "--set", "mass=1"], "unknown parameter"),
        (["simulate", "ball-on-vibrating-plane", "--solver", "rk4", "--no-progress"], "--solver 'rk4': allowed"),
        (["simulate", "ball-on-vibrating-plane", "--paths", "0", "--no-progress"], "--paths 0: must be ≥ 4"),
        (["simulate", "ball-on-vibrating-plane", "--dt", "0.03"], "--dt 0.03: must divide"),
        (["simulate", "ball-on-vibrating-plane", "--seed", str(2**64)], "--seed 18446744073709551616: must be ≤"),
        (["simulate", "ball-on-vibrating-plane", "--paths", str(2**32)], "--paths 4294967296: must be ≤ 2147483647"),
        (["simulate", "ball-on-vibrating-plane", "--t1", "1e300"], "--t1 1e\\+300: .* beyond the budget"),
    ]:
        assert main(argv) == 2, argv  # bad input: exit status 2, one line on stderr
        err = capsys.readouterr().err
        assert re.fullmatch(f"nhsde simulate: .*{match}.*\\n", err), err


def test_cli_runs_a_noiseless_scene_and_reports_the_missing_nu_derivative(capsys, tmp_path):
    """At ν = 0 paths scale like √ν: d/dν does not exist; the CLI says so (nan) instead of failing.
    The upright disk rolling straight without friction keeps its speed: x(t) = R Ω t."""
    out = tmp_path / "disk.npz"  # written as netCDF under exactly this name
    assert (
        main(["simulate", "rolling-disk", "--paths", "64", "--t1", "0.5", "--dt", "0.01", "--x64", "--out", str(out)])
        == 0
    )
    text = capsys.readouterr().out
    assert "d/d nu is nan: it does not exist at nu = 0" in text
    assert f"saved {out} (netCDF, although the name does not end in .nc)" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disk.npz"]
    data = load_run(out)
    assert np.all(np.isnan(data["d_mean_d_nu"])) and np.all(np.isfinite(data["d_mean_d_eps"]))
    x = data["mean"][-1, 0]
    assert abs(x - 0.5 * 3.0) < 1e-9 * 1.5, x  # default radius 1, spin 3 rad/s


def test_cli_differentiates_in_the_scene_s_own_noise_intensity(capsys, tmp_path):
    """A scene in a heat bath has no ``nu``: its noise intensity is ``kT`` (``Scene.intensities``).  The command
    reports and writes the derivatives in ``eps`` and ``kT`` (it raised AttributeError on ``params.nu`` before)."""
    out = tmp_path / "bath.nc"
    argv = ["simulate", "chaplygin-sleigh-in-bath", "--paths", "64", "--t1", "0.2", "--dt", "0.05", "--save-points"]
    assert main([*argv, "2", "--no-progress", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "d/d eps" in text and "d/d kT" in text and "d/d nu" not in text
    data = load_run(out)
    assert {"d_cov_d_eps", "d_cov_d_kT", "d_mean_d_kT_se"} <= set(data.data_vars) and "d_cov_d_nu" not in data
    assert np.all(np.isfinite(data["d_cov_d_kT"][-1]))
    assert float(data["d_cov_d_kT"][-1, 3, 3]) > 0  # Var v grows with kT
