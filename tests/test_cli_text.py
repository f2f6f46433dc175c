"""What the command prints for people: plain text in ``nhsde scenes``, true help, the licence that ships."""

import re
from pathlib import Path

import pytest

from nhsde.runs import build_parser, main
from nhsde.scenes import SCENES

ROOT = Path(__file__).resolve().parents[1]
MARKUP = re.compile(r":[\w:]+:`|``|\bS\d\b")  # reST roles and literals, the papers' shorthand (S0 §3)


def test_nhsde_scenes_prints_plain_text(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    assert all(f"{name}: " in out for name in SCENES)
    assert not MARKUP.findall(out), [line for line in out.splitlines() if MARKUP.search(line)]


def test_help_tells_the_dt_of_rmse(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "time step (default 0.01); with --rmse the coarsest step the estimators consider" in text
    assert "(default: t1 in equal steps of at most 0.25)" in text
    assert "with --rmse or [accuracy], the estimate as JSON" in text


def test_the_licence_is_mit_and_ships_by_default():
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert 'license = { text = "MIT" }' in (ROOT / "pyproject.toml").read_text()  # hatchling adds LICENSE* files


def test_every_solver_alias_is_listed_in_help(capsys):
    """``--solver weak2`` worked but was listed neither in ``--help`` nor in the runs guide."""
    import nhsde
    from nhsde.runs import build_parser

    for command in ("simulate", "sweep", "fit"):
        with pytest.raises(SystemExit):
            build_parser().parse_args([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert all(name in text for name in nhsde.SOLVERS), (command, text)
    guide = (Path(__file__).parents[1] / "docs" / "guide" / "runs.md").read_text()
    assert all(f"`{name}`" in guide for name in nhsde.SOLVERS)


def test_an_accuracy_run_may_ask_for_an_observable():
    """``--relative-rmse 0.01 --statistic "mean energy"`` on the sleigh was refused: "energy not saved"."""
    from nhsde.runs import RunConfig

    raw = {"scene": "chaplygin-sleigh", "solver": {"dt": 0.1, "t1": 1.0}, "paths": {"n": 64}}
    config = RunConfig.from_dict(raw | {"accuracy": {"relative_rmse": 0.01, "statistic": "mean energy"}})
    assert "energy" in config.build().names
    assert RunConfig.from_dict(raw).build().names == config.build().system.layout.names  # a plain run: as before


def test_save_chooses_what_a_plain_run_saves_and_prints(capsys):
    """A plain run of a 6-state scene printed all 27 covariances, with no way to choose."""
    argv = ["simulate", "chaplygin-sleigh", "--paths", "64", "--t1", "0.2", "--dt", "0.05", "--save-points", "3"]
    assert main([*argv, "--save", "y,energy"]) == 0
    rows = [line.split()[0] for line in capsys.readouterr().out.splitlines() if line[:2] in ("m[", "K[")]
    assert rows == ["m[y]", "m[energy]", "K[y,y]", "K[energy,y]", "K[energy,energy]"]
    assert main([*argv, "--save", "y,nope"]) == 2
    assert "--save: 'nope' is not offered; this scene offers x, y, theta, v, omega, energy" in capsys.readouterr().err
