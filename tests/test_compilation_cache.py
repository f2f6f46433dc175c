"""JAX's persistent compilation cache: where it lives, the variable that moves it or turns it off, and a compiled
program found there again by a later compilation (as by a second process), counted by JAX's cache-hit events."""

import jax
import jax.numpy as jnp
import pytest
from jax.experimental.compilation_cache import compilation_cache

import nhsde
from nhsde.runs import main

VARIABLE = "NHSDE_COMPILATION_CACHE"


@pytest.fixture(autouse=True)
def _restore_jax_cache_settings():
    """Each test changes JAX's global cache settings; put them back (no cache, as conftest.py leaves it)."""
    names = ("jax_persistent_cache_min_compile_time_secs", "jax_persistent_cache_min_entry_size_bytes")
    before = {name: getattr(jax.config, name) for name in names}
    yield
    compilation_cache.set_cache_dir(None)
    compilation_cache.reset_cache()
    for name, value in before.items():
        jax.config.update(name, value)


def _hits() -> list[str]:
    events: list[str] = []
    jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
    return events


def test_the_folder_comes_from_the_variable_or_the_user_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(VARIABLE, "off")
    assert nhsde.enable_compilation_cache() is None
    monkeypatch.setenv(VARIABLE, str(tmp_path / "moved"))
    assert nhsde.enable_compilation_cache() == tmp_path / "moved" and (tmp_path / "moved").is_dir()
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "moved")
    monkeypatch.delenv(VARIABLE)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert nhsde.enable_compilation_cache() == tmp_path / "xdg" / "nhsde" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert nhsde.enable_compilation_cache() == tmp_path / "home" / ".cache" / "nhsde" / "jax"
    assert nhsde.enable_compilation_cache(tmp_path / "given") == tmp_path / "given"  # an explicit folder wins
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match=f"compilation cache '{tmp_path}/file/sub': cannot create the folder"):
        nhsde.enable_compilation_cache(tmp_path / "file" / "sub")


def test_a_small_program_is_cached_and_found_again(tmp_path):
    """Compiled once, the in-memory caches cleared (as in a new process): the second compilation is a cache hit."""
    nhsde.enable_compilation_cache(tmp_path)
    f = jax.jit(lambda x: jnp.sin(x) * 3.0 + 0.25)  # compiles in far less than JAX's default 1 s threshold
    f(jnp.arange(3.0))
    assert any(tmp_path.iterdir()), "nothing was written to the cache"
    jax.clear_caches()
    events = _hits()
    f(jnp.arange(3.0))
    requests = events.count("/jax/compilation_cache/compile_requests_use_cache")
    assert requests > 0 and events.count("/jax/compilation_cache/cache_hits") == requests


def test_the_command_caches_in_the_folder_the_variable_names(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(VARIABLE, str(tmp_path))
    args = ["simulate", "ball-on-vibrating-plane", "--paths", "64", "--t1", "1", "--dt", "0.05", "--save-points", "2"]
    events = _hits()
    assert main(args) == 0
    requests = events.count("/jax/compilation_cache/compile_requests_use_cache")
    assert requests > 0 and len(list(tmp_path.iterdir())) > 0


def test_the_solve_itself_is_cached(tmp_path, caplog):
    """The compiled solve has no host callback (JAX writes no cache entry for one): a plain simulate leaves its solve
    in the cache, and its next compilation (as in a new process) is not a persistent-cache miss."""
    nhsde.enable_compilation_cache(tmp_path)
    scene = nhsde.scenes.BallOnVibratingPlane()

    def ask():
        nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=64, t1=1.0, dt=0.1)

    ask()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("jit__run-")], sorted(tmp_path.iterdir())
    jax.clear_caches()
    events = _hits()
    with jax.explain_cache_misses(True), caplog.at_level("WARNING", logger="jax"):
        ask()
    misses = [r.getMessage() for r in caplog.records if "PERSISTENT COMPILATION CACHE MISS" in r.getMessage()]
    # the cache answered (else an empty list of misses proves nothing); which other programs miss depends on
    # how fast the machine compiled them the first time
    assert events.count("/jax/compilation_cache/cache_hits") > 0, events
    assert not [m for m in misses if "'jit__run'" in m], misses


def test_the_main_jobs_sensitivities_are_cached_and_found_again(tmp_path, monkeypatch, capsys, caplog):
    """The README's job (``nhsde simulate ball-on-vibrating-plane``, here shorter) runs ``moment_sensitivities``: its
    parameters are concrete, checked on the host, so its program (the solve with its ε and ν tangents) has no host
    callback, is written to the cache, and its next compilation (as in a new process) is found there."""
    monkeypatch.setenv(VARIABLE, str(tmp_path))
    args = ["simulate", "ball-on-vibrating-plane", "--paths", "64", "--t1", "1", "--dt", "0.05", "--save-points", "3"]
    jax.clear_caches()  # as a new process: nothing compiled by an earlier test is reused from memory
    assert main(args) == 0
    first = capsys.readouterr().out
    written = [p.name for p in tmp_path.iterdir() if p.name.startswith("jit__sensitivities-")]
    assert len(written) == 1, sorted(p.name for p in tmp_path.iterdir())
    jax.clear_caches()
    events = _hits()
    with jax.explain_cache_misses(True), caplog.at_level("WARNING", logger="jax"):
        assert main(args) == 0
    assert capsys.readouterr().out == first
    messages = [r.getMessage() for r in caplog.records]
    assert not [m for m in messages if "'jit__sensitivities'" in m and ("MISS" in m or "Not writing" in m)], messages
    requests = events.count("/jax/compilation_cache/compile_requests_use_cache")
    assert requests > 0 and events.count("/jax/compilation_cache/cache_hits") == requests
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("jit__sensitivities-")] == written


def test_a_fit_through_the_moment_equations_is_cached(tmp_path, caplog):
    """The optimiser's step through the moment equations has no host callback (the fit checks its loss and
    gradient on the host), so its next compilation (as in a new process) is found in the cache."""
    from nhsde import fit

    nhsde.enable_compilation_cache(tmp_path)
    scene = nhsde.scenes.BallOnVibratingPlane(eps=0.8, nu=0.4)
    observed = fit.Observations.from_statistics([3.0], ("x",), [[0.0]], [[[2.7]]], [[0.05]], [[[0.11]]], 1000)
    model = fit.MomentEquations(y0=scene.initial_state(), dt=0.5)

    def ask():
        return fit.estimate(scene.build(), observed, model, vary=("nu",), max_steps=3)

    first = ask()
    jax.clear_caches()
    events = _hits()
    with jax.explain_cache_misses(True), caplog.at_level("WARNING", logger="jax"):
        again = ask()
    misses = [r.getMessage() for r in caplog.records if "PERSISTENT COMPILATION CACHE MISS" in r.getMessage()]
    assert events.count("/jax/compilation_cache/cache_hits") > 0, events
    assert not [m for m in misses if "'jit__step'" in m or "'jit__value_and_jacobian'" in m], misses
    assert again.values.tolist() == first.values.tolist()
