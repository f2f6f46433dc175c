"""A rolling contact at finite temperature (THEORY.md §8; Jagla, Bloch & Rojo, arXiv 2603.14424).

The vertical rolling disk in a bath of temperature ``kT`` (``VerticalRollingDiskInBath``), checked against statistical
mechanics, not against the code:

- soft (viscous) contact with fluctuation–dissipation noise: a Langevin system whose stationary law is Gibbs,
  ``exp(−T/kT)`` with ``T = ½ m (v² + w²) + ½ I θ̇² + ½ J φ̇²``: equipartition
  ``m⟨v²⟩ = m⟨w²⟩ = I⟨θ̇²⟩ = J⟨φ̇²⟩ = kT`` and ``⟨v⟩ = 0`` at ``γ = 1`` and ``γ = 100``;
- naive model (rolling without slipping, noise on the friction only): unlike the sleigh's, its constrained flow
  ``θ̈ = φ̈ = 0`` keeps the volume, so its stationary law is ``exp(−T_c/kT)``, ``T_c = ½ (I + mR²) θ̇² + ½ J φ̇²``
  (S0 Statement 1): Gibbs conditioned on no slip.  No forward drift, but no slip modes: ``I⟨θ̇²⟩ = kT I/(I + mR²)``;
- the Gibbs density: ``stationary_density`` proves it stationary from the equations (each dissipative channel
  balances ``exp(−T/kT)`` alone), and histograms of the energy and of ``θ̇`` at stationarity pass a chi-square test
  against it (and fail against the other model's law);
- ``∂⟨T⟩/∂kT = 2`` (four quadratic modes) from pathwise derivatives, which equal finite differences;
- the spec route's ``SoftConstraint`` and ``temperature`` give the scene's body-frame equations for the disk, and
  the spec route's soft sleigh, simulated, obeys equipartition (an independent check of that route).

Stationary averages are per path over its saved times, their standard error across paths.  At ``γ = 1`` the slowest
velocity relaxation rate is ``2ε = 1``/s (the rolling and turning modes; the slip modes are faster), so the values at
``t = 10, 20, 30`` are independent to ``e⁻¹⁰`` and serve the histograms as independent samples.
"""

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import nhsde
from nhsde import mechanics
from nhsde.scenes import ChaplyginSleighInBath, VerticalRollingDiskInBath
from nhsde.statistics import stationary_density

KEY = jax.random.key(20260314)
EPS, KT, MASS, RADIUS, ROLL, TURN = 0.5, 0.5, 1.0, 1.0, 0.5, 0.25
ROLLING = ROLL + MASS * RADIUS**2  # I + mR²
SOFT_MASSES = np.array([MASS, MASS, ROLL, TURN])  # T = ½ Σ M_i y_i² on (v, w, θ̇, φ̇)
N_PATHS = 4096
PARAMS: dict[str, Any] = dict(eps=EPS, kT=KT, mass=MASS, radius=RADIUS, roll_inertia=ROLL, turn_inertia=TURN)


def _mean_se(x):
    """Mean over paths of the per-path values ``x`` (``(n_paths,)``) and its standard error."""
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(x.size))


def _gibbs_velocities(n):
    """``(v, w, θ̇, φ̇) ~ N(0, kT M⁻¹)``: the soft disk's Gibbs law, whatever ``γ``."""
    z = np.asarray(jax.random.normal(jax.random.fold_in(KEY, 7), (n, 4)), np.float64)
    return jnp.asarray(z * np.sqrt(KT / SOFT_MASSES), jnp.float32)


@functools.cache
def _run(model, gamma):
    """Velocities ``(n_paths, 3, d)`` at the last three of four saved times (one program for both ``γ``).

    ``γ = 1``: from rolling straight ahead, ``t = 10, 20, 30`` at ``dt = 0.01``.  ``γ = 100``: the contact rate
    ``λ = γ (1/m + R²/I) = 300``/s needs ``λ dt ≤ 0.1`` for weak2's stationary law, so ``dt = 2.5·10⁻⁴`` from the
    Gibbs law, ``t = 0.25, 0.5, 0.75``.
    """
    scene = VerticalRollingDiskInBath(model=model, drift=False, gamma=gamma, **PARAMS)
    if gamma > 1:
        y0, t1, dt = _gibbs_velocities(N_PATHS), 0.75, 2.5e-4
    else:
        y0 = jnp.broadcast_to(jnp.asarray(scene.initial_state(), jnp.float32), (N_PATHS, scene.build().state_dim))
        t1, dt = 30.0, 0.01
    ens = nhsde.simulate(
        scene.build(), y0, KEY, n_paths=N_PATHS, t1=t1, dt=dt, solver="weak2", save=nhsde.Save(n=4, paths=True)
    )
    return np.asarray(ens.paths, np.float64)[:, 1:, :]


