"""Drift statistics of the coordinates a user names, beside the role-based default: against the ball's closed
form (S0 (3.1)) within the Monte-Carlo standard error, and the exact knife edge on an inclined plane."""

import sys
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import statistics
from nhsde.scenes import BallOnVibratingPlane, ball_covariances

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def ball():
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    ens = nhsde.simulate(
        scene.build(), scene.initial_state(), jax.random.key(3), n_paths=4096, t1=1.0, dt=0.01, solver="sra1"
    )
    return scene, ens


def test_named_coordinates_match_the_closed_form(ball):
    """``coordinates=("x", "u_x")``: a position and a velocity, ``K`` against ``(k_xx, k_xu; k_xu, k_uu)``."""
    scene, ens = ball
    assert statistics.drift_statistics(ens).names == ("x", "y")  # the role-based default
    drift = statistics.drift_statistics(ens, coordinates=("x", "u_x"))
    assert drift.names == ("x", "u_x") and drift.fluctuation.shape == (ens.ts.shape[0], 2, 2)
    p = scene.params
    k_xx, k_xu, k_uu = ball_covariances(ens.ts[-1], p.eps, p.nu, p.delta)
    exact = np.array([[k_xx, k_xu], [k_xu, k_uu]])
    assert drift.fluctuation_se is not None and drift.systematic_se is not None
    z = (np.asarray(drift.fluctuation[-1]) - exact) / np.asarray(drift.fluctuation_se[-1])
    assert np.all(np.abs(z) < 4), z
    assert np.all(np.abs(np.asarray(drift.systematic[-1] / drift.systematic_se[-1])) < 4)  # from rest: zero mean
    reordered = statistics.drift_statistics(ens, coordinates=("u_x", "x"))
    np.testing.assert_array_equal(reordered.fluctuation[:, 0, 1], drift.fluctuation[:, 0, 1])
    np.testing.assert_array_equal(reordered.fluctuation[:, 0, 0], drift.fluctuation[:, 1, 1])
    d_x = statistics.effective_diffusion(ens, coordinates=("x",))
    np.testing.assert_array_equal(d_x, statistics.effective_diffusion(ens)[:1, :1])


@pytest.mark.parametrize("coordinates", [("z",), (), ("x", "x")])
def test_bad_coordinates_are_refused_naming_them(ball, coordinates):
    with pytest.raises(ValueError, match=r"coordinates=.*: name distinct saved components, at least one; saved"):
        statistics.drift_statistics(ball[1], coordinates=coordinates)


@pytest.fixture(scope="module")
def knife_edge():
    sys.path.insert(0, str(DATA))
    try:
        from knife_edge import KnifeEdge  # pyright: ignore[reportMissingImports]
    finally:
        sys.path.remove(str(DATA))
    return KnifeEdge


def test_the_knife_edge_drifts_in_both_coordinates_as_the_exact_solution(knife_edge):
    """At eps = nu = 0 from rest spinning at ω: x = g sin α sin²(ωt)/(2ω²), y = g sin α (ωt − ½ sin 2ωt)/(2ω²)."""
    scene = knife_edge(omega=2.0, slope=1.5)
    ens = nhsde.simulate(
        scene.build(), scene.initial_state(), jax.random.key(0), n_paths=4, t1=3.0, dt=0.005, solver="heun2"
    )
    assert statistics.drift_statistics(ens).names == ("y",)  # one constraint: one dependent coordinate
    drift = statistics.drift_statistics(ens, coordinates=("x", "y"))
    t, w, g, dt = np.asarray(ens.ts), 2.0, 1.5, 0.005
    exact = g / (2 * w**2) * np.stack([np.sin(w * t) ** 2, w * t - np.sin(2 * w * t) / 2], axis=-1)
    np.testing.assert_allclose(drift.systematic, exact, atol=g * (w * dt) ** 2)  # heun2: second order in ω dt
    np.testing.assert_allclose(drift.fluctuation, 0.0, atol=1e-20)  # no noise: every path alike


class Moments(nhsde.AbstractMoments):
    """Moments of the given names and roles (zeros): what a system formulated from a spec would save."""

    ts: jax.Array
    mean: jax.Array
    cov: jax.Array
    names: tuple[str, ...]
    roles: tuple[str, ...]


