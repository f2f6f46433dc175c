"""Spec-built scenes against closed forms, conserved quantities and the printed equations of S1.

Trajectories are high-accuracy diffrax solves (Dopri8, rtol = atol = 1e-12) of the
vector field each route builds, so the comparisons test the library's equations,
not a solver.
"""

from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import mechanics as mech
from nhsde.scenes import (
    BeadOnRotatingRod,
    BeghinPlate,
    ChaplyginSleighFromSpec,
    ContactOscillator,
    VerticalRollingDisk,
)

RTOL = 1e-12


def solve(form, y0, ts, extra=None, rtol=RTOL):
    """Solve ``ż = drift`` (plus ``extra(t, y)`` appended as quadratures) at times ``ts``."""
    p = form.spec.params

    def field(t, z, args):
        y = z if extra is None else z[:-1]
        dy = form.drift(t, y, p)
        return dy if extra is None else jnp.concatenate([dy, extra(t, y)[None]])

    z0 = y0 if extra is None else jnp.concatenate([y0, jnp.zeros(1)])
    sol = dfx.diffeqsolve(
        dfx.ODETerm(field),
        dfx.Dopri8(),
        ts[0],
        ts[-1],
        1e-3,
        z0,
        saveat=dfx.SaveAt(ts=ts),
        stepsize_controller=dfx.PIDController(rtol=rtol, atol=rtol),
        max_steps=200_000,
    )
    return sol.ys


@eqx.filter_jit
def batched(form, method, *args):
    """``form.method`` over a batch of states (compiled once per route and spec structure)."""
    return jax.vmap(getattr(form, method))(*args)


def physical(form, ts, ys):
    """``(q, q̇)`` along a solution."""
    q, v, _ = jax.vmap(lambda t, y: form.velocities(t, y, form.spec.params))(ts, ys)
    return q, v


# --------------------------------------------------------------------------- Chaplygin sleigh


SLOW = pytest.mark.slow
# The routes agree with each other at random states (test_mechanics_routes); by default one route is solved here.
ROUTES_FAST_FIRST = ["reduced"] + [pytest.param(r, marks=SLOW) for r in ("hamiltonian", "multipliers", "gauss")]


@pytest.mark.parametrize("route", ROUTES_FAST_FIRST)
def test_sleigh_closed_form(route):
    """v = V tanh(κV(t−t0)), ω = ±√(m/J) V sech(κV(t−t0)), J = I + ma², κ = ma/J, V = √(2E/m)."""
    m, inertia, a = 1.3, 0.6, 0.8
    scene = ChaplyginSleighFromSpec(route=route, eps=0.0, nu=0.0, mass=m, inertia=inertia, offset=a)
    form = mech.formulate(scene.spec(), route, dependent=("y",))
    j = inertia + m * a**2
    kappa, energy = m * a / j, 0.9
    big_v = np.sqrt(2 * energy / m)
    t0, ts = 1.5, jnp.linspace(0.0, 3.0, 13)
    s = kappa * big_v * (np.asarray(ts) - t0)
    for sign in (1.0, -1.0):
        theta0 = -sign * np.sqrt(m / j) / kappa * 2 * np.arctan(np.tanh(kappa * big_v * t0 / 2))  # θ(t0) = 0
        v0, w0 = big_v * np.tanh(-kappa * big_v * t0), sign * np.sqrt(m / j) * big_v / np.cosh(kappa * big_v * t0)
        q0 = jnp.array([0.0, 0.0, theta0])
        y0 = form.state(q0, jnp.array([v0 * np.cos(theta0), v0 * np.sin(theta0), w0]))
        # the energy drift is Dopri8's own global error, ∝ its tolerance (9.9e-11 at 1e-12 with LAPACK's solves,
        # 1.3e-10 with the unrolled ones, which change the step sequence; 8.8e-12 at 1e-13): solved at 1e-13
        q, qd = physical(form, ts, eqx.filter_jit(solve)(form, y0, ts, rtol=1e-13))
        v = np.cos(q[:, 2]) * qd[:, 0] + np.sin(q[:, 2]) * qd[:, 1]
        w = np.asarray(qd[:, 2])
        err = max(
            np.max(np.abs(v - big_v * np.tanh(s))), np.max(np.abs(w - sign * np.sqrt(m / j) * big_v / np.cosh(s)))
        )
        e = 0.5 * (m * v**2 + j * w**2)
        print(
            f"sleigh {route} sign {sign:+.0f}: max error of (v, ω) {err:.2e}, energy drift "
            f"{np.max(np.abs(e - energy)):.2e}"
        )
        assert err < 1e-8
        assert np.max(np.abs(e - energy)) < 1e-10
        assert np.max(np.abs(-np.sin(q[:, 2]) * qd[:, 0] + np.cos(q[:, 2]) * qd[:, 1])) < 1e-9  # knife constraint


