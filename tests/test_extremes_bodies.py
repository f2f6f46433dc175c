"""Extremes of rolling bodies: near-singular configurations, long runs, ε and ν at their limits.

- A body of revolution upright (nutation θ = 0, where Euler angles are singular,
  and θ = 1e-8): deterministic (``RollingBody`` + ``solve_flow``, classic and
  rubber rolling) and on the vibrating plane (``BodyOnVibratingPlane``).
- A thin disk on its edge (γ ⊥ e₃) deterministic and stochastic; lying flat
  (γ = ±e₃, a face contact) is refused with a clear error by ``RollingBody``,
  and makes every path of the stochastic scene fail loudly (SimulationError).
- Chaplygin's balanced ball at ε = 0 (Itô identities), ε = 1e3 (stiff) and
  ν = 0 (the deterministic flow).

Tolerances.  Adaptive Dopri8 at ``rtol`` keeps each local error below about
``rtol`` relative, and the step count grows linearly with t, so a first integral
or constraint may drift by about ``rtol`` per unit time: asserted ``≤ rtol·t``
(times its scale).  Measured drifts are 1–3 orders below it, except γ² of the
disk rolling straight (0.65 of it at t = 1000: its γ turns 640 times).  Euler–Heun,
the scheme of these Stratonovich scenes, is Euler's rule in the drift and γ
carries no noise, so
``|γ_{k+1}|² = |γ_k|²(1 + h²|n_k × ω_k|²)`` exactly: ``ln|γ|² ≈ h∫|n × ω|²dt``,
first order in h and growing with t, checked against that integral.  The physics
uses n = γ/|γ| only, so this drift does not reach it
(tests/test_bodies_vibrating_plane.py::test_unit_vector_drift_is_harmless_and_reported).
"""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
import nhsde.analysis as A
import nhsde.bodies as B
from nhsde.scenes import BodyOnVibratingPlane, ChaplyginBall, RollingBody


def _oval(u, s):
    """Height of the centre of mass of an oval of revolution, semi-axes s[0] (axis), s[1], centre of mass s[2] below."""
    return jnp.sqrt(s[0] ** 2 * u**2 + s[1] ** 2 * (1 - u**2)) - s[2] * u


# Z(θ) ≈ 0.6 + 0.325θ²: the upright position is a minimum of the potential (stable)
SQUAT = B.RigidBody(mass=1.0, inertia=(0.3, 0.3, 0.5), surface=B.BodyOfRevolution(_oval, shape=(0.8, 1.0, 0.2)))
# Z(θ) ≈ 1.2 − θ²/3: standing on the tip of its long axis, the upright position is a maximum (unstable)
TALL = B.RigidBody(mass=1.0, inertia=(0.5, 0.5, 0.3), surface=B.BodyOfRevolution(_oval, shape=(1.2, 0.8, 0.0)))
DISK = B.RigidBody(mass=1.0, inertia=(0.25, 0.25, 0.5), surface=B.Disk(radius=1.0))
TH = 1e-8
RTOL = 1e-11


def nutation(ys):
    """θ = atan2(|γ⊥|, γ₃): exact near 0, where arccos(γ₃) loses everything below 1e-8."""
    return np.arctan2(np.linalg.norm(ys[..., 3:5], axis=-1), ys[..., 5])


def tilted(theta):
    return [np.sin(theta), 0.0, np.cos(theta)]


