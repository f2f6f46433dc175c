"""Nonholonomic constraints at finite temperature (THEORY.md §8; Jagla, Bloch & Rojo, arXiv 2603.14424).

The Chaplygin sleigh in a bath of temperature ``kT`` (``ChaplyginSleighInBath``), checked against statistical
mechanics and mechanics, not against the code:

- soft (viscous) knife with fluctuation–dissipation noise: a Langevin system, so its stationary law is Gibbs,
  ``exp(−T/kT)`` with ``T = ½ m (v² + (w + aω)²) + ½ I ω²`` on all three velocities: equipartition
  ``m⟨v²⟩ = m⟨(w + aω)²⟩ = I⟨ω²⟩ = kT`` and no forward drift, ``⟨v⟩ = 0``, at any contact viscosity ``γ``;
- naive model (ideal knife, noise on the friction only): the forward drift ``⟨v⟩ = a⟨ω²⟩/(2ε) > 0``;
- ``γ → ∞`` at ``kT = 0``: the ideal sleigh's closed-form tanh/sech relaxation, approached as ``m/γ``;
- the pathwise derivatives in ``kT`` and ``γ``: finite differences, and ``∂⟨m v²⟩/∂kT = 1``, ``∂⟨m v²⟩/∂γ = 0``;
- an explicit solver past its stability limit on the contact viscosity is refused before the run;
- the spec route's ``SoftConstraint`` and ``temperature`` give the same equations as the scene's Newton–Euler ones.

Stationary averages use independent paths at the saved times ``t = 10, 20, 30``: the slowest relaxation rate of
the velocities is ≥ 0.7/s here (the smallest eigenvalue of ``M⁻¹ D``), so values 10 s apart are independent to
``e⁻⁷`` and every sample counts in the standard error.
"""

import functools
from typing import Any

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import mechanics
from nhsde.scenes import ChaplyginSleighInBath

KEY = jax.random.key(20260314)
EPS, KT, MASS, INERTIA, OFFSET = 0.5, 0.5, 1.0, 1.0, 1.0
J = INERTIA + MASS * OFFSET**2
N_PATHS, T1, DT = 4096, 30.0, 0.01
SAVE = nhsde.Save(n=4, paths=True)  # t = 0, 10, 20, 30: the last three are stationary and independent


def _stationary(model, dt=DT, n_paths=N_PATHS, **params):
    """Velocities at ``t = 10, 20, 30`` of every path, flattened: ``(3 · n_paths, d)`` independent samples."""
    scene = ChaplyginSleighInBath(
        model=model, drift=False, eps=EPS, kT=KT, mass=MASS, inertia=INERTIA, offset=OFFSET, **params
    )
    ens = nhsde.simulate(
        scene.build(), scene.initial_state(), KEY, n_paths=n_paths, t1=T1, dt=dt, solver="weak2", save=SAVE
    )
    y = np.asarray(ens.paths, np.float64)[:, 1:, :]
    return y.reshape(-1, y.shape[-1])


def _mean_se(x):
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(x.size))