@pytest.mark.parametrize("gamma", [1.0, 100.0])
def test_soft_disk_is_gibbs_equipartition_and_no_forward_drift(gamma):
    """Gibbs law of the soft contact: ``T`` is diagonal in ``(v, w, θ̇, φ̇)``, so each mode holds ``kT/2`` whatever
    ``γ``, and ``⟨v⟩ = 0``.  (``I⟨θ̇²⟩/kT`` is 1 here, not the naive model's ``I/(I + mR²) = 1/3``: the slip
    along the heading is a thermal degree of freedom at every finite ``γ``.)"""
    y = _run("soft", gamma)
    for label, i in (("m<v²>/kT", 0), ("m<w²>/kT", 1), ("I<θ̇²>/kT", 2), ("J<φ̇²>/kT", 3)):
        mean, se = _mean_se((SOFT_MASSES[i] * y[..., i] ** 2 / KT).mean(axis=1))
        assert abs(mean - 1) <= 4 * se, (gamma, label, mean, se)
    for label, i in (("<v>", 0), ("<θ̇>", 2)):
        mean, se = _mean_se(y[..., i].mean(axis=1))
        assert abs(mean) <= 4 * se, (gamma, label, mean, se)


def test_naive_disk_is_gibbs_on_the_constraint_and_misses_the_slip_modes():
    """Naive model: ``(I + mR²)⟨θ̇²⟩ = J⟨φ̇²⟩ = kT``, ``⟨θ̇⟩ = 0`` (no forward drift, unlike the naive sleigh), so
    ``I⟨θ̇²⟩/kT = I/(I + mR²) = 1/3``, far from the soft model's 1."""
    y = _run("naive", 1.0)
    theta_dot, phi_dot = y[..., 0], y[..., 1]
    for label, x, expected in (
        ("(I+mR²)<θ̇²>/kT", ROLLING * theta_dot**2 / KT, 1.0),
        ("J<φ̇²>/kT", TURN * phi_dot**2 / KT, 1.0),
        ("<θ̇>", theta_dot, 0.0),
    ):
        mean, se = _mean_se(x.mean(axis=1))
        assert abs(mean - expected) <= 4 * se, (label, mean, se)
    mean, se = _mean_se((ROLL * theta_dot**2 / KT).mean(axis=1))
    assert abs(mean - ROLL / ROLLING) <= 4 * se and 1 - mean >= 20 * se, (mean, se)


# ---------------------------------------------------------------- the Gibbs density


def _soft_energy(x, p):
    return 0.5 * (p.mass * (x[0] ** 2 + x[1] ** 2) + p.roll_inertia * x[2] ** 2 + p.turn_inertia * x[3] ** 2)


def _constrained_energy(x, p):
    return 0.5 * ((p.roll_inertia + p.mass * p.radius**2) * x[0] ** 2 + p.turn_inertia * x[1] ** 2)


