"""The command's estimate before a run: a pilot of one chunk's paths, its compilation counted apart."""

import re
from pathlib import Path

import pytest

from nhsde.runs import _cli
from nhsde.runs._config import RunConfig, SceneSource


def ball_config(n_paths: int, t1: float = 5.0):
    raw = {
        "scene": "ball-on-vibrating-plane",
        "seed": 0,
        "precision": "float32",
        "parameters": {},
        "solver": {"name": "euler", "dt": 0.01, "t1": t1},
        "paths": {"n": n_paths, "chunk": n_paths},
        "statistics": {"save_points": 2, "save": None},
    }
    return RunConfig.from_dict(raw, scene_source=SceneSource(Path.cwd()))


def test_the_pilot_runs_the_runs_chunk_and_counts_its_compilation_apart(monkeypatch):
    """(Its seconds kept for the next process: ``test_internal_compilation_cache.py``.)"""
    monkeypatch.setattr(_cli, "_cache_folder", None)
    text = _cli._plan(ball_config(2048), 2048, derivatives=True)
    found = re.search(r"roughly ([0-9.]+) s with the derivatives, about ([0-9.]+) s of it compiling", text)
    assert found and float(found[2]) < float(found[1]), text
    assert text.endswith("(an estimate from a timed pilot of 2048 paths × 20 steps)"), text


@pytest.mark.parametrize("n_paths", [64, 256])
def test_a_run_about_as_short_as_its_pilot_gets_no_estimate(n_paths):
    """80 steps: the pilot's two calls of 20 steps over the same chunk would cost half the run."""
    assert _cli._plan(ball_config(n_paths, t1=0.8), n_paths) == f"{n_paths} paths × 80 steps (euler, dt = 0.01)"
