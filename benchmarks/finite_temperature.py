"""The soft-knife sleigh in a bath at large contact viscosity γ (issue 39, items 3–4).

1. Work–precision over γ ∈ {1, 10², 10⁴, 10⁶}: the error of stationary statistics against the path-steps and seconds
   spent, for Euler and weak2 (at their largest stable step and at ``λ dt ≈ 0.1``, ``λ = γ(1/m + a²/I)`` the contact
   rate, where the step count stays below ``--max-steps``) and for exponential Euler at one fixed step, as
   shipped (``solver="exponential"``: noise ``φ₁(Ah) b ΔW``) and with the exact Ornstein–Uhlenbeck covariance of the
   linear part (``ExponentialOU`` below, a prototype).
2. γ → ∞ at fixed ``kT``: ``⟨v⟩``, ``m⟨v²⟩/kT``, ``I⟨ω²⟩/kT``, ``J⟨ω²⟩/kT`` and the non-contact mode
   ``J⟨ω_s²⟩/kT`` (``ω_s = ω + (ma/J) w = L_P/J``, the angular momentum about the knife) of the soft model against
   the naive model's.

Paths start from the Gibbs law ``N(0, kT M⁻¹)`` of the velocities ``(v, w, ω)`` (``M`` the body-frame mass matrix),
so every time is stationary for the exact process; statistics are the per-path averages over the saved times
``t = 1, 2`` (standard errors across paths).  ``ε = kT = 0.5``, ``m = I = a = 1``.

    python benchmarks/finite_temperature.py [--paths 4096] [--max-steps 30000] [--part …] [--x64]

In float32 the slow rows of ``e^{Ah}`` lose the cancellation ``aγ/I − (ma/J)·γJ/(mI) = 0`` at ``γ = 10⁶``
(``J⟨ω_s²⟩/kT`` 1.33 with the exact-noise step); ``--x64`` runs in float64.
"""

from __future__ import annotations

import argparse
import time

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

import nhsde
from nhsde._solvers import ExponentialEuler
from nhsde.scenes import ChaplyginSleighInBath

EPS, KT, MASS, INERTIA, OFFSET = 0.5, 0.5, 1.0, 1.0, 1.0
J = INERTIA + MASS * OFFSET**2
T1 = 2.0
GAMMAS = (1.0, 1e2, 1e4, 1e6)
DOUBLINGS = 40


class ExponentialOU(ExponentialEuler):
    """Exponential Euler with the exact noise of the linear flow (additive noise):

        Z_{n+1} = e^{Ah} Z_n + h φ₁(Ah) N(Z_n) + ξ_n,   ξ_n ~ N(0, Σ_h),   Σ_h = ∫₀ʰ e^{As} b bᵀ e^{Aᵀs} ds,

    ``ξ_n = C ΔW_n``, ``C Cᵀ = Σ_h/h`` (the leading ``m`` eigenpairs; exact where ``rank Σ_h ≤ m``).  ``Σ_h`` by
    doubling from ``h/2⁴⁰``, ``Σ_{2s} = Σ_s + e^{As} Σ_s e^{Aᵀs}``: contractions only, no overflow at ``λh ≫ 1``
    (Van Loan's block exponential holds ``e^{−Ah}``, which overflows there).
    The shipped step's noise ``φ₁(Ah) b ΔW`` has variance ``≈ σ²/(λ²h)`` in a mode of rate ``λh ≫ 1``, not
    ``σ²/(2λ)``.
    """

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        drift, diffusion = terms.terms
        h = t1 - t0
        a = self.linear(args).astype(y0.dtype)
        d = y0.shape[0]
        block = jnp.block([[a * h, h * jnp.eye(d, dtype=y0.dtype)], [jnp.zeros((d, 2 * d), y0.dtype)]])
        e = jax.scipy.linalg.expm(block)
        propagator, h_phi = e[:d, :d], e[:d, d:]
        b = diffusion.vf(t0, y0, args)
        dw = diffusion.contr(t0, t1)
        s = h / 2.0**DOUBLINGS
        q = b @ b.T
        cov = s * q + 0.5 * s**2 * (a @ q + q @ a.T)

        def double(k, cov):  # e^{As} afresh at each level: I + As rounds to I in float32 at small s
            p = jax.scipy.linalg.expm(a * (s * 2.0**k))
            return cov + p @ cov @ p.T

        cov = jax.lax.fori_loop(0, DOUBLINGS, double, cov)
        vals, vecs = jnp.linalg.eigh(0.5 * (cov + cov.T) / h)
        m = b.shape[1]
        c = vecs[:, -m:] * jnp.sqrt(jnp.clip(vals[-m:], 0.0))
        nonlinear = drift.vf(t0, y0, args) - a @ y0
        y1 = propagator @ y0 + h_phi @ nonlinear + c @ dw
        return y1, None, dict(y0=y0, y1=y1), None, dfx.RESULTS.successful


def gibbs_start(key, n):
    """``(v, w, ω) ~ N(0, kT M⁻¹)``, ``T = ½ (v, w, ω) M (v, w, ω)ᵀ``."""
    mass = np.array([[MASS, 0, 0], [0, MASS, MASS * OFFSET], [0, MASS * OFFSET, J]])
    chol = np.linalg.cholesky(KT * np.linalg.inv(mass))
    return jnp.asarray(np.asarray(jax.random.normal(key, (n, 3))) @ chol.T, jnp.result_type(float))


def naive_start(key, n):
    return jnp.asarray(
        np.asarray(jax.random.normal(key, (n, 2))) * np.sqrt(KT / np.array([MASS, J])), jnp.result_type(float)
    )


def rate(gamma):
    return gamma * (1 / MASS + OFFSET**2 / INERTIA)