def test_without_dependent_coordinates_the_error_gives_the_fix_of_the_route():
    names, roles = ("x", "theta", "x_dot"), ("independent_coordinate", "independent_coordinate", "velocity")
    spec = Moments(jnp.zeros(2), jnp.zeros((2, 3)), jnp.zeros((2, 3, 3)), names, roles)
    with pytest.raises(ValueError, match=r"coordinates=\('x',\)\), or .*formulate\(spec, route, dependent=\('x',\)"):
        statistics.drift_statistics(spec)
    velocities = Moments(jnp.zeros(2), jnp.zeros((2, 2)), jnp.zeros((2, 2, 2)), ("u_x", "u_y"), ("velocity",) * 2)
    with pytest.raises(ValueError, match="coordinates=\\('u_x',\\)\\), or build the scene with drift=True"):
        statistics.drift_statistics(velocities)


def test_the_effective_diffusions_standard_error_matches_its_spread_over_keys():
    """16 independent ensembles: the spread of ``D̂`` agrees with the mean reported SE, within the 99.9 % range of
    a sample standard deviation of 16 values (χ² with 15 degrees of freedom)."""
    from scipy.stats import chi2

    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    run: dict[str, Any] = dict(n_paths=256, t1=4.0, dt=0.05, save=nhsde.Save(n=9, paths=True))
    d, se = [], []
    for k in range(16):
        ens = nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(100 + k), **run)
        d.append(np.asarray(statistics.effective_diffusion(ens)))
        se.append(np.asarray(statistics.effective_diffusion_se(ens)))
    ratio = np.std(d, axis=0, ddof=1) / np.mean(se, axis=0)
    low, high = np.sqrt(chi2.ppf([0.0005, 0.9995], 15) / 15)
    assert np.all((low < ratio) & (ratio < high)), (ratio, low, high)
    with pytest.raises(ValueError, match=r"needs the paths: simulate with Save\(paths=True\)"):
        statistics.effective_diffusion_se(
            nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=8, t1=1.0, dt=0.05)
        )


def test_the_effective_diffusion_under_jit_and_with_failed_paths():
    """Under jit (traced times) ``D̂`` and its SE are the plain call's, and a fit start after the last save time is
    refused with the plain message.  Failed paths (nan) are left out of the SE: it equals the delta-method formula
    ``N/(N−1)·std(ψ_p)/√N`` over the other paths, computed here in numpy."""
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0)
    run: dict[str, Any] = dict(n_paths=256, t1=2.0, dt=0.05, save=nhsde.Save(n=5, paths=True))

    def both(eps, t_from=None):
        ens = nhsde.simulate(scene.build().replace_params(eps=eps), scene.initial_state(), jax.random.key(5), **run)
        return statistics.effective_diffusion(ens, t_from), statistics.effective_diffusion_se(ens, t_from)

    plain, traced = both(1.0), jax.jit(both)(1.0)
    for a, b in zip(plain, traced, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="fewer than two save times at or after it"):
        both(1.0, 3.0)
    with pytest.raises(Exception, match="fewer than two save times at or after it"):
        jax.jit(both, static_argnums=1)(1.0, 3.0)

    ens = nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(5), **run)
    failed = np.zeros(256, bool)
    failed[[3, 70, 200]] = True
    paths = np.where(failed[:, None, None], np.nan, np.asarray(ens.paths))
    broken = eqx.tree_at(lambda e: (e.paths, e.failed), ens, (jnp.asarray(paths), jnp.asarray(failed)))
    z = paths[~failed][:, 2:, :2].astype(np.float64)  # t ≥ 1 (the default start), the coordinates x, y
    ts = np.asarray(ens.ts)[2:]
    c = (ts - ts.mean()) / np.sum((ts - ts.mean()) ** 2)
    f = z - z.mean(axis=0)
    psi = np.einsum("n,pni,pnj->pij", c, f, f) / 2
    n = len(z)
    expected = n / (n - 1) * np.std(psi, axis=0, ddof=1) / np.sqrt(n)
    np.testing.assert_allclose(statistics.effective_diffusion_se(broken), expected, rtol=1e-5)