def test_upright_body_of_revolution_deterministic():
    """Classic rolling from θ = 0 and θ = 1e-8 (spinning about the axis), t = 200.

    θ = 0 is an equilibrium for any spin (γ̇ = γ × ω = 0) and stays exactly upright.
    Stable upright (potential minimum): θ stays of the order of 1e-8.  Unstable
    upright (maximum, slow spin): the 1e-8 tilt grows to O(1) and the body falls
    through the singular region of Euler angles without NaN.  Energy and γ² drift
    ≤ rtol·t.
    """
    states = []
    for spin in (3.0, 0.5):
        states += [[0.0, 0.0, spin, *tilted(0.0)], [0.0, 0.0, spin, *tilted(TH)]]
    y0 = jnp.asarray(states)
    t1 = 200.0
    integrals = {"E": B.rolling_energy, "g2": lambda y, p: y[3:6] @ y[3:6]}
    for body, stable in ((SQUAT, True), (TALL, False)):
        sc = RollingBody(body=body, contact="classic", gravity=1.0)
        flow = A.solve_flow(sc.vector_field, y0, sc.params, t1=t1, n_save=401, rtol=RTOL)
        ys = np.asarray(flow.ys)
        assert np.all(np.isfinite(ys))
        theta = nutation(ys)
        np.testing.assert_array_equal(ys[0::2], np.broadcast_to(ys[0::2, :1], ys[0::2].shape))  # θ = 0: at rest in γ
        drift = A.integral_drift(integrals, flow, sc.params)
        scale = np.maximum(1.0, np.abs(np.asarray(jax.vmap(B.rolling_energy, in_axes=(0, None))(y0, sc.params))))
        assert np.all(np.asarray(drift["E"]) <= RTOL * t1 * scale), drift["E"]
        assert np.all(np.asarray(drift["g2"]) <= RTOL * t1), drift["g2"]
        if stable:
            assert np.max(theta[1::2]) < 10 * TH, np.max(theta[1::2], axis=1)
        else:  # the slow spinner falls; the fast one sleeps (measured θ ≤ 1.7e-8)
            assert np.max(theta[3]) > 0.5, np.max(theta[3])
        print(
            f"{'stable' if stable else 'unstable'} upright: max θ from 1e-8 = {np.max(theta[1::2], axis=1)}, "
            f"energy drift {np.asarray(drift['E'])}, γ² drift {np.asarray(drift['g2'])} over t = {t1:g}"
        )


@pytest.mark.slow
def test_upright_rubber_rolling_keeps_the_no_spin_constraint():
    """Rubber rolling over the pole (θ = 0 exactly and 1e-8, ω ⊥ γ), t = 1000: the constraint (ω, γ) = 0, S2's
    integral F₂ = g₁^{1/2}ω₃ (S2 (3.4)), energy and γ² drift ≤ rtol·t."""
    sc = RollingBody(body=SQUAT, contact="rubber", gravity=1.0)
    y0 = jnp.stack(
        [sc.initial_state([1.0, 0.0, 0.0], tilted(0.0)), sc.initial_state([np.cos(TH), 0.0, -np.sin(TH)], tilted(TH))]
    )
    t1 = 1000.0
    flow = A.solve_flow(sc.vector_field, y0, sc.params, t1=t1, n_save=201, rtol=RTOL)
    assert bool(jnp.all(jnp.isfinite(flow.ys)))
    assert np.max(nutation(np.asarray(flow.ys))) > 0.5  # it rolls far from upright and back
    drift = A.integral_drift(
        {
            "E": B.rolling_energy,
            "g2": lambda y, p: y[3:6] @ y[3:6],
            "no_spin": lambda y, p: y[:3] @ y[3:6],
            "F2": B.revolution_integral,
        },
        flow,
        sc.params,
    )
    for name, d in drift.items():
        assert float(jnp.max(d)) <= RTOL * t1, (name, d)
    print("rubber rolling over the pole, t = 1000:", {k: float(jnp.max(v)) for k, v in drift.items()})


def log_norm_law(ens, h):
    """``ln|γ(T)|²`` per path and ``h ∫|n × ω|² dt`` (trapezoid over the saved states)."""
    ys = np.asarray(ens.paths)
    n = ys[..., 3:6] / np.linalg.norm(ys[..., 3:6], axis=-1, keepdims=True)
    rate = np.sum(np.cross(n, ys[..., :3]) ** 2, axis=-1)
    dt = np.diff(np.asarray(ens.ts))
    integral = np.sum(0.5 * (rate[:, 1:] + rate[:, :-1]) * dt, axis=1)
    return np.log(np.sum(ys[:, -1, 3:6] ** 2, axis=-1)), h * integral