def test_stationary_density_proves_gibbs_for_both_models_and_refuses_the_naive_sleigh():
    """S0 Statements 1–2 checked on the equations (``stationary_density``'s conditions at test points):

    - soft disk: the friction (at ``γ = 0``) and the contact (at ``ε = 0``) each balance ``exp(−T/kT)``,
      ``α = 1/kT``; the Fokker–Planck operator is the sum of the conservative part and the two, so Gibbs is
      stationary for the full model;
    - naive disk: ``α = 1/kT`` and the law's covariance ``kT diag(1/(I + mR²), 1/J)`` by quadrature;
    - naive sleigh: refused, its constrained flow compresses phase space (``div = −(ma/J) v``).
    """
    kt = 0.4
    for zeroed, friction in ((dict(gamma=0.0), "eps"), (dict(eps=0.0, gamma=3.0), "gamma")):
        params = {**PARAMS, "kT": kt, **zeroed}
        system = VerticalRollingDiskInBath(model="soft", drift=False, **params).build()
        rho = stationary_density(system, _soft_energy, friction=friction, noise="kT")
        np.testing.assert_allclose(float(rho.alpha), 1 / kt, rtol=1e-9)
    system = VerticalRollingDiskInBath(model="naive", drift=False, **{**PARAMS, "kT": kt}).build()
    rho = stationary_density(system, _constrained_energy, noise="kT")
    np.testing.assert_allclose(float(rho.alpha), 1 / kt, rtol=1e-9)
    assert rho.cov is not None
    np.testing.assert_allclose(np.asarray(rho.cov), kt * np.diag([1 / ROLLING, 1 / TURN]), atol=1e-9)
    sleigh = ChaplyginSleighInBath(model="naive", drift=False).build()
    with pytest.raises(ValueError, match="invariant measure of the frictionless, noiseless flow fails"):
        energy = lambda x, p: 0.5 * (p.mass * x[0] ** 2 + (p.inertia + p.mass * p.offset**2) * x[1] ** 2)
        stationary_density(sleigh, energy, noise="kT")


N_BINS = 20
CHI2_LIMIT = float(stats.chi2.ppf(1 - 1e-4, N_BINS - 1))  # a false alarm once in 10⁴ runs


def _chi2(samples, law):
    """Pearson's statistic of ``samples`` in ``N_BINS`` bins of equal probability under ``law`` (scipy)."""
    edges = law.ppf(np.linspace(0.0, 1.0, N_BINS + 1))
    counts = np.histogram(samples, np.clip(edges, -1e300, 1e300))[0]
    expected = samples.size / N_BINS
    return float(np.sum((counts - expected) ** 2 / expected))


def test_histograms_at_stationarity_fit_the_gibbs_density():
    """Independent samples at ``t = 10, 20, 30`` (``γ = 1``, 3 · 4096 of them) against the Gibbs law, by Pearson's
    chi-square with 20 equiprobable bins (19 degrees of freedom; the limit is its ``1 − 10⁻⁴`` quantile):

    - soft: ``T/kT ~ Γ(2)`` (four quadratic modes), ``θ̇ ~ N(0, kT/I)``;
    - naive: ``T_c/kT ~ Γ(1)`` (two), ``θ̇ ~ N(0, kT/(I + mR²))``;
    - and each model's samples fail the other model's law (the test has the power to tell them apart).
    """
    soft, naive = _run("soft", 1.0).reshape(-1, 4), _run("naive", 1.0).reshape(-1, 2)
    soft_energy = 0.5 * (soft**2 @ SOFT_MASSES) / KT
    naive_energy = 0.5 * (ROLLING * naive[:, 0] ** 2 + TURN * naive[:, 1] ** 2) / KT
    soft_law, naive_law = stats.norm(scale=np.sqrt(KT / ROLL)), stats.norm(scale=np.sqrt(KT / ROLLING))
    for label, samples, law in (
        ("soft T/kT", soft_energy, stats.gamma(2)),
        ("soft θ̇", soft[:, 2], soft_law),
        ("naive T_c/kT", naive_energy, stats.gamma(1)),
        ("naive θ̇", naive[:, 0], naive_law),
    ):
        assert _chi2(samples, law) <= CHI2_LIMIT, (label, _chi2(samples, law), CHI2_LIMIT)
    for label, samples, law in (("soft θ̇ vs naive", soft[:, 2], naive_law), ("naive θ̇ vs soft", naive[:, 0], soft_law)):
        assert _chi2(samples, law) > 10 * CHI2_LIMIT, (label, _chi2(samples, law))


# ---------------------------------------------------------------- the derivative in the temperature


@functools.cache
def _tangent_program():
    def velocities(kt, n_paths, t1):
        scene = VerticalRollingDiskInBath(model="soft", drift=False, gamma=1.0, **{**PARAMS, "kT": kt})
        ens = nhsde.simulate(
            scene.build(),
            scene.initial_state(),
            KEY,
            n_paths=n_paths,
            t1=t1,
            dt=0.01,
            solver="weak2",
            save=nhsde.Save(n=3, paths=True),
        )
        assert ens.paths is not None
        return ens.paths[:, 1:, :]  # t = 10, 20

    return velocities