# --------------------------------------------------------------------------- vertical rolling disk


DISK = {"mass": 1.2, "radius": 0.7, "w_theta": 1.1, "w_phi": 0.6}


def _disk_exact(ts):
    _, r, w_theta, w_phi = DISK.values()
    phi = 0.5 + w_phi * ts
    rho = r * w_theta / w_phi
    q = jnp.stack(
        [0.3 + rho * (jnp.sin(phi) - np.sin(0.5)), -0.2 - rho * (jnp.cos(phi) - np.cos(0.5)), 0.1 + w_theta * ts, phi],
        1,
    )
    qd = jnp.stack(
        [
            r * w_theta * jnp.cos(phi),
            r * w_theta * jnp.sin(phi),
            jnp.full_like(phi, w_theta),
            jnp.full_like(phi, w_phi),
        ],
        1,
    )
    return q, qd


def _disk_spec():
    return VerticalRollingDisk(
        eps=0.0, nu=0.0, mass=DISK["mass"], radius=DISK["radius"], roll_inertia=0.4, turn_inertia=0.3
    ).spec()


@pytest.mark.parametrize("route", ROUTES_FAST_FIRST)
def test_disk_exact_solution(route):
    """θ̇ = Ω_θ, φ̇ = Ω_φ constant; the contact point runs on a circle of radius R Ω_θ/Ω_φ."""
    ts = jnp.linspace(0.0, 10.0, 21)
    exact_q, exact_qd = _disk_exact(ts)
    form = mech.formulate(_disk_spec(), route, dependent=("x", "y"))
    q, qd = physical(form, ts, eqx.filter_jit(solve)(form, form.state(exact_q[0], exact_qd[0]), ts))
    err = float(jnp.max(jnp.abs(q - exact_q)))
    print(f"disk {route}: max |q − exact| over t ≤ 10: {err:.2e}")
    assert err < 1e-9
    assert float(jnp.max(jnp.abs(qd - exact_qd))) < 1e-9


def test_disk_multipliers():
    """λ = m Ω_φ R Ω_θ (−sin φ, cos φ) along the exact motion; the reactions are the contact force and its torque."""
    m, r, w_theta, w_phi = DISK.values()
    ts = jnp.linspace(0.0, 10.0, 21)
    exact_q, exact_qd = _disk_exact(ts)
    phi = exact_q[:, 3]
    exact_lam = m * w_phi * r * w_theta * jnp.stack([-jnp.sin(phi), jnp.cos(phi)], 1)
    multipliers = mech.formulate(_disk_spec(), "multipliers", dependent=("x", "y"))
    lam = batched(multipliers, "multipliers", exact_q, exact_qd)
    assert float(jnp.max(jnp.abs(lam - exact_lam))) < 1e-12
    reactions = batched(multipliers, "reactions", exact_q, exact_qd)
    np.testing.assert_allclose(reactions[:, :2], exact_lam, atol=1e-12)  # the contact force on the centre
    assert (
        float(jnp.max(jnp.abs(reactions[:, 2] + r * (jnp.cos(phi) * exact_lam[:, 0] + jnp.sin(phi) * exact_lam[:, 1]))))
        < 1e-12
    )


# --------------------------------------------------------------------------- contact oscillator


def _oscillator_drift_rates(t1, routes, rate=0.0):
    scene = ContactOscillator(eps=0.0, nu=0.0, mass=1.0, stiffness=1.0, gravity=0.0)
    spec = scene.spec()
    q0, qd0 = scene.configuration()
    ts = jnp.linspace(0.0, t1, 11)
    rates = {}
    for route in routes:
        form = mech.formulate(
            spec, route, dependent=("x",), stabilization=rate if route in ("multipliers", "gauss") else 0.0
        )
        q, qd = physical(form, ts, eqx.filter_jit(solve)(form, form.state(q0, qd0), ts))
        h = 0.5 * jnp.sum(qd**2, 1) + 0.5 * (q[:, 0] ** 2 + q[:, 1] ** 2)
        h_y = 0.5 * (q[:, 1] ** 2 + qd[:, 1] ** 2)
        residual = jnp.abs(qd[:, 0] + q[:, 1] * qd[:, 2])
        rates[route] = (
            float(jnp.max(jnp.abs(h - h[0])) / t1),
            float(jnp.max(jnp.abs(h_y - h_y[0])) / t1),
            float(jnp.max(residual)),
        )
        print(
            f"contact oscillator {route} (κ = {rate:g}), t ≤ {t1:g}: max |ΔH|/t = {rates[route][0]:.2e}, "
            f"max |ΔH_y|/t = {rates[route][1]:.2e}, max |ẋ + y ż| = {rates[route][2]:.2e}"
        )
    return rates


