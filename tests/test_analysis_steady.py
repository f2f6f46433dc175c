"""Steady motions of Chaplygin systems and their stability (S4 §4), against closed forms.

Closed forms used (derived here, not taken from the library):

* Chaplygin sleigh (mass m, central inertia I, centre of mass a ahead of the knife,
  J = I + m a²): with v the speed along the knife and ω = θ̇, J ω̇ = −m a v ω and
  m v̇ = m a ω².  Straight motion v = V, ω = 0 linearises to ω̇ = −(m a V/J) ω: the
  transverse root is μ = −m a V/J (stable forward, V > 0; unstable backward —
  S4 Remark 4.4); the Routh pencil (4.19) in r = θ is A0 = J, D0 = m a V, C0 = 0.
  With a torsion spring κ on the heading, J μ² + m a V μ + κ = 0: a complex pair
  crosses the imaginary axis at V = 0 with μ = ±i√(κ/J) (an Andronov–Hopf point,
  S4 Remark 4.6).
* Upright rolling of a symmetric disk (axial inertia C, diametral A, radius R):
  linearising about θ = 0, ψ̇ = 0, φ̇ = Ω, the heading obeys A ψ̈ = ∓C Ω θ̇, so
  ψ̇ = ∓(CΩ/A) θ on the family (the m = 2 zero roots are ψ̇ and φ̇ shifts), and
  the tilt (about the contact point) (A + mR²) θ̈ = m g R θ ± (C + mR²) Ω ψ̇.  Hence
  (A + mR²) μ² = m g R − (C + mR²) C Ω²/A: μ = ±i·(…) (neutral, not asymptotic: no
  D0) iff Ω² > m g R A / (C (C + mR²)); thin disk (C = mR²/2, A = mR²/4):
  Ω² > g/(3R); hoop (C = mR², A = mR²/2): Ω² > g/(4R).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nhsde import parameter
from nhsde.analysis import (
    chaplygin_system,
    delta_matrix,
    linear_stability,
    stability_boundary,
    steady_motions,
    steady_stability,
)
from nhsde.mechanics import MechanicalSpec
from nhsde.scenes import ChaplyginSleighFromSpec, RollingDisk, SleighParameters, rolling_disk_kinematics

M, I, A_OFF = 2.0, 0.7, 0.4
J = I + M * A_OFF**2


class SpringSleighParameters(SleighParameters):
    stiffness: jnp.ndarray = parameter(default=0.0, lower=0.0, doc="torsion spring κ on the heading")


def _heading_spring(q, pi, t, p):
    return 0.5 * p.stiffness * q[2] ** 2


def _sleigh(stiffness):
    """ChaplyginSleighFromSpec's Lagrangian (ε = ν = 0) plus a heading spring ½κθ² (none at κ = 0)."""
    base = ChaplyginSleighFromSpec(eps=0.0, nu=0.0).spec()
    params = SpringSleighParameters(eps=0.0, nu=0.0, mass=M, inertia=I, offset=A_OFF, stiffness=stiffness)
    spec = MechanicalSpec(
        coordinates=base.coordinates,
        params=params,
        kinetic_energy=base.kinetic_energy,
        constraints=base.constraints,
        potential=_heading_spring,
    )
    return chaplygin_system(spec, ("y",), jnp.zeros(3))


@pytest.fixture(scope="module")
def sleigh():
    return _sleigh(0.0)


def _disk(mass=1.3, radius=0.7, axial=None, diametral=None):
    axial = 0.5 * mass * radius**2 if axial is None else axial
    diametral = 0.25 * mass * radius**2 if diametral is None else diametral
    scene = RollingDisk(mass=mass, radius=radius, axial_inertia=axial, diametral_inertia=diametral, gravity=9.81)
    return scene, chaplygin_system(scene.spec(), scene.dependent, jnp.zeros(5))


@pytest.fixture(scope="module")
def disk():
    return _disk()


