"""Internals of the finite-temperature models: the stability limit on the contact viscosity, the PSD factor, and an
exponential step with the exact noise of the linear flow (a proposal for ``ExponentialEuler``)."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde._simulate import stable_step
from nhsde._solvers import ExponentialEuler
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


class ExponentialOU(ExponentialEuler):
    """Exponential Euler with the exact noise of the linear flow (additive noise ``b``):

        Z_{n+1} = e^{Ah} Z_n + h φ₁(Ah) N(Z_n) + C ΔW_n,   C Cᵀ h = Σ_h = ∫₀ʰ e^{As} b bᵀ e^{Aᵀs} ds,

    ``C`` from the leading ``m`` eigenpairs of ``Σ_h/h`` (exact where ``rank Σ_h ≤ m``); ``Σ_h`` by doubling from
    ``h/2⁴⁰``, ``Σ_{2s} = Σ_s + e^{As} Σ_s e^{Aᵀs}`` (contractions only: Van Loan's block exponential holds
    ``e^{−Ah}``, which overflows at ``λh ≫ 1``).  Same as ``benchmarks/finite_temperature.py``.
    """

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        drift, diffusion = terms.terms
        h, d = t1 - t0, y0.shape[0]
        a = self.linear(args).astype(y0.dtype)
        e = jax.scipy.linalg.expm(
            jnp.block([[a * h, h * jnp.eye(d, dtype=y0.dtype)], [jnp.zeros((d, 2 * d), y0.dtype)]])
        )
        b = diffusion.vf(t0, y0, args)
        s, q = h / 2.0**40, b @ b.T
        cov = s * q + 0.5 * s**2 * (a @ q + q @ a.T)

        def double(k, cov):  # e^{As} afresh at each level: I + As rounds to I in float32 at small s
            p = jax.scipy.linalg.expm(a * (s * 2.0**k))
            return cov + p @ cov @ p.T

        cov = jax.lax.fori_loop(0, 40, double, cov)
        vals, vecs = jnp.linalg.eigh(0.5 * (cov + cov.T) / h)
        c = vecs[:, -b.shape[1] :] * jnp.sqrt(jnp.clip(vals[-b.shape[1] :], 0.0))
        y1 = e[:d, :d] @ y0 + e[:d, d:] @ (drift.vf(t0, y0, args) - a @ y0) + c @ diffusion.contr(t0, t1)
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful


@pytest.mark.parametrize("offset", [0.0, 1.0])
def test_exact_noise_exponential_step_keeps_gibbs_whatever_the_contact(offset):
    """With the exact covariance of the linear flow, one step ``dt = 0.01`` keeps Gibbs for ``γ`` from 1 to 10⁴
    (``λ dt`` from 0.02 to 200), for the sleigh (``a = 1``) and the knife edge (``a = 0``): the three independent
    modes of ``T``, ``m⟨v²⟩ = m⟨(w + aω)²⟩ = I⟨ω²⟩ = kT``, the modes the contact does not touch and the contact's,
    ``J⟨ω_s²⟩ = (mI/J)⟨w²⟩ = kT`` (``ω_s = ω + (ma/J) w``, the angular momentum about the knife over ``J``), and
    ``⟨v⟩ = 0``, where the shipped step's cold contact drifts forward (``test_finite_temperature``).

    From Gibbs, ``N(0, kT M⁻¹)``, averages over ``t = 1, 2`` per path, 4096 paths, one program for every ``γ`` and
    ``a``.  (At ``γ = 10⁶`` in float32 the slow rows of ``e^{Ah}`` lose the cancellation
    ``aγ/I − (ma/J)·γJ/(mI) = 0``, relative error ``~ 10⁻⁷ λh``: ``J⟨ω_s²⟩/kT`` came out 1.33; in float64
    1.010 ± 0.016, ``benchmarks/finite_temperature.py``.)
    """
    eps, kt, m, i, a = 0.5, 0.5, 1.0, 1.0, offset
    j, n = i + m * a**2, 4096
    mass = np.array([[m, 0, 0], [0, m, m * a], [0, m * a, j]])
    key = jax.random.key(39)
    z = np.asarray(jax.random.normal(jax.random.fold_in(key, 1), (n, 3)), np.float64)
    y0 = jnp.asarray(z @ np.linalg.cholesky(kt * np.linalg.inv(mass)).T, jnp.float32)
    for gamma in (1.0, 10.0, 1e2, 1e3, 1e4):
        system = ChaplyginSleighInBath(model="soft", drift=False, eps=eps, kT=kt, gamma=gamma, offset=a).build()
        ens = nhsde.simulate(
            system,
            y0,
            key,
            n_paths=n,
            t1=2.0,
            dt=0.01,
            solver=ExponentialOU(system.linear_drift),
            save=nhsde.Save(n=3, paths=True),
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