def test_contact_oscillator_conserves_h_and_h_y():
    for route, (h_rate, hy_rate, residual) in _oscillator_drift_rates(100.0, ["reduced"]).items():
        assert h_rate < 1e-11 and hy_rate < 1e-11, route
        assert residual < 1e-9, route


@pytest.mark.slow
def test_contact_oscillator_conserves_h_and_h_y_over_a_long_run():
    """t ≤ 2000.  The reduced routes stay on the constraint; H and H_y keep to rounding.

    Routes (c), (d) carry ẋ too: the solver's errors off the constraint feed the
    energy, whose error then grows like t² (≈ 3e-8 at t = 2000, 1.7e-11 per unit
    time); Baumgarte stabilisation (κ = 1/s) bounds it (≈ 4e-11 over the run).
    """
    for route, (h_rate, hy_rate, residual) in _oscillator_drift_rates(2000.0, ["reduced", "hamiltonian"]).items():
        assert h_rate < 1e-13 and hy_rate < 1e-13, route
    free = _oscillator_drift_rates(2000.0, ["multipliers", "gauss"])
    held = _oscillator_drift_rates(2000.0, ["multipliers", "gauss"], rate=1.0)
    for route in ("multipliers", "gauss"):
        assert free[route][1] < 1e-13 and held[route][1] < 1e-13  # H_y: no reaction along y
        assert free[route][2] < 1e-9 and held[route][2] < 1e-9  # the constraint itself
        assert held[route][0] * 2000.0 < 1e-10 < free[route][0] * 2000.0  # energy: bounded with κ, growing without


# --------------------------------------------------------------------------- Beghin's plate


def _beghin_states(n=100):
    k1, k2 = jax.random.split(jax.random.key(11))
    beta = jax.random.uniform(k1, (n,), minval=-3.0, maxval=3.0)
    rate = jax.random.normal(k2, (n,))
    return jnp.stack([beta + jnp.pi / 2, beta], 1), jnp.stack([rate, rate], 1)


@pytest.mark.parametrize("realisation", ["servo", "contact"])
def test_beghin_plate_reproduces_the_printed_equations(realisation):
    """Servo: S1 (3.4) M(b²+k²)β̈ − MRbβ̇² + Fa sinβ = 0; contact: S1 (3.5) [M(R²+b²+k²)+I₁]β̈ + F(a sinβ + R cosβ) = 0."""
    qs, vs = _beghin_states()
    for disk_inertia in (2.0, 7.0):
        scene = BeghinPlate(realisation=realisation, eps=0.0, nu=0.0, disk_inertia=disk_inertia)
        p = scene.params
        mm, k, b, r, f, a = p.plate_mass, p.gyration, p.hinge_offset, p.disk_radius, p.force, p.arm
        beta, rate = qs[:, 1], vs[:, 1]
        if realisation == "servo":
            printed = (mm * r * b * rate**2 - f * a * jnp.sin(beta)) / (mm * (b**2 + k**2))
        else:
            printed = -f * (a * jnp.sin(beta) + r * jnp.cos(beta)) / (mm * (r**2 + b**2 + k**2) + disk_inertia)
        for route in ("reduced", "multipliers"):
            form = mech.formulate(scene.spec(), route, dependent=("alpha",))
            acc = batched(form, "accelerations", qs, vs)
            err = float(jnp.max(jnp.abs(acc[:, 1] - printed)))
            print(f"Beghin {realisation}, I₁ = {disk_inertia}, {route}: max |β̈ − printed| = {err:.2e}")
            assert err < 1e-12
            assert float(jnp.max(jnp.abs(acc[:, 0] - acc[:, 1]))) < 1e-12  # α̈ = β̈: the relation holds


def test_beghin_servo_torque_is_the_control_of_kirgetovs_equation():
    """The servo reaction μ on the disk equals u of S1 (3.6) with β̈ from (3.4) — Rumyantsev's resolution."""
    qs, vs = _beghin_states()
    scene = BeghinPlate(realisation="servo", eps=0.0, nu=0.0)
    p = scene.params
    form = mech.formulate(scene.spec(), "multipliers", dependent=("alpha",))
    mu = batched(form, "multipliers", qs, vs)[:, 0]
    acc = batched(form, "accelerations", qs, vs)[:, 1]
    beta = qs[:, 1]
    u = (p.plate_mass * (p.disk_radius**2 + p.hinge_offset**2 + p.gyration**2) + p.disk_inertia) * acc + p.force * (
        p.arm * jnp.sin(beta) + p.disk_radius * jnp.cos(beta)
    )
    assert float(jnp.max(jnp.abs(mu - u))) < 1e-12
    assert float(jnp.max(jnp.abs(u))) > 0.1
    contact = mech.formulate(
        BeghinPlate(realisation="contact", eps=0.0, nu=0.0).spec(), "reduced", dependent=("alpha",)
    )
    assert float(jnp.min(jnp.abs(batched(contact, "accelerations", qs, vs)[:, 1] - acc))) > 0  # the two differ