@pytest.mark.parametrize("gamma, dt, n_paths", [(2.0, DT, N_PATHS), (20.0, DT / 4, N_PATHS // 2)])
def test_soft_sleigh_is_gibbs_equipartition_and_no_forward_drift(gamma, dt, n_paths):
    """Gibbs law of the soft knife: each quadratic mode of ``T`` holds ``kT/2``, whatever ``γ``, and ``⟨v⟩ = 0``.

    In body-frame velocities ``(v, w, ω)``, ``T = ½ m v² + ½ m (w + aω)² + ½ I ω²`` is a sum of three
    independent squares under ``exp(−T/kT)``.  (``J⟨ω²⟩/kT`` is ``J/I = 2`` here, not 1: the slip ``w`` is a
    thermal degree of freedom at every finite ``γ``; the ideal-constraint value 1 is the naive model's.)

    The step keeps the contact rate ``λ ≈ γ (1/m + a²/I)`` at ``λ dt ≤ 0.1``: weak2's stationary law is biased
    beyond (measured at ``γ = 20`` on 8192 paths: ``I⟨ω²⟩/kT = 0.963, 0.977, 0.985 ± 0.009`` and
    ``⟨ω (w + aω)⟩ = 0.014, 0.007, 0.001 ± 0.003`` at ``dt = 0.01, 0.005, 0.0025``).
    """
    y = _stationary("soft", dt=dt, n_paths=n_paths, gamma=gamma)
    v, w, omega = y[:, 0], y[:, 1], y[:, 2]
    for label, x in (
        ("m<v²>/kT", MASS * v**2 / KT),
        ("m<(w+aω)²>/kT", MASS * (w + OFFSET * omega) ** 2 / KT),
        ("I<ω²>/kT", INERTIA * omega**2 / KT),
    ):
        mean, se = _mean_se(x)
        assert abs(mean - 1) <= 4 * se, (gamma, label, mean, se)
    mean, se = _mean_se(v)
    assert abs(mean) <= 4 * se, (gamma, "<v>", mean, se)


def test_naive_sleigh_drifts_forward_by_the_mean_balance():
    """Naive model: ``⟨v⟩ = a⟨ω²⟩/(2ε)``, and it is far from 0.

    Its forward speed obeys ``dv = (a ω² − 2ε v) dt + √(4εkT/m) dW₁`` (the scene at ``ν = 4εkT``, THEORY.md §8).
    Taking expectations, ``d⟨v⟩/dt = a⟨ω²⟩ − 2ε⟨v⟩``, which vanishes at stationarity: ``⟨v⟩ = a⟨ω²⟩/(2ε)``.  The
    centripetal term ``a ω²`` is never negative, so a bath that shakes ``ω`` pushes the sleigh forward.  The
    per-sample difference ``v − a ω²/(2ε)`` has mean 0; its standard error is the test's tolerance.
    """
    y = _stationary("naive")
    v, omega = y[:, 0], y[:, 1]
    mean, se = _mean_se(v - OFFSET * omega**2 / (2 * EPS))
    assert abs(mean) <= 4 * se, (mean, se)
    drift, drift_se = _mean_se(v)
    assert drift >= 10 * drift_se, (drift, drift_se)  # the second law's violation, unmistakable
    # and equipartition fails between v and ω, though E[H] = kT (Itô: dE[H]/dt = −4ε E[H] + 4εkT)
    kin_v, se_v = _mean_se(MASS * v**2 / KT)
    kin_w, se_w = _mean_se(J * omega**2 / KT)
    assert kin_v - 1 >= 4 * se_v and 1 - kin_w >= 4 * se_w, (kin_v, se_v, kin_w, se_w)
    assert abs((kin_v + kin_w) / 2 - 1) <= 4 * np.hypot(se_v, se_w) / 2


LOAD = 0.1  # the load force F, small against the naive drive m·2ε⟨v⟩ ≈ 0.23


@pytest.mark.parametrize("model", ["naive", "soft"])
def test_work_against_a_load_only_the_naive_model_extracts_it(model):
    """A constant load ``F`` along ``−e₁``: the power extracted against it, ``F⟨v⟩``, is positive in the naive model
    and not in the soft one (the second law: one bath does no net work in a steady state).

    Soft knife: a free rigid body, ``d(∂T/∂q̇) − ∂T/∂q = (−D q̇ + f) dt + √(2kT) D^{1/2} dW``, with the load ``f``
    (``D`` friction and contact).  In a steady state the entropy production ``Q̇/kT ≥ 0`` (``Q̇`` the heat into the
    bath, Sekimoto) and the energy balance ``d⟨T⟩/dt = ⟨f·q̇⟩ − Q̇ = 0`` give ``−F⟨v⟩ = ⟨f·q̇⟩ ≥ 0``: ``F⟨v⟩ ≤ 0``
    (linear response: ``≈ −F²/(2εm)``).
    Naive model: its constrained flow is not volume-preserving (``div = −(ma/J) v``), so Gibbs is not stationary,
    the argument fails, and ``⟨v⟩ = (a⟨ω²⟩ − F/m)/(2ε) > 0`` for small ``F`` (the mean balance of ``v``).
    """
    y = _stationary(model, load=LOAD)
    v = y[:, 0]
    power, se = _mean_se(LOAD * v)
    if model == "naive":
        assert power >= 5 * se, (power, se)  # measured 0.0143 ± 0.0006
        mean, se_balance = _mean_se(v - (OFFSET * y[:, 1] ** 2 - LOAD / MASS) / (2 * EPS))
        assert abs(mean) <= 4 * se_balance, (mean, se_balance)
    else:
        assert power <= 2 * se, (power, se)  # measured −0.0090 ± 0.0006


def _relaxation(gamma, ts):
    """The soft sleigh at ``kT = ε = 0`` from ``v = w = 0``, ``ω = 1``: ``(v, ω, θ)`` at ``ts`` (Tsit5, tight)."""
    scene = ChaplyginSleighInBath(model="soft", eps=0.0, kT=0.0, gamma=gamma, mass=MASS, inertia=INERTIA, offset=OFFSET)
    system = scene.build()
    term = diffrax.ODETerm(lambda t, y, p: system.drift(t, y, p))
    y0 = jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    sol = diffrax.diffeqsolve(
        term,
        diffrax.Tsit5(),
        0.0,
        float(ts[-1]),
        1e-4,
        y0,
        args=system.params,
        saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-12),
        max_steps=400_000,
    )
    y = np.asarray(sol.ys)
    return y[:, 3], y[:, 5], y[:, 2]


def test_stiff_contact_at_zero_temperature_is_the_ideal_sleigh():
    """``γ → ∞``, ``kT = 0``: the ideal sleigh without friction, whose energy ``½(m v² + J ω²)`` is conserved and
    ``v̇ = a ω² = (a m/J)(V² − v²)``, so from ``v = 0``, ``ω = ω₀``: ``v = V tanh(kt)``, ``ω = ω₀ sech(kt)``,
    ``θ = (ω₀/k) gd(kt)``, with ``V = ω₀ √(J/m)``, ``k = a m V/J`` and ``gd(x) = 2 atan(tanh(x/2))``.

    The soft knife's slip relaxes on the time scale ``m/γ``, so its error is ``O(1/γ)``: it falls tenfold from
    ``γ = 10³`` to ``10⁴`` (first order; measured 2.4·10⁻⁴ and 2.4·10⁻⁵), and is below ``10⁻³`` at ``10⁴``.
    """
    ts = np.linspace(0.0, 8.0, 81)
    speed = np.sqrt(J / MASS)
    k = OFFSET * MASS * speed / J
    exact = np.stack([speed * np.tanh(k * ts), 1 / np.cosh(k * ts), 2 * np.arctan(np.tanh(k * ts / 2)) / k])
    errors = []
    for gamma in (1e3, 1e4):
        errors.append(np.max(np.abs(np.stack(_relaxation(gamma, ts)) - exact)))
    assert errors[1] < 1e-3, errors
    assert 7 < errors[0] / errors[1] < 13, errors  # O(1/γ)


def test_stiffest_contact_with_the_exponential_solver_is_the_ideal_sleigh():
    """``γ = 10⁶``, ``kT = ε = 0``, ``solver="exponential"``: the ideal sleigh's tanh/sech law (above) to 10⁻³ at
    ``dt = 10⁻³`` (``λ dt = 2000``), the error first order in ``dt`` (the contact's own, ``~ m/γ``, is 10⁻⁷):
    measured 5.7·10⁻⁴ and 2.8·10⁻⁴ at ``dt = 10⁻³, 5·10⁻⁴``."""
    ts = np.linspace(0.0, 8.0, 81)
    speed = np.sqrt(J / MASS)
    k = OFFSET * MASS * speed / J
    exact = np.stack([speed * np.tanh(k * ts), 1 / np.cosh(k * ts), 2 * np.arctan(np.tanh(k * ts / 2)) / k])
    scene = ChaplyginSleighInBath(model="soft", eps=0.0, kT=0.0, gamma=1e6, mass=MASS, inertia=INERTIA, offset=OFFSET)
    errors = []
    for dt in (1e-3, 5e-4):
        ens = nhsde.simulate(
            scene.build(),
            jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
            KEY,
            n_paths=4,
            t1=8.0,
            dt=dt,
            solver="exponential",
            save=nhsde.Save(n=81, paths=True),
        )
        y = np.asarray(ens.paths)[0]
        errors.append(np.max(np.abs(np.stack([y[:, 3], y[:, 5], y[:, 2]]) - exact)))
    assert errors[0] < 1e-3 and 1.7 < errors[0] / errors[1] < 2.3, errors


@functools.cache
def _tangent_program():
    def velocities(kt, gamma, n_paths, t1):
        scene = ChaplyginSleighInBath(
            model="soft", drift=False, eps=EPS, kT=kt, gamma=gamma, mass=MASS, inertia=INERTIA, offset=OFFSET
        )
        ens = nhsde.simulate(
            scene.build(),
            scene.initial_state(),
            KEY,
            n_paths=n_paths,
            t1=t1,
            dt=DT,
            solver="weak2",
            save=nhsde.Save(n=3, paths=True),
        )
        return ens.paths[:, 1:, :]  # t = 10, 20

    return velocities


def test_derivatives_in_temperature_and_viscosity():
    """Pathwise derivatives of the velocities in ``kT`` and ``γ`` (forward mode, fixed noise).

    - they equal central finite differences of the same paths (common random numbers), at ``t = 10, 20``;
    - at stationarity ``⟨m v²⟩ = ⟨I ω²⟩ = kT`` whatever ``γ`` (Gibbs), so ``∂⟨m v²⟩/∂kT = ∂⟨I ω²⟩/∂kT = 1``
      and ``∂⟨m v²⟩/∂γ = 0``; no forward drift at any ``kT`` or ``γ``, so ``∂⟨v⟩/∂kT = ∂⟨v⟩/∂γ = 0``; within 4
      standard errors of the per-sample derivatives.
    """
    velocities = _tangent_program()
    n_paths, t1 = 512, 20.0
    kt, gamma = jnp.asarray(KT), jnp.asarray(2.0)
    f = functools.partial(velocities, n_paths=n_paths, t1=t1)
    y = f(kt, gamma)
    dy_kt, dy_gamma = jax.jacfwd(f, argnums=(0, 1))(kt, gamma)
    for tangent, args in ((dy_kt, (1e-4, 0.0)), (dy_gamma, (0.0, 1e-4))):
        up = f(kt + args[0], gamma + args[1])
        down = f(kt - args[0], gamma - args[1])
        fd = (up - down) / (2 * max(args))
        np.testing.assert_allclose(np.asarray(tangent), np.asarray(fd), rtol=1e-5, atol=1e-6)
    y, dy_kt, dy_gamma = (np.asarray(a, np.float64).reshape(-1, 3) for a in (y, dy_kt, dy_gamma))
    v, omega = y[:, 0], y[:, 2]
    for label, x, expected in (
        ("∂<m v²>/∂kT", 2 * MASS * v * dy_kt[:, 0], 1.0),
        ("∂<I ω²>/∂kT", 2 * INERTIA * omega * dy_kt[:, 2], 1.0),
        ("∂<m v²>/∂γ", 2 * MASS * v * dy_gamma[:, 0], 0.0),
        ("∂<v>/∂kT", dy_kt[:, 0], 0.0),
        ("∂<v>/∂γ", dy_gamma[:, 0], 0.0),
    ):
        mean, se = _mean_se(x)
        assert np.isfinite(mean) and abs(mean - expected) <= 4 * se, (label, mean, se)


def test_explicit_solver_past_the_contact_stability_limit_is_refused():
    """The contact damps the slip at rate ``λ = γ (1/m + a²/I)`` (plus ``O(ε)``); Euler–Maruyama multiplies it
    by ``1 − λ dt`` per step, unstable from ``λ dt = 2``.  At ``γ = 1000`` (``λ ≈ 2000``) ``dt = 0.01`` is
    refused before the run for the explicit solvers, and the exponential solver, exact on the linear damping,
    takes it (the limit itself: ``test_internal_finite_temperature``)."""
    scene = ChaplyginSleighInBath(model="soft", drift=False, gamma=1000.0, eps=EPS, kT=KT)
    system, y0 = scene.build(), scene.initial_state()
    run: dict[str, Any] = dict(n_paths=64, t1=0.1)
    for solver in ("euler", "heun", "weak2"):
        with pytest.raises(ValueError, match="unstable on this system's linear friction"):
            nhsde.simulate(system, y0, KEY, dt=0.01, solver=solver, **run)
    ens = nhsde.simulate(system, y0, KEY, dt=0.01, solver="exponential", **run)
    assert np.all(np.isfinite(np.asarray(ens.mean)))


# ---------------------------------------------------------------- the stiff extreme: γ up to 10⁶ at one step

STIFF_DT, STIFF_T1, STIFF_PATHS = 0.01, 2.0, 4096


def _gibbs_velocities(n):
    """``(v, w, ω) ~ N(0, kT M⁻¹)``, ``M`` the body-frame mass matrix of ``T``: stationary for every ``γ``."""
    mass = np.array([[MASS, 0, 0], [0, MASS, MASS * OFFSET], [0, MASS * OFFSET, J]])
    z = np.asarray(jax.random.normal(jax.random.fold_in(KEY, 7), (n, 3)), np.float64)
    return jnp.asarray(z @ np.linalg.cholesky(KT * np.linalg.inv(mass)).T, jnp.float32)


@functools.cache
def _exponential_at(gamma):
    """The soft sleigh from Gibbs, ``solver="exponential"`` at ``dt = 0.01`` whatever ``γ``: velocities at
    ``t = 1, 2`` averaged per path, and the step count."""
    scene = ChaplyginSleighInBath(model="soft", drift=False, eps=EPS, kT=KT, gamma=gamma, offset=OFFSET)
    ens = nhsde.simulate(
        scene.build(),
        _gibbs_velocities(STIFF_PATHS),
        KEY,
        n_paths=STIFF_PATHS,
        t1=STIFF_T1,
        dt=STIFF_DT,
        solver="exponential",
        save=nhsde.Save(n=3, paths=True),
    )
    return np.asarray(ens.paths, np.float64)[:, 1:, :], ens


def _contact_rate(gamma):
    """The fastest damping rate, the largest eigenvalue of ``M⁻¹ diag(2εm, γ, 2εJ)``: ``≈ γ (1/m + a²/I)``."""
    mass = np.array([[MASS, 0, 0], [0, MASS, MASS * OFFSET], [0, MASS * OFFSET, J]])
    return float(np.max(np.linalg.eigvals(np.linalg.solve(mass, np.diag([2 * EPS * MASS, gamma, 2 * EPS * J]))).real))


@pytest.mark.parametrize("gamma", [1e2, 1e4, 1e6])
def test_exponential_solver_takes_one_step_whatever_the_contact_viscosity(gamma):
    """``γ`` up to 10⁶ at ``dt = 0.01`` (``λ dt`` up to 2·10⁴): the exponential solver runs the same 200 steps,
    finite, where Euler, Heun and weak2 are refused before the run, and its contact mode is thermal: its noise has
    the exact covariance of the linear flow, so a mode of any rate keeps Gibbs's variance, the contact energy
    ``(mI/J)⟨w²⟩/2 = kT/2``, and the sleigh does not drift, ``⟨v⟩ = 0`` (Euler–Maruyama's noise ``φ₁(Ah) b ΔW``
    left it at ``tanh(λh/2)/(λh/2)`` of Gibbs, 10⁻⁴ at ``γ = 10⁶``, and the sleigh drifted forward at
    ``⟨v⟩ ≈ 0.17``: a cold contact is the naive model's ideal knife).
    """
    scene = ChaplyginSleighInBath(model="soft", drift=False, eps=EPS, kT=KT, gamma=gamma, offset=OFFSET)
    for solver in ("euler", "heun", "weak2"):
        with pytest.raises(ValueError, match="unstable on this system's linear friction"):
            nhsde.simulate(
                scene.build(), scene.initial_state(), KEY, n_paths=64, t1=STIFF_T1, dt=STIFF_DT, solver=solver
            )
    y, ens = _exponential_at(gamma)
    assert np.all(np.isfinite(y)) and ens.dt == STIFF_DT and int(ens.n_used) == STIFF_PATHS  # 200 steps, all kept
    assert _contact_rate(gamma) * STIFF_DT >= 2  # past Euler's limit
    for label, x, expected in (
        ("(mI/J)<w²>/kT", (MASS * INERTIA / J) * y[..., 1] ** 2 / KT, 1.0),
        ("<v>", y[..., 0], 0),
    ):
        mean, se = _mean_se(x.mean(axis=1))
        assert abs(mean - expected) <= 4 * se, (gamma, label, mean, se)


# ---------------------------------------------------------------- the spec route: SoftConstraint and temperature


def _kinetic(q, v, pi, t, p):
    s, c = jnp.sin(q[2]), jnp.cos(q[2])
    vx, vy = v[0] - p.offset * s * v[2], v[1] + p.offset * c * v[2]
    return 0.5 * p.mass * (vx**2 + vy**2) + 0.5 * p.inertia * v[2] ** 2


def _knife(q, pi, t, p):
    return jnp.stack([-jnp.sin(q[2]), jnp.cos(q[2]), jnp.zeros((), q.dtype)])[None, :]


def _friction(q, v, pi, t, p):
    along = jnp.cos(q[2]) * v[0] + jnp.sin(q[2]) * v[1]
    return p.eps * (p.mass * along**2 + (p.inertia + p.mass * p.offset**2) * v[2] ** 2)


@pytest.mark.parametrize("model", ["soft", "naive"])
def test_spec_route_gives_the_newton_euler_equations(model):
    """A user's sleigh on the spec route (``T``, ``R``, the knife, a ``temperature``; the knife a
    ``SoftConstraint`` or an ideal constraint) has the drift and noise covariance of the scene's Newton–Euler
    equations, at random states, after turning world-frame velocities into the body frame
    (``v = e₁·Ṗ``, ``w = e₂·Ṗ``, ``v̇ = e₁·P̈ + ω w``, ``ẇ = e₂·P̈ − ω v``)."""
    scene = ChaplyginSleighInBath(model=model, gamma=3.0, offset=0.7, inertia=1.3, mass=0.8, eps=0.4, kT=0.6)
    p, hand = scene.params, scene.build()
    knife = (
        dict(soft=mechanics.SoftConstraint(_knife, lambda p: p.gamma)) if model == "soft" else dict(constraints=_knife)
    )
    spec = mechanics.MechanicalSpec(
        coordinates=("x", "y", "theta"),
        params=p,
        kinetic_energy=_kinetic,
        dissipation=_friction,
        temperature=lambda p: p.kT,
        **knife,
    )
    assert (spec.n_ideal, spec.n_soft) == ((0, 1) if model == "soft" else (1, 0))
    assert spec.noise_dim == 3 + spec.n_soft  # √(2kT) L, L Lᵀ = ∂²R/∂q̇² (3 columns), then √(2γkT) Aᵀ
    form = mechanics.formulate(spec, "multipliers", reference=jnp.zeros(3))
    system = form.system()
    rng = np.random.default_rng(0)
    for _ in range(4):
        theta, v, w, omega = rng.uniform(-3, 3), *rng.normal(size=3)
        w = w if model == "soft" else 0.0
        c, s = np.cos(theta), np.sin(theta)
        y = form.state(jnp.array([0.1, -0.2, theta]), jnp.array([v * c - w * s, v * s + w * c, omega]))
        a, b = np.asarray(system.drift(0.0, y, p)), np.asarray(system.diffusion(0.0, y, p))
        rotation = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        acc, noise = rotation @ a[3:] + np.array([omega * w, -omega * v, 0.0]), rotation @ b[3:]
        keep = [0, 1, 2] if model == "soft" else [0, 2]
        body = np.array([0.1, -0.2, theta, v, w, omega] if model == "soft" else [0.1, -0.2, theta, v, omega])
        a_hand, b_hand = hand.drift(0.0, jnp.array(body), p), hand.diffusion(0.0, jnp.array(body), p)
        np.testing.assert_allclose(acc[keep], np.asarray(a_hand)[3:], atol=1e-12)
        np.testing.assert_allclose(
            (noise @ noise.T)[np.ix_(keep, keep)], np.asarray(b_hand @ b_hand.T)[3:, 3:], atol=1e-12
        )


def test_spec_bath_refuses_what_it_cannot_model():
    class P(nhsde.AbstractParameters):
        eps: jnp.ndarray = nhsde.parameter(default=0.5, lower=0.0, doc="friction")
        kT: jnp.ndarray = nhsde.parameter(default=0.5, doc="temperature")

    common: dict[str, Any] = dict(coordinates=("x", "y", "theta"), kinetic_energy=lambda q, v, pi, t, p: 0.5 * (v @ v))
    with pytest.raises(TypeError, match="soft=function; expected a SoftConstraint"):
        mechanics.MechanicalSpec(params=P(), soft=_knife, **common)
    with pytest.raises(ValueError, match=r"temperature\(p\) returned shape \(2,\); expected \(\)"):
        mechanics.MechanicalSpec(params=P(), temperature=lambda p: jnp.stack([p.kT, p.kT]), **common)
    quartic = mechanics.MechanicalSpec(
        params=P(), dissipation=lambda q, v, pi, t, p: p.eps * (v @ v) ** 2, temperature=lambda p: p.kT, **common
    )
    with pytest.raises(ValueError, match="dissipation is not quadratic in q̇"):
        quartic.check(jnp.zeros(3))
    cold = mechanics.MechanicalSpec(params=P(kT=-1.0), temperature=lambda p: p.kT, **common)
    with pytest.raises(ValueError, match=r"temperature\(p\) = -1.0; must be finite and ≥ 0"):
        cold.check(jnp.zeros(3))


@pytest.mark.parametrize("offset", [0.0, OFFSET])
def test_soft_sleigh_and_knife_edge_are_gibbs_on_2_16_paths(offset):
    """Issue 39's target: the soft-thermal sleigh (``a = 1``) and knife edge (``a = 0``) at ``γ ∈ {1, 10, 10², 10³}``
    (``λ dt`` from 0.02 to 20), ``solver="exponential"`` at ``dt = 0.01``: equipartition in every velocity
    component, ``m⟨v²⟩ = m⟨(w + aω)²⟩ = I⟨ω²⟩ = kT``, and no forward drift, ``⟨v⟩ = 0``, each within 4 standard
    errors on 2¹⁶ paths from Gibbs (stationary at every time), averaged over ``t = 0.5, 1``; one program."""
    n, j = 2**16, INERTIA + MASS * offset**2
    mass = np.array([[MASS, 0, 0], [0, MASS, MASS * offset], [0, MASS * offset, j]])
    z = np.asarray(jax.random.normal(jax.random.fold_in(KEY, 16), (n, 3)), np.float64)
    y0 = jnp.asarray(z @ np.linalg.cholesky(KT * np.linalg.inv(mass)).T, jnp.float32)
    for gamma in (1.0, 10.0, 1e2, 1e3):
        scene = ChaplyginSleighInBath(model="soft", drift=False, eps=EPS, kT=KT, gamma=gamma, offset=offset)
        ens = nhsde.simulate(
            scene.build(), y0, KEY, n_paths=n, t1=1.0, dt=0.01, solver="exponential", save=nhsde.Save(n=3, paths=True)
        )
        y = np.asarray(ens.paths, np.float64)[:, 1:, :]
        v, w, omega = y[..., 0], y[..., 1], y[..., 2]
        for label, x, expected in (
            ("<v>", v, 0.0),
            ("m<v²>/kT", MASS * v**2 / KT, 1.0),
            ("m<(w+aω)²>/kT", MASS * (w + offset * omega) ** 2 / KT, 1.0),
            ("I<ω²>/kT", INERTIA * omega**2 / KT, 1.0),
        ):
            mean, se = _mean_se(x.mean(axis=1))
            assert abs(mean - expected) <= 4 * se, (offset, gamma, label, mean, se)