def norm_drift(sc, y0, key, h, t1, brownian_dt=None):
    """Euler–Heun at step h, 201 saved states: no failure, no NaN, and ln|γ(t1)|² = h∫|n × ω|²dt (ensemble
    means, to 5 %: the trapezoid over the saved states is the only approximation).  Returns the paths and
    ln|γ(t1)|² per path."""
    ens = nhsde.simulate(
        sc.build(),
        y0,
        jax.random.key(key),
        n_paths=y0.shape[0],
        t1=t1,
        steps=nhsde.FixedSteps(h, brownian_dt=brownian_dt),
        solver="heun",
        save=nhsde.Save(n=201, paths=True),
    )
    assert int(ens.n_failed) == 0 and bool(jnp.all(jnp.isfinite(ens.paths)))
    law, predicted = log_norm_law(ens, h)
    assert abs(law.mean() / predicted.mean() - 1) < 0.05, (law.mean(), predicted.mean())
    return np.asarray(ens.paths), law


UPRIGHT_ON_PLANE: dict[str, Any] = {"eps": 0.5, "nu": 1.0, "gravity": 1.0}


def upright_states(n):
    """Half at rest upright (θ = 0), half at θ = 1e-8 spinning at ω₃ = 3."""
    return jnp.asarray([[0.0, 0.0, 0.0, *tilted(0.0)], [0.0, 0.0, 3.0, *tilted(TH)]] * (n // 2))


def test_upright_body_on_the_vibrating_plane():
    """The squat body of revolution on the vibrating plane (ε = 0.5, ν = 1, g = 1) from θ = 0 at rest and from
    θ = 1e-8 spinning at ω₃ = 3; 128 paths to t = 20 (Euler–Heun, h = 0.01): no failure, no NaN, and the
    unit-vector drift ln|γ|² = h∫|n × ω|²dt (to 5 %)."""
    sc = BodyOnVibratingPlane(body=SQUAT, **UPRIGHT_ON_PLANE)
    _, law = norm_drift(sc, upright_states(128), 21, 0.01, 20.0)
    print(
        f"upright on the vibrating plane: | |γ(20)| − 1 | mean {np.mean(np.expm1(law / 2)):.3g}, "
        f"max {np.max(np.expm1(law / 2)):.3g} (h = 0.01)"
    )


@pytest.mark.slow
def test_unit_vector_drift_is_first_order_in_the_step():
    """The same ensemble at h = 0.01 and 0.005 on one Brownian path: ln|γ(20)|² halves with h (ratio 1.8–2.2)."""
    sc = BodyOnVibratingPlane(body=SQUAT, **UPRIGHT_ON_PLANE)
    laws = [norm_drift(sc, upright_states(128), 21, h, 20.0, brownian_dt=0.005)[1] for h in (0.01, 0.005)]
    ratio = laws[0].mean() / laws[1].mean()
    print(f"ln|γ(20)|²: {laws[0].mean():.4g} (h = 0.01), {laws[1].mean():.4g} (h = 0.005), ratio {ratio:.3f}")
    assert 1.8 < ratio < 2.2


def test_disk_on_its_edge():
    """A thin disk with γ ⊥ e₃ (edge contact).  Deterministic, t = 1000: at rest on its edge it stays (an
    equilibrium); rolling straight (ω = ω₃e₃) γ stays in the disk plane (γ₃ = 0 exactly) and ω constant;
    slightly tilted and rolling, energy and γ² drift ≤ rtol·t.  Flat (γ = ±e₃, or within 1e-6 of it)
    is refused: the contact is a face, not a point."""
    sc = RollingBody(body=DISK, contact="classic", gravity=1.0)
    y0 = jnp.stack(
        [
            sc.initial_state([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
            sc.initial_state([0.0, 0.0, 4.0], [1.0, 0.0, 0.0]),
            sc.initial_state([0.1, 0.0, 4.0], tilted(np.pi / 2 - 0.05)),
        ]
    )
    t1 = 1000.0
    flow = A.solve_flow(sc.vector_field, y0, sc.params, t1=t1, n_save=201, rtol=RTOL)
    ys = np.asarray(flow.ys)
    assert np.all(np.isfinite(ys))
    np.testing.assert_array_equal(ys[0], np.broadcast_to(ys[0, :1], ys[0].shape))
    assert np.max(np.abs(ys[1, :, 5])) == 0.0
    np.testing.assert_allclose(ys[1, :, :3], np.broadcast_to(ys[1, :1, :3], ys[1, :, :3].shape), rtol=0, atol=1e-12)
    drift = A.integral_drift({"E": B.rolling_energy, "g2": lambda y, p: y[3:6] @ y[3:6]}, flow, sc.params)
    scale = np.maximum(1.0, np.abs(np.asarray(jax.vmap(B.rolling_energy, in_axes=(0, None))(y0, sc.params))))
    assert np.all(np.asarray(drift["E"]) <= RTOL * t1 * scale) and np.all(np.asarray(drift["g2"]) <= RTOL * t1)
    print(
        f"disk on its edge over t = {t1:g}: energy drift {np.asarray(drift['E'])}, γ² drift {np.asarray(drift['g2'])}"
    )
    for gamma in ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1e-7, 0.0, 1.0]):
        with pytest.raises(ValueError, match="the disk lies flat"):
            sc.initial_state([0.0, 0.0, 1.0], gamma)


def test_disk_on_its_edge_on_the_vibrating_plane():
    """The disk rolling on its edge (ω₃ = 4) on the weakly vibrating plane (ε = 0.05, ν = 0.01, g = 1), 128 paths
    to t = 10: no failure, no NaN, it stays on its edge (|γ₃| ≤ 0.5), and the unit-vector drift law as above.
    Started flat (γ = e₃, where the contact point is undefined) every path fails loudly: SimulationError,
    not NaN statistics."""
    sc = BodyOnVibratingPlane(body=DISK, eps=0.05, nu=0.01, gravity=1.0)
    y0 = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 4.0, 1.0, 0.0, 0.0]), (128, 6))
    ys, law = norm_drift(sc, y0, 22, 0.01, 10.0)
    tilt = np.abs(ys[..., 5]) / np.linalg.norm(ys[..., 3:6], axis=-1)
    assert np.max(tilt) < 0.5
    flat = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 4.0, 0.0, 0.0, 1.0]), (128, 6))
    with pytest.raises(nhsde.SimulationError, match="128 of 128 paths failed"):
        nhsde.simulate(
            sc.build(),
            flat,
            jax.random.key(22),
            n_paths=128,
            t1=10.0,
            dt=0.01,
            solver="heun",
            save=nhsde.Save(n=201, paths=True),
        )
    print(
        f"disk on the vibrating plane: max |γ₃|/|γ| = {np.max(tilt):.3g}, "
        f"| |γ(10)| − 1 | mean {np.mean(np.expm1(law / 2)):.3g}"
    )


