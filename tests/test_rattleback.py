"""Kane & Levinson's rattleback: steady spins, their linear stability in both senses (S4 Remark 4.4),
the growth rate against nonlinear simulations, and the spin reversal.

Checks against theory: the small-oscillation frequencies at ``n = 0`` in closed
form, the reversibility ``μ(−n) = −μ(n)``, the mirror image ``D → −D``, the
same body written in Kane & Levinson's axes, the kernel of the linearisation
(the family and the first integrals), the growth rate ``Re μ`` measured on
the nonlinear flow, and conservation of energy and ``γ²`` through a reversal.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde.bodies as B
from nhsde.analysis import integral_drift, jacobian, linear_stability, solve_flow
from nhsde.scenes import Rattleback, RollingBody

KL = {"a": 0.2, "b": 0.03, "c": 0.02, "h": 0.01, "m": 1.0, "A": 2e-4, "B": 1.6e-3, "C": 1.7e-3, "D": -2e-5, "g": 9.81}

# Growth rates max Re μ (1/s) of the steady spin, counter-clockwise (n > 0) and clockwise (n < 0) seen
# from above; the table of the module docstring.
TABLE = {1.0: (0.4260, 0.04234), 2.0: (0.8515, 0.08421), 5.0: (2.1207, 0.2025), 10.0: (4.1931, 0.3568)}


def stability(scene, n):
    return linear_stability(scene.vector_field, scene.spin(n), scene.params, n_family=2)


@pytest.fixture(scope="module")
def scene():
    return Rattleback()


def test_kane_levinson_body_in_library_axes(scene):
    body = scene.params.body
    i12 = -KL["D"]  # b₂ = −e₂: the product changes sign in the library's axes (e₃ up)
    expected = np.array([[KL["A"], i12, 0.0], [i12, KL["B"], 0.0], [0.0, 0.0, KL["C"]]])
    np.testing.assert_array_equal(np.asarray(body.inertia), expected)
    # centre of mass h below the centre: the contact point at rest lies c − h below it
    r = np.asarray(body.surface.contact_point(jnp.array([0.0, 0.0, 1.0])))
    np.testing.assert_allclose(r, [0.0, 0.0, -(KL["c"] - KL["h"])], atol=1e-15)
    # E = ½(ω, Ĩω) + U has ∂E/∂D = −ω₁ω₂ (I₁₂ = −D); autodiff through the constructor reaches D
    y = jnp.array([0.3, -0.7, 2.0, 0.1, 0.2, 0.97])
    grad = jax.grad(lambda d: Rattleback(product=d).energy(y))(jnp.asarray(KL["D"]))
    np.testing.assert_allclose(float(grad), -0.3 * -0.7, rtol=1e-12)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="height=0.03.*c = 0.02"):
        Rattleback(height=0.03)
    with pytest.raises(ValueError, match="inertia has shape"):
        Rattleback(inertia=np.eye(3))


def test_steady_spin_and_the_two_zero_roots(scene):
    """``ω = nγ, γ = e₃`` is steady; the family (``n``, ``|γ|``) spans the kernel and ``E``, ``γ²`` the left kernel."""
    for n in (-10.0, -1.0, 0.5, 5.0):
        y = scene.spin(n)
        assert float(jnp.max(jnp.abs(scene.vector_field(0.0, y, scene.params)))) == 0.0
        jac = np.asarray(jacobian(scene.vector_field, y, scene.params))
        scale = np.linalg.norm(jac, 2)
        along_family = np.array([[0, 0, 1, 0, 0, 0], [0, 0, 0, 0, 0, 1]], float)  # ∂/∂n, ∂/∂|γ|
        assert np.max(np.abs(jac @ along_family.T)) <= 1e-12 * scale
        for integral in (scene.energy, lambda z: z[3:] @ z[3:]):
            grad = np.asarray(jax.grad(integral)(y))
            assert np.linalg.norm(grad @ jac) <= 1e-12 * scale * np.linalg.norm(grad)
        eig = np.sort(np.abs(np.linalg.eigvals(jac)))
        assert eig[1] <= 1e-10 * scale and eig[2] > 30.0  # two zero roots, four oscillation roots


def test_rest_frequencies_closed_form(scene):
    """At ``n = 0``: ``±iω`` with ``det(K − ω²M) = 0``, ``M`` the inertia about the contact point in the
    tilt plane, ``K = mg·diag(b²/c − ℓ, a²/c − ℓ)`` (radii of curvature minus the height ``ℓ = c − h``)."""
    p = KL
    ell = p["c"] - p["h"]
    mass = np.array([[p["A"] + p["m"] * ell**2, -p["D"]], [-p["D"], p["B"] + p["m"] * ell**2]])
    stiff = p["m"] * p["g"] * np.diag([p["b"] ** 2 / p["c"] - ell, p["a"] ** 2 / p["c"] - ell])
    omega = np.sort(np.sqrt(np.linalg.eigvals(np.linalg.solve(mass, stiff)).real))
    st = stability(scene, 0.0)
    assert st.verdict == "neutral"
    np.testing.assert_allclose(np.sort(np.asarray(st.roots.imag))[2:], omega, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(st.roots.real), 0.0, atol=1e-9)


def test_growth_rates_both_senses(scene):
    """Both senses unstable (the conservative rattleback reverses either way); counter-clockwise through the
    pitch (≈ 107 rad/s), ten times faster than clockwise through the roll (≈ 34 rad/s).  Reversibility
    ``(ω, γ, t) → (−ω, γ, −t)`` makes the roots at ``−n`` minus those at ``n`` (S4 Remark 4.4)."""
    for n, (ccw_rate, cw_rate) in TABLE.items():
        ccw, cw = stability(scene, n), stability(scene, -n)
        assert ccw.verdict == cw.verdict == "unstable"
        np.testing.assert_allclose([float(ccw.growth_rate), float(cw.growth_rate)], [ccw_rate, cw_rate], rtol=2e-4)
        assert abs(ccw.roots[0].imag) > 100.0 and abs(cw.roots[0].imag) < 40.0
        np.testing.assert_allclose(
            np.sort_complex(np.asarray(cw.roots)), np.sort_complex(-np.asarray(ccw.roots)), rtol=1e-10
        )
        # sum of the roots = −a₁/a₀ (S4 Remark 4.3): a₁ < 0 counter-clockwise (unstable whatever the other
        # coefficients), a₁ > 0 clockwise (necessary for stability, not sufficient)
        assert float(jnp.sum(ccw.roots.real)) > 0 > float(jnp.sum(cw.roots.real))


def test_mirror_image_and_kane_levinson_axes(scene):
    """The mirror image (``D → −D``) spun the other way has the same roots; the same body written in
    Kane & Levinson's axes (``b₃`` down: ``γ = −b₃``, centre of mass at ``+h b₃``, inertia entry ``+D``)
    spun with ``ω₃ = −n`` too."""
    p = KL
    mirror = Rattleback(product=-p["D"])
    inertia = [[p["A"], p["D"], 0.0], [p["D"], p["B"], 0.0], [0.0, 0.0, p["C"]]]
    surface = B.Ellipsoid(semi_axes=(p["a"], p["b"], p["c"]), offset=(0.0, 0.0, p["h"]))
    kl_axes = RollingBody(
        body=B.RigidBody(mass=p["m"], inertia=inertia, surface=surface), contact="classic", gravity=p["g"]
    )
    for n in (2.0, -5.0):
        roots = np.sort_complex(np.asarray(stability(scene, n).roots))
        np.testing.assert_allclose(np.sort_complex(np.asarray(stability(mirror, -n).roots)), roots, rtol=1e-10)
        kl = linear_stability(
            kl_axes.vector_field, jnp.array([0.0, 0.0, -n, 0.0, 0.0, -1.0]), kl_axes.params, n_family=2
        )
        np.testing.assert_allclose(np.sort_complex(np.asarray(kl.roots)), roots, rtol=1e-10)


def test_remark_4_4_stable_one_way():
    """A rounder, stiffer-rolling variant spun fast: asymptotically stable clockwise, unstable counter-clockwise
    with the opposite roots (S4 Remark 4.4)."""
    variant = Rattleback(inertia=(8e-4, 1.6e-3, 1.7e-3), semi_axes=(0.2, 0.03, 0.025), height=0.005)
    cw, ccw = stability(variant, -50.0), stability(variant, 50.0)
    assert cw.verdict == "asymptotically stable" and ccw.verdict == "unstable"
    np.testing.assert_allclose(float(cw.roots[0].real), -0.10632, rtol=1e-4)
    np.testing.assert_allclose(float(ccw.growth_rate), 6.4114, rtol=1e-4)


def envelope_rate(ts, amplitude, window):
    """Slope of ``log`` of the local maxima of ``amplitude`` (parabola-refined) over ``window = (t₀, t₁)``."""
    la = np.log(amplitude)
    i = np.where((la[1:-1] > la[:-2]) & (la[1:-1] >= la[2:]))[0] + 1
    shift = 0.5 * (la[i - 1] - la[i + 1]) / (la[i - 1] - 2 * la[i] + la[i + 1])
    t_peak = ts[i] + shift * (ts[1] - ts[0])
    log_peak = la[i] - 0.25 * (la[i - 1] - la[i + 1]) * shift
    keep = (t_peak > window[0]) & (t_peak < window[1])
    assert keep.sum() > 100
    return np.polyfit(t_peak[keep], log_peak[keep], 1)[0]


@pytest.mark.parametrize("n, t1", [(5.0, 6.0), (-5.0, 60.0)], ids=["counter-clockwise", "clockwise"])
def test_growth_rate_from_nonlinear_flow(scene, n, t1):
    """From a tilt of 1e-8 rad the tilt ``|γ × e₃|`` grows as ``e^{Re μ t}``: the log of its peaks over
    ``[0.4, 0.95]·t₁`` (other mode down by ≥ e^{-5}, amplitude ≤ 5e-3) has slope ``Re μ``."""
    rate = float(stability(scene, n).growth_rate)
    flow = solve_flow(
        scene.vector_field, scene.spin(n, 1e-8, 0.7)[None], scene.params, t1=t1, n_save=6001, rtol=1e-12, atol=1e-14
    )
    ys = np.asarray(flow.ys[0])
    tilt = np.hypot(ys[:, 3], ys[:, 4])
    assert tilt[-1] < 1e-2  # still linear
    measured = envelope_rate(np.asarray(flow.ts), tilt, (0.4 * t1, 0.95 * t1))
    assert abs(measured / rate - 1) < 1e-3, (measured, rate)


def vertical_spin(ys):
    """``(ω, γ)/|γ|``: the spin about the vertical, positive counter-clockwise seen from above."""
    return np.sum(ys[..., :3] * ys[..., 3:6], axis=-1) / np.linalg.norm(ys[..., 3:6], axis=-1)


def drifts(scene, flow):
    d = integral_drift({"E": lambda y, p: scene.energy(y), "g2": lambda y, p: y[3:6] @ y[3:6]}, flow, scene.params)
    return float(d["E"][0]) / float(scene.energy(flow.ys[0, 0])), float(d["g2"][0])


def test_spin_reversal(scene):
    """Spun counter-clockwise at 5 rad/s with the long axis tipped by 1e-3 rad, the rattleback pitches, stops
    (t ≈ 3.7 s) and spins clockwise at 5 rad/s; energy kept to 1e-9 (relative) and ``γ²`` to 1e-10."""
    flow = solve_flow(scene.vector_field, scene.spin(5.0, 1e-3)[None], scene.params, t1=8.0, n_save=801)
    ts, spin = np.asarray(flow.ts), vertical_spin(np.asarray(flow.ys[0]))
    crossings = ts[1:][np.diff(np.sign(spin)) != 0]
    assert spin[0] == pytest.approx(5.0) and np.all(spin[ts > 7.0] < -4.9)
    assert len(crossings) == 1 and 3.0 < crossings[0] < 4.5, crossings
    energy, gamma2 = drifts(scene, flow)
    assert energy < 1e-9 and gamma2 < 1e-10, (energy, gamma2)


@pytest.mark.slow
def test_repeated_reversals(scene):
    """Without dissipation the clockwise spin is unstable too (slowly): it reverses back (t ≈ 30 s) and again
    (t ≈ 51 s); energy kept to 1e-10 (relative) and ``γ²`` to 1e-11."""
    flow = solve_flow(
        scene.vector_field, scene.spin(5.0, 1e-3)[None], scene.params, t1=60.0, n_save=6001, rtol=1e-12, atol=1e-13
    )
    ts, spin = np.asarray(flow.ts), vertical_spin(np.asarray(flow.ys[0]))
    crossings = ts[1:][np.diff(np.sign(spin)) != 0]
    assert len(crossings) == 3 and crossings[0] < 4.5 and 25.0 < crossings[1] < 35.0 < crossings[2], crossings
    energy, gamma2 = drifts(scene, flow)
    assert energy < 1e-10 and gamma2 < 1e-11, (energy, gamma2)


@pytest.mark.slow
def test_asymptotic_stability_nonlinear():
    """S4 Theorem 4.1 on the flow: spun clockwise at 50 rad/s from a tilt of 1e-4, the variant's tilt decays
    at the rate ``Re μ`` of its slowest root and the spin settles on the steady spin of the same energy,
    ``n∞ = −√(2(E₀ − U(e₃))/C)`` (the family is parametrised by the first integrals)."""
    variant = Rattleback(inertia=(8e-4, 1.6e-3, 1.7e-3), semi_axes=(0.2, 0.03, 0.025), height=0.005)
    rate = float(stability(variant, -50.0).roots[0].real)
    y0 = variant.spin(-50.0, 1e-4, 0.7)
    flow = solve_flow(variant.vector_field, y0[None], variant.params, t1=60.0, n_save=20001, rtol=1e-11, atol=1e-13)
    ys = np.asarray(flow.ys[0])
    measured = envelope_rate(np.asarray(flow.ts), np.hypot(ys[:, 3], ys[:, 4]), (20.0, 59.0))
    assert abs(measured / rate - 1) < 1e-4, (measured, rate)
    potential = float(variant.energy(variant.spin(0.0)))
    n_final = -np.sqrt(2 * (float(variant.energy(y0)) - potential) / 1.7e-3)
    assert n_final + 50.0 < -2e-4  # the decayed wobble's energy went into the spin
    assert abs(vertical_spin(ys)[-1] - n_final) < 1e-8, (vertical_spin(ys)[-1], n_final)