def test_derivative_of_the_kinetic_energy_in_the_temperature():
    """``⟨T⟩ = 2kT`` at stationarity (Gibbs, four modes), so ``∂⟨T⟩/∂kT = 2``: the pathwise derivative
    ``Σ M_i y_i ∂y_i/∂kT`` (forward mode, fixed noise) averages to it within 4 standard errors, and the tangents
    equal central finite differences of the same paths."""
    f = functools.partial(_tangent_program(), n_paths=512, t1=20.0)
    kt, h = jnp.asarray(KT), 1e-4
    y, dy = jax.jvp(f, (kt,), (jnp.ones_like(kt),))
    fd = (jax.jvp(f, (kt + h,), (jnp.ones_like(kt),))[0] - jax.jvp(f, (kt - h,), (jnp.ones_like(kt),))[0]) / (2 * h)
    np.testing.assert_allclose(np.asarray(dy), np.asarray(fd), rtol=1e-5, atol=1e-6)
    y, dy = np.asarray(y, np.float64), np.asarray(dy, np.float64)
    mean, se = _mean_se((SOFT_MASSES * y * dy).sum(axis=-1).mean(axis=1))
    assert np.isfinite(mean) and abs(mean - 2.0) <= 4 * se, (mean, se)
    mean, se = _mean_se((0.5 * (SOFT_MASSES * y**2).sum(axis=-1)).mean(axis=1))
    assert abs(mean - 2 * KT) <= 4 * se, (mean, se)


# ---------------------------------------------------------------- the spec route


def _disk_kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * (v[0] ** 2 + v[1] ** 2) + 0.5 * p.roll_inertia * v[2] ** 2 + 0.5 * p.turn_inertia * v[3] ** 2


def _disk_rolling(q, pi, t, p):
    one, zero = jnp.ones((), q.dtype), jnp.zeros((), q.dtype)
    c, s = p.radius * jnp.cos(q[3]), p.radius * jnp.sin(q[3])
    return jnp.stack([jnp.stack([one, zero, -c, zero]), jnp.stack([zero, one, -s, zero])])


def _disk_friction(q, v, pi, t, p):
    return 2.0 * p.eps * _disk_kinetic(q, v, pi, t, p)