# ----------------------------------------------------------------------------- Chaplygin's ball: ε, ν extremes


M0, G0 = np.array([0.3, -0.2, 0.5]), np.array(tilted(0.4))


def chaplygin_run(eps, nu, h=0.01, key=31):
    """1024 paths of Chaplygin's ball from (M₀, γ₀) to t = 5, SRA1 (one compiled program for every ε, ν)."""
    system = ChaplyginBall(eps=eps, nu=nu).build()
    y0 = jnp.asarray(np.concatenate([M0, G0]))
    return (
        system,
        y0,
        nhsde.simulate(
            system, y0, jax.random.key(key), n_paths=1024, t1=5.0, dt=h, solver="sra1", save=nhsde.Save(n=6, paths=True)
        ),
    )


def test_chaplygin_ball_without_friction_obeys_ito_identities():
    """ε = 0: the conservative drift keeps (M, M) and (M, γ), so Itô's formula gives exactly
    E|M|²(t) = |M₀|² + 3νt and E(M, γ)² = (M₀, γ₀)² + ν∫|γ|²dt = (M₀, γ₀)² + νt.  1024 paths (SRA1, h = 0.01)
    to t = 5, every save time within 4 Monte-Carlo standard errors."""
    nu = 1.0
    _, _, ens = chaplygin_run(0.0, nu)
    m0, g0 = M0, G0
    ys = np.asarray(ens.paths)
    ts = np.asarray(ens.ts)
    m2 = np.sum(ys[..., :3] ** 2, axis=-1)
    mg2 = np.sum(ys[..., :3] * ys[..., 3:6], axis=-1) ** 2
    for values, exact in ((m2, m0 @ m0 + 3 * nu * ts), (mg2, (m0 @ g0) ** 2 + nu * ts)):
        se = values.std(axis=0, ddof=1) / np.sqrt(values.shape[0])
        assert np.all(np.abs(values.mean(axis=0) - exact)[1:] <= 4 * se[1:]), (values.mean(axis=0), exact, se)
    print(
        f"ε = 0: E|M|²(5) = {m2[:, -1].mean():.3f} (exact {m0 @ m0 + 15 * nu:.3f}), "
        f"E(M,γ)²(5) = {mg2[:, -1].mean():.3f} (exact {(m0 @ g0) ** 2 + 5 * nu:.3f})"
    )


