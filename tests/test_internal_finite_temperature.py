"""Internals of the finite-temperature models: the stability limit on the contact viscosity, the PSD factor, and the
exponential step's exact noise of the linear flow (``ExponentialEuler``)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde._simulate import stable_step
from nhsde._solvers import linear_flow
from nhsde.mechanics._small import psd_factor
from nhsde.scenes import ChaplyginSleighInBath


def test_euler_limit_is_the_contact_rate():
    """Euler–Maruyama is stable on the soft knife exactly while ``λ dt < 2``, ``λ`` the fastest damping rate,
    here the largest eigenvalue of ``M⁻¹ diag(2εm, γ, 2εJ)`` in ``(v, w, ω)``: ``≈ γ (1/m + a²/I) = 2000``."""
    eps, gamma, m, i, a = 0.5, 1000.0, 1.0, 1.0, 1.0
    j = i + m * a**2
    mass = np.array([[m, 0, 0], [0, m, m * a], [0, m * a, j]])
    rate = np.max(np.linalg.eigvals(np.linalg.solve(mass, np.diag([2 * eps * m, gamma, 2 * eps * j]))).real)
    system = ChaplyginSleighInBath(model="soft", drift=False, gamma=gamma, eps=eps).build()
    assert stable_step(system, "euler", 0.999 * 2 / rate)
    assert not stable_step(system, "euler", 1.001 * 2 / rate)


def test_psd_factor_of_singular_friction():
    """``L Lᵀ = C`` for a positive semidefinite ``C`` of rank 2 (the sleigh's ``∂²R/∂q̇²``), at every heading,
    including where a pivot vanishes (``cos θ = 0``)."""
    for theta in (0.0, 0.3, np.pi / 2, 2.0, np.pi):
        e1 = np.array([np.cos(theta), np.sin(theta), 0.0])
        c = 2 * 0.5 * (np.outer(e1, e1) + 2.0 * np.diag([0.0, 0.0, 1.0]))
        low = np.asarray(psd_factor(jnp.asarray(c)))
        assert np.all(np.isfinite(low)) and np.allclose(np.tril(low), low)
        np.testing.assert_allclose(low @ low.T, c, atol=1e-14)
    assert np.allclose(jax.jacfwd(lambda x: psd_factor(jnp.diag(jnp.stack([x, x]))))(jnp.asarray(4.0)).sum(), 0.5)


@pytest.mark.parametrize("offset", [0.0, 1.0])
def test_exact_noise_exponential_step_keeps_gibbs_whatever_the_contact(offset):
    """``solver="exponential"`` draws the exact covariance of the linear flow: one step ``dt = 0.01`` keeps Gibbs
    for ``γ`` from 1 to 10⁶ (``λ dt`` from 0.02 to 2·10⁴), for the sleigh (``a = 1``) and the knife edge (``a = 0``):
    the three independent modes of ``T``, ``m⟨v²⟩ = m⟨(w + aω)²⟩ = I⟨ω²⟩ = kT``, the modes the contact does not
    touch and the contact's, ``J⟨ω_s²⟩ = (mI/J)⟨w²⟩ = kT`` (``ω_s = ω + (ma/J) w``, the angular momentum about the
    knife over ``J``), and ``⟨v⟩ = 0``.

    From Gibbs, ``N(0, kT M⁻¹)``, averages over ``t = 1, 2`` per path, 4096 paths, float32 states (the matrices of
    the linear flow in float64), one program for every ``γ`` and ``a``.
    """
    eps, kt, m, i, a = 0.5, 0.5, 1.0, 1.0, offset
    j, n = i + m * a**2, 4096
    mass = np.array([[m, 0, 0], [0, m, m * a], [0, m * a, j]])
    key = jax.random.key(39)
    z = np.asarray(jax.random.normal(jax.random.fold_in(key, 1), (n, 3)), np.float64)
    y0 = jnp.asarray(z @ np.linalg.cholesky(kt * np.linalg.inv(mass)).T, jnp.float32)
    for gamma in (1.0, 10.0, 1e2, 1e3, 1e4, 1e6):
        system = ChaplyginSleighInBath(model="soft", drift=False, eps=eps, kT=kt, gamma=gamma, offset=a).build()
        ens = nhsde.simulate(
            system, y0, key, n_paths=n, t1=2.0, dt=0.01, solver="exponential", save=nhsde.Save(n=3, paths=True)
        )
        y = np.asarray(ens.paths, np.float64)[:, 1:, :]
        v, w, omega = y[..., 0], y[..., 1], y[..., 2]
        for label, x, expected in (
            ("<v>", v, 0.0),
            ("m<v²>/kT", m * v**2 / kt, 1.0),
            ("m<(w+aω)²>/kT", m * (w + a * omega) ** 2 / kt, 1.0),
            ("I<ω²>/kT", i * omega**2 / kt, 1.0),
            ("J<ω_s²>/kT", j * (omega + m * a * w / j) ** 2 / kt, 1.0),
            ("(mI/J)<w²>/kT", (m * i / j) * w**2 / kt, 1.0),
        ):
            per_path = x.mean(axis=1)
            mean, se = float(per_path.mean()), float(per_path.std(ddof=1) / np.sqrt(n))
            assert abs(mean - expected) <= 4 * se, (offset, gamma, label, mean, se)


def _ou_covariance(a, q, h, levels=40):
    """``Σ_h = ∫₀ʰ e^{As} Q e^{Aᵀs} ds`` by doubling from ``h/2⁴⁰`` (NumPy, float64): the reference."""
    import scipy.linalg

    s = h / 2.0**levels
    cov = s * q + 0.5 * s**2 * (a @ q + q @ a.T)
    for k in range(levels):
        p = scipy.linalg.expm(a * (s * 2.0**k))
        cov = cov + p @ cov @ p.T
    return cov


def _soft_flow(gamma, kt, h=0.01, eps=0.5):
    system = ChaplyginSleighInBath(model="soft", drift=False, eps=eps, kT=kt, gamma=gamma).build()
    p = system.params
    b = system.diffusion(0.0, jnp.zeros(3), p)
    return linear_flow(system.linear_drift(p), jnp.asarray(h), b, jnp.float64), system, b


@pytest.mark.parametrize("gamma", [1.0, 1e3, 1e6])
def test_noise_factor_is_the_exact_covariance_of_the_linear_flow(gamma):
    """``C Cᵀ h = Σ_h`` (against doubling), ``C = φ₁(Ah) b + O(h²)`` (strong order), at ``λh`` from 0.02 to
    2·10⁴; ``e^{Ah}`` and ``hφ₁(Ah)`` as before."""
    import scipy.linalg

    h = 0.01
    flow, system, b = _soft_flow(gamma, 0.5, h)
    a, b = np.asarray(system.linear_drift(system.params)), np.asarray(b)
    c = np.asarray(flow.noise)
    sigma = _ou_covariance(a, b @ b.T, h)
    np.testing.assert_allclose(c @ c.T * h, sigma, rtol=1e-9, atol=1e-12 * np.abs(sigma).max())
    np.testing.assert_allclose(np.asarray(flow.propagator), scipy.linalg.expm(a * h), rtol=1e-9, atol=1e-14)
    if gamma == 1.0:  # C − φ₁(Ah) b = O(h²)
        p = np.asarray(flow.h_phi) @ b / h
        assert np.max(np.abs(c - p)) <= 10 * h**2 * np.max(np.abs(b)), np.max(np.abs(c - p))


def test_noise_factor_derivatives_match_finite_differences():
    """Forward and reverse mode of ``C`` in ``γ`` and ``kT`` (stiff ``λh = 200`` and mild ``0.2``) equal central
    differences, and ``C`` is ``√kT`` times a factor independent of ``kT``; at ``kT = 0`` it is 0."""

    @jax.jit
    def factor(theta):
        return _soft_flow(theta[0], theta[1])[0].noise

    for gamma in (10.0, 1e4):
        theta = jnp.array([gamma, 0.5])
        fwd, rev = jax.jit(jax.jacfwd(factor))(theta), jax.jit(jax.jacrev(factor))(theta)
        np.testing.assert_allclose(np.asarray(fwd), np.asarray(rev), rtol=1e-10, atol=1e-14)
        for k in range(2):
            step = 1e-6 * float(theta[k])
            e = jnp.zeros(2).at[k].set(step)
            fd = (factor(theta + e) - factor(theta - e)) / (2 * step)
            np.testing.assert_allclose(np.asarray(fwd[..., k]), np.asarray(fd), rtol=1e-5, atol=1e-8)
        np.testing.assert_allclose(
            np.asarray(fwd[..., 1]), np.asarray(factor(theta)) / (2 * 0.5), rtol=1e-9, atol=1e-14
        )
    assert np.all(np.asarray(_soft_flow(1e4, 0.0)[0].noise) == 0.0)
