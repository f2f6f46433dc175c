"""A scene of the user's goes wherever a shipped one goes: ``MODULE:CLASS`` on the command line, in run files and
through the ``nhsde.scenes`` entry points; a run of it resumes only from the same module source."""

import hashlib
import itertools
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nhsde.runs import ConfigError, RunConfig, load_config, load_run, main, run
from nhsde.scenes import AbstractScene, get_scene, installed_scenes

KNIFE_EDGE = Path(__file__).parent / "data" / "knife_edge.py"
_count = itertools.count()


def _module(directory: Path) -> str:
    """A fresh copy of the knife-edge scene's module in ``directory``; its name (unique: imports are cached)."""
    name = f"user_knife_edge_{next(_count)}"
    shutil.copy(KNIFE_EDGE, directory / f"{name}.py")
    return name


def test_module_class_names_a_scene_class_on_the_path(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    name = _module(tmp_path)
    cls = get_scene(f"{name}:KnifeEdge")
    assert issubclass(cls, AbstractScene) and cls.__module__ == name
    system = cls(omega=2.0).build()
    assert system.layout.names == ("x", "y", "theta", "x_dot", "y_dot", "theta_dot")


@pytest.mark.parametrize(
    "spec, message",
    [
        ("no_such_module_here:KnifeEdge", "no module named 'no_such_module_here' on the Python path"),
        ("{m}:Knife", "module '{m}' has no attribute 'Knife'; its scene classes: KnifeEdge"),
        ("{m}:kinetic", "kinetic is a function, not a scene class"),
        ("{m}:KnifeEdgeParameters", "KnifeEdgeParameters is a class, not a scene class"),
        ("nhsde.scenes:AbstractSpecScene", "AbstractSpecScene is an abstract scene; it leaves .*configuration"),
        ("{m}:", "expected MODULE:CLASS"),
    ],
)
def test_a_bad_module_class_is_refused_naming_the_argument(tmp_path, monkeypatch, spec, message):
    monkeypatch.syspath_prepend(str(tmp_path))
    m = _module(tmp_path)
    spec, message = spec.format(m=m), message.format(m=m)
    with pytest.raises(ValueError, match=f"scene '{spec}': {message}"):
        get_scene(spec)
    with pytest.raises(ConfigError, match=f"scene = '{spec}': {message}"):
        RunConfig.from_dict({"scene": spec, "solver": {"dt": 0.1, "t1": 1.0}, "paths": {"n": 64}})


def test_a_module_that_fails_to_import_is_named(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    (tmp_path / "broken_user_scene.py").write_text("import no_such_dependency_here\n")
    with pytest.raises(ValueError, match="importing module 'broken_user_scene' failed: No module named 'no_such_"):
        get_scene("broken_user_scene:KnifeEdge")


def test_the_command_line_runs_a_user_scene_from_the_current_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    name = _module(tmp_path)
    args = ["simulate", f"{name}:KnifeEdge", "--paths", "64", "--t1", "2", "--dt", "0.05", "--x64"]
    assert main([*args, "--set", "nu=0.5", "--save-points", "3", "--out", "knife.nc"]) == 0
    out = capsys.readouterr().out
    assert f"scene {name}:KnifeEdge: eps=0, nu=0.5" in out and "m[y] (systematic drift)" in out
    ds = load_run(tmp_path / "knife.nc")
    assert ds.attrs["scene"] == f"{name}:KnifeEdge" and len(ds.attrs["scene_source"]) == 64
    assert str(tmp_path) not in sys.path  # the command leaves sys.path as it was


def test_a_run_file_of_a_user_scene_resumes_only_from_the_same_source(tmp_path):
    """At eps = nu = 0 the mean is the exact solution; a run file records its module's SHA-256, checked before the
    import; editing the scene's module makes loading (and, trusted, resuming) refuse."""
    name = _module(tmp_path)  # beside the run file: found there, with no sys.path entry
    source = tmp_path / f"{name}.py"
    sha256 = hashlib.sha256(source.read_bytes()).hexdigest()
    (tmp_path / "run.toml").write_text(
        f'scene = "{name}:KnifeEdge"\nscene_sha256 = "{sha256}"\n[options]\nomega = 2.0\n'
        '[solver]\nname = "heun2"\ndt = 0.01\nt1 = 2.0\n[paths]\nn = 64\nchunk = 64\n[statistics]\nsave_points = 5\n'
    )
    config = load_config(tmp_path / "run.toml")
    ds = run(config, tmp_path / "run.nc")
    t, w, dt = ds["time"].values, 2.0, 0.01
    x, y = np.sin(w * t) ** 2 / (2 * w**2), (w * t - np.sin(2 * w * t) / 2) / (2 * w**2)
    np.testing.assert_allclose(ds["mean"].sel(name="x"), x, atol=(w * dt) ** 2)  # heun2: second order in ω dt
    np.testing.assert_allclose(ds["mean"].sel(name="y"), y, atol=(w * dt) ** 2)
    assert ds.attrs["scene_source"] == sha256
    run(config, tmp_path / "run.nc")  # the same source: resumes (nothing left to do)
    sys.modules.pop(name)
    source.write_text(source.read_text().replace("return -p.mass * p.slope * q[0]", "return p.mass * p.slope * q[0]"))
    with pytest.raises(ConfigError, match=f"has SHA-256 [0-9a-f]{{64}}, not the {sha256} recorded"):
        load_config(tmp_path / "run.toml")
    assert name not in sys.modules  # refused before the import
    toml = tmp_path / "run.toml"
    toml.write_text(toml.read_text().replace(f'scene_sha256 = "{sha256}"\n', ""))  # no hash, trusted: the run file
    with pytest.raises(ConfigError, match=r"was started with the scene's module source \(SHA-256\) " + sha256):
        run(load_config(toml, trust_scene=True), tmp_path / "run.nc")


MARKER_CODE = "import pathlib; pathlib.Path(__file__).with_suffix('.ran').write_text('ran')\n"


def test_a_run_file_from_someone_else_runs_none_of_their_code(tmp_path, monkeypatch, capsys):
    """A run file naming ``evil:Evil`` used to import ./evil.py (running it) before anything was checked."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "evil.py").write_text(MARKER_CODE)
    (tmp_path / "run.toml").write_text('scene = "evil:Evil"\n[solver]\ndt = 0.1\nt1 = 1.0\n[paths]\nn = 64\n')
    assert main(["simulate", "--config", "run.toml"]) == 2
    err = capsys.readouterr().err
    assert "records no scene_sha256" in err and "--trust-scene" in err
    assert hashlib.sha256(MARKER_CODE.encode()).hexdigest() in err  # what to record, found without running it
    assert not (tmp_path / "evil.ran").exists() and "evil" not in sys.modules


def test_shipped_scenes_run_no_module_of_the_current_directory(tmp_path):
    """The ``nhsde`` command used to put the current directory first on sys.path: a ./scipy.py or ./optax.py ran
    when a user simulated or fitted a shipped scene there.  A plain console script does not look there."""
    for name in ("scipy", "optax", "xarray"):
        (tmp_path / f"{name}.py").write_text(MARKER_CODE)
    command = Path(sys.executable).parent / "nhsde"
    assert command.exists(), "the console script of the installed package"
    env = {**os.environ, "NHSDE_COMPILATION_CACHE": "off"}
    args = ["simulate", "ball-on-vibrating-plane", "--paths", "64", "--t1", "0.1", "--dt", "0.01"]
    out = subprocess.run([str(command), *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert not list(tmp_path.glob("*.ran")), "a module of the current directory ran"


def test_a_compilation_cache_others_can_write_to_is_refused(tmp_path, monkeypatch):
    """The cache holds code that runs: a folder writable by others was used silently."""
    import nhsde

    shared = tmp_path / "shared"
    shared.mkdir(mode=0o700)
    shared.chmod(0o777)
    with pytest.raises(ValueError, match=r"not used: its mode 777 lets others write to it"):
        nhsde.enable_compilation_cache(shared)
    monkeypatch.setenv("NHSDE_COMPILATION_CACHE", str(shared))
    assert main(["scenes"]) == 2


def _install(site: Path, module: str, entry: str) -> None:
    """An installed distribution in ``site`` whose entry point ``nhsde.scenes`` names ``module:KnifeEdge``."""
    info = site / "user_scenes-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: user-scenes\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[nhsde.scenes]\n{entry} = {module}:KnifeEdge\nbroken = {module}:Nope\n")


def test_an_installed_package_adds_scenes_by_entry_point(tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(tmp_path))
    name = _module(tmp_path)
    _install(tmp_path, name, "knife-edge")
    assert installed_scenes() == {"knife-edge": f"{name}:KnifeEdge", "broken": f"{name}:Nope"}
    assert get_scene("knife-edge").__module__ == name
    with pytest.raises(ValueError, match=f"scene 'broken': the installed entry point broken = '{name}:Nope'"):
        get_scene("broken")
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    assert "knife-edge: Knife edge on an inclined plane, spinning at rate omega from rest at the origin. " in out
    assert f"(installed: {name}:KnifeEdge)" in out and "broken: cannot be loaded" in out
    assert "ball-on-vibrating-plane: " in out


def test_a_user_scene_runs_in_a_fresh_process_from_pythonpath(tmp_path):
    """The ``nhsde`` command in its own process, the scene found through PYTHONPATH."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    name = _module(scenes)
    env = {**os.environ, "PYTHONPATH": str(scenes), "NHSDE_COMPILATION_CACHE": "off"}
    args = [sys.executable, "-m", "nhsde.runs", "simulate", f"{name}:KnifeEdge", "--paths", "64", "--t1", "1"]
    done = subprocess.run([*args, "--dt", "0.1", "--save-points", "2"], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert f"scene {name}:KnifeEdge" in done.stdout and "m[y] (systematic drift)" in done.stdout