def test_chaplygin_ball_stiff_friction():
    """ε = 1e3, ν = 1e3 (E[H] = 3ν/(8ε) = 0.375 stationary).  The friction −2εĨ(γ)⁻¹M is not linear in the state,
    so 'exponential' is refused with its clear error; Euler–Maruyama beyond its stability bound (rate 2ε/I_min)
    fails loudly (SimulationError, no silent NaN); at h = 4e-6 (rate·h ≤ 0.027, stationary bias ≤ rate·h/2)
    2048 paths from rest relax by t = 8e-3 (friction alone takes H down at a rate ≥ 4ε/(max Iᵢ + mR²) ≈ 2.7e3:
    e^{−21}) to E[H] within 4 SE + that bias."""
    eps = nu = 1e3
    sc = ChaplyginBall(eps=eps, nu=nu)
    system = sc.build()
    y0 = sc.initial_state()
    with pytest.raises(ValueError, match="linear drift"):
        nhsde.simulate(system, y0, jax.random.key(0), n_paths=64, t1=1e-3, dt=1e-4, solver="exponential")
    rate = 2 * eps / 0.3  # largest eigenvalue of 2εĨ⁻¹ is at most 2ε/min(I)
    with pytest.raises(nhsde.SimulationError):
        nhsde.simulate(system, y0, jax.random.key(0), n_paths=64, t1=200 * 4 / rate, dt=4 / rate, solver="euler")
    h = 4e-6
    ens = nhsde.simulate(
        system,
        y0,
        jax.random.key(32),
        n_paths=2048,
        t1=8e-3,
        dt=h,
        solver="euler",
        save=nhsde.Save(names=("energy",), n=2),
    )
    exact = 3 * nu / (8 * eps)
    value, se = float(ens.mean[-1, 0]), float(ens.mean_se[-1, 0])
    bias = rate * h / (2 - rate * h) * exact  # Euler–Maruyama's stationary variance σ²/(2λ(1 − λh/2)) at rate λ
    assert abs(value - exact) <= 4 * se + bias, (value, exact, se)
    print(f"ε = 1e3: E[H] = {value:.4f} ± {se:.4f} (exact {exact}), bias bound {bias:.4f}")


def deterministic_error(h):
    """ν = 0 (ε = 0.5): every path is the same; its largest distance from the Dopri8 solution over the save times."""
    system, y0, ens = chaplygin_run(0.5, 0.0, h=h)
    np.testing.assert_array_equal(np.asarray(ens.paths), np.broadcast_to(ens.paths[:1], ens.paths.shape))
    assert float(jnp.max(jnp.abs(ens.cov))) == 0.0
    flow = A.solve_flow(system.drift_fn, y0[None], system.params, t1=5.0, n_save=6, rtol=RTOL)
    return float(jnp.max(jnp.abs(ens.mean - flow.ys[0])))


def test_chaplygin_ball_without_noise_is_the_deterministic_flow():
    """ν = 0: the paths coincide (covariances exactly 0) and follow the Dopri8 solution of the drift: at h = 0.01
    within 0.5·h² = 5e-5 (measured 9e-6; SRA1's deterministic part is Ralston's second-order method, the slow
    test below measures the order)."""
    error = deterministic_error(0.01)
    print(f"ν = 0: max |SRA1 − Dopri8| over t ≤ 5: {error:.3g} (h = 0.01)")
    assert error < 0.5 * 0.01**2


@pytest.mark.slow
def test_chaplygin_ball_without_noise_converges_at_second_order():
    """ν = 0: the distance to the Dopri8 solution shrinks ×4 (3–5) when h halves from 0.02 to 0.01."""
    errors = [deterministic_error(h) for h in (0.02, 0.01)]
    print(f"ν = 0: max |SRA1 − Dopri8| over t ≤ 5: {errors[0]:.3g} (h = 0.02), {errors[1]:.3g} (h = 0.01)")
    assert 3.0 < errors[0] / errors[1] < 5.0, errors