def _upright(system, rate):
    return steady_motions(system, {"psi_dot": 0.0, "phi_dot": rate}, {"theta": 0.0})


def _threshold(p):
    m, r, c, a, g = (float(x) for x in (p.mass, p.radius, p.axial_inertia, p.diametral_inertia, p.gravity))
    return np.sqrt(m * g * r * a / (c * (c + m * r**2))), (m, r, c, a, g)


# ------------------------------------------------------------------ sleigh: Remark 4.4


def test_sleigh_coordinates_and_family(sleigh):
    """θ positional, x pseudo-cyclic (S4 (4.7)); straight motion at any heading: a 2-parameter family."""
    assert [sleigh.spec.coordinates[i] for i in sleigh.positional] == ["theta"]
    assert [sleigh.spec.coordinates[i] for i in sleigh.pseudo_cyclic] == ["x"]
    motions = steady_motions(sleigh, {"x_dot": np.array([1.5, -1.5, 0.8])}, {"theta": 0.3})
    np.testing.assert_allclose(motions.positions[:, 0], 0.3, atol=1e-14)  # any heading solves (4.9)
    assert motions.family_dimension == (2, 2, 2)
    assert float(jnp.max(motions.residual)) < 1e-14


@pytest.mark.parametrize("speed", [1.5, -1.5])
@pytest.mark.parametrize("heading", [0.0, 0.3])
def test_sleigh_direction_decides_stability(sleigh, speed, heading):
    """Forward (centre of mass ahead, V > 0) asymptotically stable, backward unstable; μ = −m a V/J."""
    motions = steady_motions(sleigh, {"x_dot": speed}, {"theta": heading})
    result = steady_stability(sleigh, motions)
    v = speed / np.cos(heading)  # speed along the knife
    expected = -M * A_OFF * v / J
    assert result.verdict == ("asymptotically stable" if speed > 0 else "unstable")
    assert result.drift.verdict == result.verdict
    np.testing.assert_allclose(np.asarray(result.roots), [expected], rtol=1e-12)
    np.testing.assert_allclose(float(result.routh.growth_rate), expected, rtol=1e-12)
    # the Routh pencil (4.19): A0 = J (θ̇ = ω), D0 = m a V odd in the speed (Remark 4.4), C0 = 0
    np.testing.assert_allclose(np.asarray(result.A0), [[J]], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(result.D0), [[M * A_OFF * v]], rtol=1e-12)
    assert abs(float(result.C0[0, 0])) < 1e-12
    # the independent route: Jacobian of the library's reduced drift (two family zeros)
    drift_roots = np.asarray(result.drift.roots)
    np.testing.assert_allclose(drift_roots, [expected], rtol=1e-10)
    assert np.max(np.abs(np.asarray(result.drift.family_roots))) < 1e-12


def _d0_s4(system, r0, s0):
    """S4 (4.21): d⁰_ij = ½(d_ijα + d_jiα) ṡ_α, d_ijα = ω_αij + θ^βγ(θ_γi ω_βαj + θ_βj ω_iγα), written out."""
    p, ind = system.spec.params, system.form.elimination.independent
    rs = [ind.index(i) for i in system.positional]
    ss = [ind.index(i) for i in system.pseudo_cyclic]
    x = system.reference[np.asarray(ind)].at[np.asarray(rs)].set(r0)
    om, th = (np.asarray(a) for a in eqx.filter_jit(lambda x: (system.omega(x, p), system.theta(x, p)))(x))
    inv, t_sr = np.linalg.inv(th[np.ix_(ss, ss)]), th[np.ix_(ss, rs)]
    k, m = len(rs), len(ss)
    d = np.zeros((k, k, m))
    for i, j, a in np.ndindex(k, k, m):
        d[i, j, a] = om[ss[a], rs[i], rs[j]] + sum(
            inv[b, g] * (t_sr[g, i] * om[ss[b], ss[a], rs[j]] + t_sr[b, j] * om[rs[i], ss[g], ss[a]])
            for b, g in np.ndindex(m, m)
        )
    return 0.5 * np.einsum("ija,a->ij", d + d.transpose(1, 0, 2), np.asarray(s0))


