"""JAX's persistent compilation cache, internals: programs traced with parameters checked on the host
(``nhsde._params.checked_on_host``, the estimators' forward mode) enter the cache and are never reused where the
parameters need their run-time checks, and the command's timed pilot is kept in the cache folder.  The public side
is tests/test_compilation_cache.py."""

import jax
import jax.numpy as jnp
import pytest

# the public tests' autouse fixture (JAX's global cache settings put back after each test) applies here too
from test_compilation_cache import VARIABLE, _restore_jax_cache_settings  # noqa: F401

import nhsde
from nhsde._params import checked_on_host
from nhsde._simulate import simulate_run
from nhsde.runs import _cli, main

SINGULAR = "the derivative with respect to a noise intensity nu at nu = 0 is singular"


def test_a_forward_mode_derivative_in_nu_at_concrete_nu_is_cached(tmp_path, caplog):
    """The estimators' ν-tangents (forward mode of concrete parameters, ``forward_only``): no differentiated
    parameter is 0, checked on the host, so √ν's derivative carries no host callback and the solve enters the
    cache; its next compilation (as in a new process) is not a persistent-cache miss."""
    nhsde.enable_compilation_cache(tmp_path)
    scene = nhsde.scenes.BallOnVibratingPlane()
    system = scene.build()

    def ask():
        def k_xx(eps, nu):
            p = system.replace_params(eps=eps, nu=nu)
            run = nhsde.RunOptions(t1=1.0, steps=nhsde.FixedSteps(0.1), save=nhsde.Save())
            ens = simulate_run(p, scene.initial_state(), jax.random.key(0), run, n_paths=64, forward_only=True)
            return ens.cov[-1, 0, 0]

        return jax.jacfwd(k_xx, argnums=(0, 1))(system.params.eps, system.params.nu)

    d_eps, d_nu = ask()
    assert jnp.isfinite(d_eps) and jnp.isfinite(d_nu) and d_nu > 0
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("jit__run-")], sorted(tmp_path.iterdir())
    jax.clear_caches()
    with jax.explain_cache_misses(True), caplog.at_level("WARNING", logger="jax"):
        again = ask()
    assert jnp.allclose(again[1], d_nu)
    messages = [r.getMessage() for r in caplog.records]
    assert not [m for m in messages if "'jit__run'" in m and ("MISS" in m or "Not writing" in m)], messages


def test_a_program_traced_with_host_checked_parameters_is_cached_and_never_reused_without(tmp_path):
    """In ``checked_on_host`` √ν's derivative has no run-time check (the program is cached); the same function traced
    outside (traced ν, checked by no one) gets its own program, with the check, even after the first."""
    nhsde.enable_compilation_cache(tmp_path)
    derivative = jax.jit(jax.grad(nhsde.sqrt_intensity))
    with checked_on_host():
        assert float(derivative(4.0)) == 0.25
    assert [p.name for p in tmp_path.iterdir() if "sqrt_intensity" in p.name], [p.name for p in tmp_path.iterdir()]
    with pytest.raises(Exception, match=SINGULAR):
        derivative(0.0)
    assert float(derivative(4.0)) == 0.25


def test_the_pilot_is_timed_once_per_cache_folder(tmp_path, monkeypatch, capsys):
    """The command's estimate comes from a timed pilot; its seconds are kept in the cache folder, so the same run
    again prints the same estimate without simulating the pilot (whose programs a warm process would load)."""
    monkeypatch.setenv(VARIABLE, str(tmp_path))
    args = ["simulate", "ball-on-vibrating-plane", "--paths", "8192", "--t1", "5", "--dt", "0.05", "--save-points", "2"]
    timed = []
    real = _cli._timed_pilot
    monkeypatch.setattr(_cli, "_timed_pilot", lambda *a: timed.append(a) or real(*a))
    assert main(args) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert len(timed) == 1 and "roughly" in first and (tmp_path / _cli.PILOTS).is_file()
    assert main(args) == 0
    assert capsys.readouterr().out.splitlines()[0] == first and len(timed) == 1
    assert main([*args[:3], "16384", *args[4:]]) == 0  # the same pilot (one chunk of 8192): twice the paths
    assert len(timed) == 1
    (tmp_path / _cli.PILOTS).write_text("{not json")  # a damaged file is measured again and rewritten
    assert main(args) == 0 and len(timed) == 2
    monkeypatch.setenv(VARIABLE, "off")  # no cache folder: every process times its pilot
    assert main(args) == 0 and len(timed) == 3