@pytest.mark.parametrize("model", ["soft", "naive"])
def test_spec_route_gives_the_disk_scene_equations(model):
    """The disk on the spec route (``T``, ``R = 2εT``, the rolling constraint soft or ideal, a ``temperature``)
    has the drift and noise covariance of the scene's body-frame equations at random states, after
    ``v = e·(ẋ, ẏ)``, ``w = e⊥·(ẋ, ẏ)``, ``v̇ = e·(ẍ, ÿ) + φ̇ w``, ``ẇ = e⊥·(ẍ, ÿ) − φ̇ v``."""
    scene = VerticalRollingDiskInBath(
        model=model, eps=0.4, kT=0.6, gamma=3.0, mass=0.8, radius=1.3, roll_inertia=0.7, turn_inertia=0.3
    )
    p, hand = scene.params, scene.build()
    contact = (
        dict(soft=mechanics.SoftConstraint(_disk_rolling, lambda p: p.gamma))
        if model == "soft"
        else dict(constraints=_disk_rolling)
    )
    spec = mechanics.MechanicalSpec(
        coordinates=("x", "y", "theta", "phi"),
        params=p,
        kinetic_energy=_disk_kinetic,
        dissipation=_disk_friction,
        temperature=lambda p: p.kT,
        **contact,
    )
    form = mechanics.formulate(spec, "multipliers", reference=jnp.zeros(4))
    system = form.system()
    rng = np.random.default_rng(0)
    for _ in range(4):
        phi, v, w, theta_dot, phi_dot = rng.uniform(-3, 3), *rng.normal(size=4)
        v, w = (v, w) if model == "soft" else (1.3 * theta_dot, 0.0)
        c, s = np.cos(phi), np.sin(phi)
        q = jnp.array([0.1, -0.2, 0.3, phi])
        y = form.state(q, jnp.array([v * c - w * s, v * s + w * c, theta_dot, phi_dot]))
        a, b = np.asarray(system.drift(0.0, y, p)), np.asarray(system.diffusion(0.0, y, p))
        rotation = np.array([[c, s, 0, 0], [-s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        acc, noise = rotation @ a[4:] + np.array([phi_dot * w, -phi_dot * v, 0.0, 0.0]), rotation @ b[4:]
        keep = [0, 1, 2, 3] if model == "soft" else [2, 3]
        body = [*np.asarray(q), v, w, theta_dot, phi_dot] if model == "soft" else [*np.asarray(q), theta_dot, phi_dot]
        a_hand, b_hand = hand.drift(0.0, jnp.array(body), p), hand.diffusion(0.0, jnp.array(body), p)
        np.testing.assert_allclose(acc[keep], np.asarray(a_hand)[4:], atol=1e-12)
        np.testing.assert_allclose(
            (noise @ noise.T)[np.ix_(keep, keep)], np.asarray(b_hand @ b_hand.T)[4:, 4:], atol=1e-12
        )


def _sleigh_kinetic(q, v, pi, t, p):
    s, c = jnp.sin(q[2]), jnp.cos(q[2])
    vx, vy = v[0] - p.offset * s * v[2], v[1] + p.offset * c * v[2]
    return 0.5 * p.mass * (vx**2 + vy**2) + 0.5 * p.inertia * v[2] ** 2


def _sleigh_knife(q, pi, t, p):
    return jnp.stack([-jnp.sin(q[2]), jnp.cos(q[2]), jnp.zeros((), q.dtype)])[None, :]


def _sleigh_friction(q, v, pi, t, p):
    along = jnp.cos(q[2]) * v[0] + jnp.sin(q[2]) * v[1]
    return p.eps * (p.mass * along**2 + (p.inertia + p.mass * p.offset**2) * v[2] ** 2)


def test_spec_route_soft_sleigh_obeys_equipartition():
    """The spec route's soft sleigh (``SoftConstraint`` knife, ``temperature``), simulated in world-frame velocities:
    ``m⟨v²⟩ = m⟨(w + aω)²⟩ = I⟨ω²⟩ = kT`` and ``⟨v⟩ = 0`` at ``t = 5, 10`` (``γ = 2``, ``ε = kT = 0.5``,
    ``m = I = a = 1``; the slowest velocity relaxation rate is above 0.7/s, so the start is forgotten to ``e⁻⁷`` in
    the second moments), with ``v = e₁·Ṗ``, ``w = e₂·Ṗ``; 1024 paths (the spec route's generic solves are slower
    per step than the scene's)."""
    params = ChaplyginSleighInBath(gamma=2.0, eps=0.5, kT=0.5).params
    spec = mechanics.MechanicalSpec(
        coordinates=("x", "y", "theta"),
        params=params,
        kinetic_energy=_sleigh_kinetic,
        dissipation=_sleigh_friction,
        soft=mechanics.SoftConstraint(_sleigh_knife, lambda p: p.gamma),
        temperature=lambda p: p.kT,
    )
    form = mechanics.formulate(spec, "multipliers", reference=jnp.zeros(3))
    y0 = jnp.asarray(form.state(jnp.zeros(3), jnp.array([1.0, 0.0, 0.0])), jnp.float32)
    ens = nhsde.simulate(
        form.system(), y0, KEY, n_paths=1024, t1=10.0, dt=0.01, solver="weak2", save=nhsde.Save(n=3, paths=True)
    )
    y = np.asarray(ens.paths, np.float64)[:, 1:, :]
    theta, xdot, ydot, omega = y[..., 2], y[..., 3], y[..., 4], y[..., 5]
    v = np.cos(theta) * xdot + np.sin(theta) * ydot
    w = -np.sin(theta) * xdot + np.cos(theta) * ydot
    for label, x, expected in (
        ("m<v²>/kT", v**2 / 0.5, 1.0),
        ("m<(w+aω)²>/kT", (w + omega) ** 2 / 0.5, 1.0),
        ("I<ω²>/kT", omega**2 / 0.5, 1.0),
        ("<v>", v, 0.0),
    ):
        mean, se = _mean_se(x.mean(axis=1))
        assert abs(mean - expected) <= 4 * se, (label, mean, se)