def run(model, gamma, solver, dt, n_paths, key, t1=T1):
    """Per-path averages over ``t = t1/2, t1`` of the statistics; and the seconds of a warm run."""
    scene = ChaplyginSleighInBath(
        model=model, drift=False, eps=EPS, kT=KT, gamma=gamma, mass=MASS, inertia=INERTIA, offset=OFFSET
    )
    system = scene.build()
    if solver == "exponential-ou":
        solver = ExponentialOU(system.linear_drift)
    start = (gibbs_start if model == "soft" else naive_start)(jax.random.fold_in(key, 1), n_paths)
    kw = dict(n_paths=n_paths, t1=t1, dt=dt, solver=solver, save=nhsde.Save(n=3, paths=True))
    nhsde.simulate(system, start, key, **kw).paths.block_until_ready()  # compile
    tic = time.perf_counter()
    ens = nhsde.simulate(system, start, key, **kw)
    y = np.asarray(ens.paths, np.float64)
    seconds = time.perf_counter() - tic
    y = y[:, 1:, :]
    v = y[..., 0]
    if model == "soft":
        w, omega = y[..., 1], y[..., 2]
        stats = {
            "<v>": v,
            "m<v²>/kT": MASS * v**2 / KT,
            "J<ω_s²>/kT": J * (omega + MASS * OFFSET * w / J) ** 2 / KT,
            "I<ω²>/kT": INERTIA * omega**2 / KT,
            "J<ω²>/kT": J * omega**2 / KT,
            "(mI/J)<w²>/kT": (MASS * INERTIA / J) * w**2 / KT,
        }
    else:
        omega = y[..., 1]
        stats = {"<v>": v, "m<v²>/kT": MASS * v**2 / KT, "I<ω²>/kT": INERTIA * omega**2 / KT}
        stats["J<ω²>/kT"] = J * omega**2 / KT
    out = {}
    for name, x in stats.items():
        per_path = x.mean(axis=1)
        out[name] = (float(per_path.mean()), float(per_path.std(ddof=1) / np.sqrt(per_path.size)))
    return out, seconds


def fmt(mean_se):
    return f"{mean_se[0]:.3f} ± {mean_se[1]:.3f}"


def work_precision(n_paths, max_steps, key):
    print("| γ | solver | dt | λ dt | steps/path | s | ⟨v⟩ | m⟨v²⟩/kT | J⟨ω_s²⟩/kT | (mI/J)⟨w²⟩/kT |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for gamma in GAMMAS:
        lam = rate(gamma)
        rows = [("exponential", 0.01), ("exponential-ou", 0.01)]
        for solver in ("euler", "weak2"):
            dt = 0.01
            while True:  # the largest stable step 0.01/2^k: simulate refuses the others before the run
                try:
                    nhsde.simulate(
                        ChaplyginSleighInBath(model="soft", drift=False, gamma=gamma, eps=EPS, kT=KT).build(),
                        jnp.zeros(3),
                        key,
                        n_paths=64,
                        t1=dt,
                        dt=dt,
                        solver=solver,
                    )
                    break
                except ValueError as e:
                    if "unstable" not in str(e):
                        raise
                    dt /= 2
            rows.append((solver, dt))
            accurate = 0.01
            while lam * accurate > 0.1:
                accurate /= 2
            if accurate != dt:
                rows.append((solver, accurate))
        for solver, dt in rows:
            steps = int(round(T1 / dt))
            if steps > max_steps:
                print(f"| {gamma:g} | {solver} | {dt:.3g} | {lam * dt:.3g} | {steps} | not run | | | | |")
                continue
            out, seconds = run("soft", gamma, solver, dt, n_paths, key)
            print(
                f"| {gamma:g} | {solver} | {dt:.3g} | {lam * dt:.3g} | {steps} | {seconds:.2f} | {fmt(out['<v>'])} "
                f"| {fmt(out['m<v²>/kT'])} | {fmt(out['J<ω_s²>/kT'])} | {fmt(out['(mI/J)<w²>/kT'])} |",
                flush=True,
            )


def large_gamma(n_paths, key):
    print("| model | ⟨v⟩ | m⟨v²⟩/kT | I⟨ω²⟩/kT | J⟨ω²⟩/kT | J⟨ω_s²⟩/kT |")
    print("|---|---:|---:|---:|---:|---:|")
    for gamma in (1.0, 10.0, 1e2, 1e3, 1e4, 1e6):
        out, _ = run("soft", gamma, "exponential-ou", 0.01, n_paths, key, t1=20.0)
        names = ("<v>", "m<v²>/kT", "I<ω²>/kT", "J<ω²>/kT", "J<ω_s²>/kT")
        print(f"| soft, γ = {gamma:g} | " + " | ".join(fmt(out[n]) for n in names) + " |", flush=True)
    out, _ = run("naive", 0.0, "weak2", 0.01, n_paths, key, t1=20.0)
    names = ("<v>", "m<v²>/kT", "I<ω²>/kT", "J<ω²>/kT")
    print("| naive | " + " | ".join(fmt(out[n]) for n in names) + " | (= J⟨ω²⟩/kT) |", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--paths", type=int, default=4096)
    parser.add_argument("--max-steps", type=int, default=30000)
    parser.add_argument("--part", choices=("all", "work-precision", "large-gamma"), default="all")
    parser.add_argument("--x64", action="store_true", help="float64 states (float32 loses γ ≳ 10⁵: docstring)")
    args = parser.parse_args()
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    key = jax.random.key(39)
    if args.part in ("all", "work-precision"):
        work_precision(args.paths, args.max_steps, key)
    if args.part in ("all", "large-gamma"):
        large_gamma(args.paths, key)


if __name__ == "__main__":
    main()