def test_d0_matches_the_explicit_formula(sleigh):
    """The symmetric part of the Routh pencil's μ-coefficient equals S4 (4.21), odd in ṡ0 (Remark 4.4)."""
    for speed in (1.5, -1.5):
        motions = steady_motions(sleigh, {"x_dot": speed}, {"theta": 0.3})
        result = steady_stability(sleigh, motions, drift=False)
        np.testing.assert_allclose(np.asarray(result.D0), _d0_s4(sleigh, *motions[0]), rtol=1e-12)
        np.testing.assert_allclose(float(result.D0[0, 0]), M * A_OFF * speed / np.cos(0.3), rtol=1e-12)


@pytest.mark.slow
def test_routh_pencil_gradients_reach_the_parameters(sleigh):
    """∂A0/∂a = 2 m a and ∂D0/∂a = m V, ∂D0/∂m = a V (A0 = I + m a², D0 = m a V): params are leaves."""
    speed = 1.5
    r0, s0 = steady_motions(sleigh, {"x_dot": speed})[0]
    grads = eqx.filter_jit(jax.jacrev(lambda p: sleigh.routh(r0, s0, p)[:2]))(sleigh.spec.params)
    (da0, dd0) = grads
    np.testing.assert_allclose(float(da0.offset[0, 0]), 2 * M * A_OFF, rtol=1e-12)
    np.testing.assert_allclose(float(dd0.offset[0, 0]), M * speed, rtol=1e-12)
    np.testing.assert_allclose(float(dd0.mass[0, 0]), A_OFF * speed, rtol=1e-12)


# ------------------------------------------------------------------ upright rolling disk


def test_rolling_disk_kinematics_from_lagrangian(disk):
    """Velocities on the constraints leave the material contact point at rest; the spec is Chaplygin."""
    scene, system = disk
    spec, p = scene.spec(), scene.params
    rng = np.random.default_rng(1)
    for _ in range(3):
        q = jnp.asarray(rng.uniform(-1, 1, 5))
        angles = jnp.asarray(rng.normal(size=3))
        r = float(p.radius)
        v = jnp.concatenate([r * angles[2] * jnp.stack([jnp.cos(q[2]), jnp.sin(q[2])]), angles])
        assert float(jnp.max(jnp.abs(spec.constraint_residual(q, v, jnp.zeros(0), 0.0, p)))) < 1e-14
        g_dot, omega, _ = rolling_disk_kinematics(q, v, p)
        centre_to_contact = -r * jnp.stack(
            [jnp.sin(q[3]) * jnp.sin(q[2]), -jnp.sin(q[3]) * jnp.cos(q[2]), jnp.cos(q[3])]
        )
        np.testing.assert_allclose(np.asarray(g_dot + jnp.cross(omega, centre_to_contact)), 0.0, atol=1e-14)
    assert [spec.coordinates[i] for i in system.positional] == ["theta"]
    assert [spec.coordinates[i] for i in system.pseudo_cyclic] == ["psi", "phi"]


@pytest.mark.slow
def test_rolling_disk_scene_friction_and_noise():
    """R = 2εT: the drift dissipates energy at dE/dt = −4εT; the three random torques enter the velocities."""
    scene = RollingDisk(eps=0.2, nu=0.3, spin=2.0)
    form, system = scene.form(), scene.build()
    y0 = scene.initial_state()
    p = scene.params
    energy = lambda y: form.spec.energy(*form.velocities(0.0, y, p)[:2], jnp.zeros(0), 0.0, p)
    rate = jax.jit(lambda y: jax.jvp(energy, (y,), (system.drift_fn(0.0, y, p),))[1])(y0)
    q, v, _ = form.velocities(0.0, y0, p)
    kinetic = float(form.spec.kinetic(q, v, jnp.zeros(0), 0.0, p))
    np.testing.assert_allclose(float(rate), -4 * 0.2 * kinetic, rtol=1e-12)
    noise = np.asarray(system.diffusion_fn(0.0, y0, p))
    assert noise.shape == (len(y0), 3) and np.linalg.matrix_rank(noise) == 3