# --------------------------------------------------------------------------- controlled constraint


def test_controlled_constraint_energy_change_is_the_work_of_the_reactions():
    """S1 (2.5)–(2.6): d(T + Π) = (Dᵀλ)·dq; and λ = m (2 ṙ u̇ + r ü) depends on ü (S1 (2.4))."""
    scene = BeadOnRotatingRod(eps=0.0, nu=0.0, spin=0.7, wobble=0.4, wobble_rate=1.3)
    spec, p = scene.spec(), scene.params
    form = mech.formulate(spec, "multipliers")
    q0, qd0 = scene.configuration()
    ts = jnp.linspace(0.0, 3.0, 11)

    def power(t, y):
        q, v, _ = form.velocities(t, y, p)
        return form.reactions(q, v, t=t) @ v

    zs = eqx.filter_jit(solve)(form, form.state(q0, qd0), ts, power)
    q, qd = physical(form, ts, zs[:, :-1])
    energy = jax.vmap(lambda q, v, t: spec.energy(q, v, jnp.zeros(0), t, p))(q, qd, ts)
    change, work = energy - energy[0], zs[:, -1]
    print(f"rod: energy change {np.asarray(change)[-3:]}, work of the reactions {np.asarray(work)[-3:]}")
    assert float(jnp.max(jnp.abs(change))) > 0.5  # the control pumps energy in and out
    assert float(jnp.max(jnp.abs(change - work))) < 1e-10 * float(jnp.max(energy))  # the solver's rtol 1e-12, summed
    assert float(jnp.max(jnp.abs(q[:, 0] * jnp.sin(p.control(ts)) - q[:, 1] * jnp.cos(p.control(ts))))) < 1e-9
    # the multiplier against its closed form at the solution's states
    u_dot = jax.vmap(jax.grad(p.control))(ts)
    u_ddot = jax.vmap(jax.grad(jax.grad(p.control)))(ts)
    radius = jnp.hypot(q[:, 0], q[:, 1])
    r_dot = (q[:, 0] * qd[:, 0] + q[:, 1] * qd[:, 1]) / radius
    lam = batched(form, "multipliers", q, qd, jnp.zeros((len(ts), 0)), ts)[:, 0]
    np.testing.assert_allclose(lam, p.mass * (2 * r_dot * u_dot + radius * u_ddot), rtol=1e-9, atol=1e-10)


# --------------------------------------------------------------------------- constraint residual


def test_constraint_residual_reduced_at_round_off_multipliers_bounded():
    """Along noisy Euler–Maruyama runs of the disk (dt = 0.01, t ≤ 10): mean over paths of |A q̇ + A0|.

    Reduced form: zero to rounding (q̇'' is computed from the constraint).  Multiplier
    form: each step injects O(dt |Δq̇|) because A(q) turns during the step, so the
    residual random-walks (∝ √t) without stabilisation and is held at the
    injection level with Baumgarte stabilisation (κ = 10/s).
    """
    scene = VerticalRollingDisk(eps=0.2, nu=0.5)
    spec = scene.spec()
    q0, qd0 = scene.configuration()
    kw: dict[str, Any] = {
        "n_paths": 64,
        "t1": 10.0,
        "dt": 0.01,
        "save": nhsde.Save(names=("constraint_residual",), n=11),
    }
    report = {}
    for label, route, rate in (
        ("reduced", "reduced", 0.0),
        ("multipliers κ=0", "multipliers", 0.0),
        ("multipliers κ=10", "multipliers", 10.0),
    ):
        form = mech.formulate(spec, route, dependent=("x", "y"), stabilization=rate)
        ens = nhsde.simulate(form.system(), form.state(q0, qd0), jax.random.key(4), **kw)
        report[label] = np.asarray(ens.mean[:, 0])
        print(
            f"mean over paths of |A q̇ + A0| ({label}) at t = 0, 1, …, 10: "
            f"{np.array2string(report[label], formatter={'float_kind': lambda x: f'{x:.1e}'})}"
        )
    assert np.max(report["reduced"]) < 1e-14
    grow, held = report["multipliers κ=0"], report["multipliers κ=10"]
    assert grow[-1] > 2 * grow[1]  # unstabilised: grows (√10 ≈ 3.2 from t = 1 to 10 for a random walk)
    assert np.max(held[6:]) < 1.5 * np.max(held[1:6])  # stabilised: bounded
    assert held[-1] < grow[-1] / 3