@pytest.mark.slow
@pytest.mark.parametrize("factor", [0.5, 2.0])
def test_upright_disk_roots_match_closed_form(disk, factor):
    """Roots of (4.19) = closed form = eigenvalues of the reduced drift (relative 1e-10); verdicts honest."""
    scene, system = disk
    critical, (m, r, c, a, g) = _threshold(scene.params)
    rate = factor * critical
    result = steady_stability(system, _upright(system, rate))
    mu2 = (m * g * r - (c + m * r**2) * c * rate**2 / a) / (a + m * r**2)
    expected = np.sqrt(complex(mu2)) * np.array([1, -1])
    routh = np.asarray(result.roots)
    drift = np.asarray(result.drift.roots)
    key = lambda z: (round(z.real, 6), round(z.imag, 6))
    for roots in (routh, drift):
        np.testing.assert_allclose(sorted(roots, key=key), sorted(expected, key=key), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(result.A0), [[a + m * r**2]], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(result.D0), 0.0, atol=1e-12)  # no D0: at best neutral (Remark 4.3)
    # det Δ(μ) (4.22)–(4.23) vanishes at the drift's roots, relative to Hadamard's bound Π|rows|
    for mu in drift:
        delta = np.asarray(delta_matrix(mu, *result.linearisation, system.k))
        assert abs(np.linalg.det(delta)) < 1e-12 * np.prod(np.linalg.norm(delta, axis=1))
    assert result.verdict == ("unstable" if factor < 1 else "neutral")
    assert result.drift.verdict == result.verdict


@pytest.mark.slow
def test_tilted_circular_rolling(disk):
    """Tilted steady motions (ψ̇ ≠ 0) from S4 (4.9) are fixed points of the library's reduced drift,
    and the roots of (4.19) equal the drift's eigenvalues there (relative 1e-10)."""
    _, system = disk
    motions = steady_motions(system, {"psi_dot": np.array([0.5, 1.0, -1.0]), "phi_dot": 4.0}, {"theta": 0.0})
    tilt = np.asarray(motions.positions[:, 0])
    # leaning into the turn (θ < 0 leans towards ℓ = ẑ × e, the left, for a left turn ψ̇ > 0); mirror symmetry
    assert np.all(np.sign(tilt) == [-1, -1, 1]) and np.all(np.abs(tilt) > 0.1)
    np.testing.assert_allclose(tilt[1], -tilt[2], rtol=1e-12)
    for i in range(3):
        result = steady_stability(system, motions, i)
        assert float(result.drift.residual) < 1e-12  # |reduced drift| at the steady motion (rates ~ 1–5)
        key = lambda z: (round(z.real, 6), round(z.imag, 6))
        np.testing.assert_allclose(
            sorted(np.asarray(result.drift.roots), key=key), sorted(np.asarray(result.roots), key=key), rtol=1e-10
        )


def test_disk_threshold_located_by_scanning(disk):
    """The verdict changes at Ω² = g/(3R) for a thin disk (relative 1e-8): a real pair through zero."""
    scene, system = disk
    critical, _ = _threshold(scene.params)
    np.testing.assert_allclose(critical**2, 9.81 / (3 * 0.7), rtol=1e-14)
    _, (m, r, c, a, g) = _threshold(scene.params)
    rates = np.linspace(0.5, 2.0, 6) * critical
    results = [steady_stability(system, _upright(system, w), drift=False) for w in rates]
    assert [s.verdict for s in results] == ["unstable"] * 2 + ["neutral"] * 4
    for rate, result in zip(rates, results):  # (A + mR²) μ² = m g R − (C + mR²) C Ω²/A
        mu2 = (m * g * r - (c + m * r**2) * c * rate**2 / a) / (a + m * r**2)
        np.testing.assert_allclose(np.sort_complex(np.asarray(result.roots) ** 2), mu2, rtol=1e-10)
    boundary = stability_boundary(
        system, {"psi_dot": 0.0, "phi_dot": rates[1]}, {"psi_dot": 0.0, "phi_dot": rates[2]}, {"theta": 0.0}
    )
    assert boundary.verdicts == ("unstable", "neutral")
    assert boundary.kind == "real root through zero"
    assert abs(boundary.parameter["phi_dot"] / critical - 1) < 1e-8


@pytest.mark.parametrize("shape", ["hoop", "general"])
def test_threshold_hoop_and_general_inertia(shape):
    """Hoop: Ω² = g/(4R); any C, A: Ω² = m g R A/(C(C + mR²)) (relative 1e-8)."""
    m, r = 0.9, 0.45
    axial, diametral = (m * r**2, 0.5 * m * r**2) if shape == "hoop" else (0.11, 0.07)
    scene, system = _disk(m, r, axial, diametral)
    critical, _ = _threshold(scene.params)
    if shape == "hoop":
        np.testing.assert_allclose(critical**2, 9.81 / (4 * r), rtol=1e-14)
    boundary = stability_boundary(
        system, {"psi_dot": 0.0, "phi_dot": 0.5 * critical}, {"psi_dot": 0.0, "phi_dot": 2 * critical}, {"theta": 0.0}
    )
    assert abs(boundary.parameter["phi_dot"] / critical - 1) < 1e-8


# ------------------------------------------------------------------ Andronov–Hopf (Remark 4.6)


def test_hopf_point_of_the_spring_sleigh():
    """J μ² + m a V μ + κ = 0: a complex pair crosses Re μ = 0 at V = 0 with μ = ±i√(κ/J)."""
    system = _sleigh(3.0)
    kappa = float(system.spec.params.stiffness)
    for speed in (0.7, -0.7):
        result = steady_stability(system, steady_motions(system, {"x_dot": speed}))
        expected = np.roots([J, M * A_OFF * speed, kappa])
        np.testing.assert_allclose(np.sort_complex(np.asarray(result.roots)), np.sort_complex(expected), rtol=1e-12)
        np.testing.assert_allclose(
            np.sort_complex(np.asarray(result.drift.roots)), np.sort_complex(expected), rtol=1e-10
        )
    boundary = stability_boundary(system, {"x_dot": -0.5}, {"x_dot": 1.0})
    assert boundary.verdicts == ("unstable", "asymptotically stable")
    assert boundary.kind == "Andronov–Hopf"
    assert abs(boundary.parameter["x_dot"]) < 1e-12
    np.testing.assert_allclose(
        np.sort(np.abs(np.asarray(boundary.critical_roots).imag)), np.sqrt(kappa / J), rtol=1e-10
    )


# ------------------------------------------------------------------ the generic linear test


def test_linear_stability_on_a_damped_oscillator():
    """ẍ = −k x − c ẋ plus a conserved z: roots (−c ± √(c² − 4k))/2, the family root 0."""

    def field(t, y, p):
        return jnp.stack([y[1], -p[0] * y[0] - p[1] * y[1], jnp.zeros((), y.dtype)])

    for c, verdict in ((0.3, "asymptotically stable"), (-0.3, "unstable"), (0.0, "neutral")):
        params = jnp.array([2.0, c])
        result = linear_stability(field, jnp.zeros(3), params, n_family=1)
        assert result.verdict == verdict
        np.testing.assert_allclose(
            np.sort_complex(np.asarray(result.roots)), np.sort_complex(np.roots([1, c, 2.0])), rtol=1e-14
        )
    with pytest.raises(ValueError, match=r"not a steady state.*\|f\(state\)\| = 2\.508e\+00"):
        linear_stability(field, jnp.ones(3), jnp.array([2.0, 0.3]), n_family=1)
    with pytest.raises(ValueError, match=r"the 2 smallest eigenvalues .* are not ≈ 0"):
        linear_stability(field, jnp.zeros(3), jnp.array([2.0, 0.3]), n_family=2)
    # float32 rounding (1e-7) is above the tolerances that tell zero, neutral and growing roots apart
    with pytest.raises(ValueError, match=r"state has dtype float32; stability analysis needs float64"):
        linear_stability(field, jnp.zeros(3, jnp.float32), jnp.array([2.0, 0.3], jnp.float32), n_family=1)


# ------------------------------------------------------------------ bad input


class ParticleParameters(SleighParameters):
    slope: jnp.ndarray = parameter(default=0.2, doc="sine of the incline along y")


def test_non_chaplygin_specs_are_refused():
    """M depending on y (ż = z ẋ), or V depending on y (an incline along y): clear errors."""
    params = ParticleParameters(eps=0.0, nu=0.0)
    particle = MechanicalSpec(
        coordinates=("x", "y", "z"),
        params=params,
        kinetic_energy=lambda q, v, pi, t, p: 0.5 * v @ v,
        constraints=lambda q, pi, t, p: jnp.stack([-q[2], jnp.zeros((), q.dtype), jnp.ones((), q.dtype)])[None],
    )
    with pytest.raises(
        ValueError,
        match=r"not a Chaplygin system: the constraint matrix M .* depends on the dependent coordinate\(s\) \('z',\)",
    ):
        chaplygin_system(particle, ("z",), jnp.ones(3))
    base = ChaplyginSleighFromSpec(eps=0.0, nu=0.0).spec()
    incline = MechanicalSpec(
        coordinates=base.coordinates,
        params=params,
        kinetic_energy=base.kinetic_energy,
        constraints=base.constraints,
        potential=lambda q, pi, t, p: p.mass * 9.81 * p.slope * (q[1] + p.offset * jnp.sin(q[2])),
    )
    with pytest.raises(ValueError, match=r"not a Chaplygin system: the potential V depends on .* \('y',\)"):
        chaplygin_system(incline, ("y",), jnp.zeros(3))
    with pytest.raises(ValueError, match=r"S4 treats conservative systems"):
        chaplygin_system(ChaplyginSleighFromSpec(eps=0.1, nu=0.0).spec(), ("y",), jnp.zeros(3))


def test_family_parameter_outside_the_domain(disk):
    """A tilted disk cannot roll straight: θ = 0.3, ψ̇ = 0 has no steady motion; wrong names are named."""
    _, system = disk
    with pytest.raises(
        ValueError, match=r"no steady motion with theta=0\.3, psi_dot=0: .* outside the family's domain"
    ):
        steady_motions(system, {"theta": 0.3, "psi_dot": 0.0}, {"phi_dot": 1.0})
    with pytest.raises(ValueError, match=r"family fixes \['phi_dot'\]; give exactly m = 2"):
        steady_motions(system, {"phi_dot": 1.0})
    with pytest.raises(ValueError, match=r"family names \['omega'\]; allowed: \('theta', 'psi_dot', 'phi_dot'\)"):
        steady_motions(system, {"omega": 1.0, "psi_dot": 0.0})
    with pytest.raises(ValueError, match=r"the verdict is 'neutral' at both"):
        stability_boundary(system, {"psi_dot": 0.0, "phi_dot": 5.0}, {"psi_dot": 0.0, "phi_dot": 6.0}, {"theta": 0.0})
