"""The soft-knife sleigh in a bath at large contact viscosity γ (issue 39, items 3–4).

1. Work–precision over γ ∈ {1, 10², 10⁴, 10⁶}: the error of stationary statistics against the path-steps and seconds
   spent, for Euler and weak2 (at their largest stable step and at ``λ dt ≈ 0.1``, ``λ = γ(1/m + a²/I)`` the contact
   rate, where the step count stays below ``--max-steps``) and for ``solver="exponential"`` at one fixed step (its
   noise has the exact covariance of the linear flow).
2. γ → ∞ at fixed ``kT``: ``⟨v⟩``, ``m⟨v²⟩/kT``, ``I⟨ω²⟩/kT``, ``J⟨ω²⟩/kT`` and the non-contact mode
   ``J⟨ω_s²⟩/kT`` (``ω_s = ω + (ma/J) w = L_P/J``, the angular momentum about the knife) of the soft model against
   the naive model's.
4. The naive model's forward drift (``--part naive-table``): ``ChaplyginSleigh(eps=0.25, nu=0.5, mass=1,
   inertia=1, offset=a)`` (``kT = ν/(4ε) = 0.5``) for ``a = 0, 0.5, 1``, stationary averages over ``t ∈ [20, 40]``:
   ``E[H]/kT``, ``⟨v⟩`` against the mean balance ``a⟨ω²⟩/(2ε)``, ``m⟨v²⟩/kT`` and ``J⟨ω²⟩/kT``.
5. Calibration of the derivatives (``--part calibration``): ``moment_sensitivities`` of the soft sleigh in
   ``(kT, γ)`` at ``t = 20`` (stationary, from rest) over 16 keys; the z-scores of ``∂⟨v⟩/∂kT``, ``∂⟨v⟩/∂γ``,
   ``∂Var v/∂γ`` (Gibbs: 0) and ``∂(m Var v)/∂kT``, ``∂(I Var ω)/∂kT`` (Gibbs: 1) against their standard errors.
3. Stiffness (``--part stiffness``): the steps and seconds ``solver="exponential"`` needs for every Gibbs statistic
   of part 1 within ``--tol`` (and 4 SE) of Gibbs, at γ = 1 and 10⁶ (the largest of ``dt = 0.25/2^k`` that meets
   it), their ratio, and Euler's and Heun's refusal at γ = 10⁶.

Paths start from the Gibbs law ``N(0, kT M⁻¹)`` of the velocities ``(v, w, ω)`` (``M`` the body-frame mass matrix),
so every time is stationary for the exact process; statistics are the per-path averages over the saved times
``t = 1, 2`` (standard errors across paths).  ``ε = kT = 0.5``, ``m = I = a = 1``.

    python benchmarks/finite_temperature.py [--paths 4096] [--max-steps 30000] [--part …] [--tol 0.02] [--x64]

``--x64`` runs in float64; without it states are float32, and so are the exponential solver's matrices of the
linear flow, which lose the slow modes' part of ``b bᵀ`` at large ``γ`` (``ExponentialEuler``).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import nhsde
from nhsde.scenes import ChaplyginSleighInBath

EPS, KT, MASS, INERTIA, OFFSET = 0.5, 0.5, 1.0, 1.0, 1.0
J = INERTIA + MASS * OFFSET**2
T1 = 2.0
GAMMAS = (1.0, 1e2, 1e4, 1e6)


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
        rows = [("exponential", 0.01)]
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
        out, _ = run("soft", gamma, "exponential", 0.01, n_paths, key, t1=20.0)
        names = ("<v>", "m<v²>/kT", "I<ω²>/kT", "J<ω²>/kT", "J<ω_s²>/kT")
        print(f"| soft, γ = {gamma:g} | " + " | ".join(fmt(out[n]) for n in names) + " |", flush=True)
    out, _ = run("naive", 0.0, "weak2", 0.01, n_paths, key, t1=20.0)
    names = ("<v>", "m<v²>/kT", "I<ω²>/kT", "J<ω²>/kT")
    print("| naive | " + " | ".join(fmt(out[n]) for n in names) + " | (= J⟨ω²⟩/kT) |", flush=True)


def stiffness(n_paths, key, tol):
    print("| γ | λ dt at the accepted dt | dt | steps/path | s (warm) | largest |stat − Gibbs| | SE |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    cost = {}
    for gamma in (1.0, 1e6):
        dt = 0.25
        while dt >= 0.25 / 2**6:
            out, seconds = run("soft", gamma, "exponential", dt, n_paths, key, t1=2.0)
            gibbs = {name: (0.0 if name == "<v>" else 1.0) for name in out if name != "J<ω²>/kT"}
            worst = max(abs(out[name][0] - value) for name, value in gibbs.items())
            se = max(out[name][1] for name in gibbs)
            if worst <= max(tol, 4 * se):
                break
            dt /= 2
        steps = int(round(2.0 / dt))
        cost[gamma] = (steps, seconds)
        print(f"| {gamma:g} | {rate(gamma) * dt:.3g} | {dt:g} | {steps} | {seconds:.2f} | {worst:.4f} | {se:.4f} |")
    print(f"cost ratio γ = 10⁶ : γ = 1: steps {cost[1e6][0] / cost[1.0][0]:.2f}, s {cost[1e6][1] / cost[1.0][1]:.2f}")
    scene = ChaplyginSleighInBath(model="soft", drift=False, gamma=1e6, eps=EPS, kT=KT)
    for solver in ("euler", "heun"):
        try:
            nhsde.simulate(scene.build(), jnp.zeros(3), key, n_paths=64, t1=2.0, dt=0.01, solver=solver)
            print(f"{solver}: ran (not refused)")
        except ValueError as e:
            print(f"{solver}: refused: {str(e).splitlines()[0][:160]}")


def naive_table(n_paths, key):
    """The naive sleigh's stationary statistics against its mean balance, for three offsets (item 4)."""
    from nhsde.scenes import ChaplyginSleigh

    eps, nu = 0.25, 0.5
    kt = nu / (4 * eps)
    print(f"\nnaive sleigh, kT = {kt}, {n_paths} paths, averages over t in [20, 40] (5 saved times)")
    print("| offset a | E[H]/kT | <v> | a<ω²>/(2ε) | <v> − a<ω²>/(2ε) | m<v²>/kT | J<ω²>/kT |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for a in (0.0, 0.5, 1.0):
        scene = ChaplyginSleigh(eps=eps, nu=nu, mass=1.0, inertia=1.0, offset=a, drift=False)
        ens = nhsde.simulate(
            scene.build(),
            scene.initial_state(),
            key,
            n_paths=n_paths,
            t1=40.0,
            dt=0.01,
            solver="weak2",
            save=nhsde.Save(n=9, paths=True),
        )
        y = np.asarray(ens.paths, np.float64)[:, 4:, :]  # t = 20, 25, …, 40
        v, omega = y[..., 0], y[..., 1]
        j = 1.0 + a**2

        def stat(x):
            per_path = x.mean(axis=1)
            return per_path.mean(), per_path.std(ddof=1) / np.sqrt(n_paths)

        cells = [
            stat((0.5 * v**2 + 0.5 * j * omega**2) / kt),
            stat(v),
            stat(a * omega**2 / (2 * eps)),
            stat(v - a * omega**2 / (2 * eps)),
            stat(v**2 / kt),
            stat(j * omega**2 / kt),
        ]
        print(f"| {a} | " + " | ".join(f"{m:.3f} ± {se:.3f}" for m, se in cells) + " |")


def calibration(n_paths, key, n_keys=16):
    """z-scores of Gibbs's derivatives in ``kT`` and ``γ`` over ``n_keys`` keys (item 5); their sd should be ≈ 1."""
    scene = ChaplyginSleighInBath(model="soft", drift=False, eps=EPS, kT=KT, gamma=2.0, offset=OFFSET)
    system, y0 = scene.build(), scene.initial_state()
    v, omega = system.layout.index("v"), system.layout.index("omega")
    z = {label: [] for label in ("d<v>/dkT", "d<v>/dγ", "dVar v/dγ", "d(m Var v)/dkT", "d(I Var ω)/dkT")}
    for k in range(n_keys):
        sens = nhsde.statistics.moment_sensitivities(
            system, y0, jax.random.fold_in(key, k), wrt=("kT", "gamma"), n_paths=n_paths, t1=20.0, dt=0.01,
            solver="weak2", save=nhsde.Save(n=2),
        )  # fmt: skip
        dm, dm_se = np.asarray(sens.d_mean)[:, -1], np.asarray(sens.d_mean_se)[:, -1]
        dc, dc_se = np.asarray(sens.d_cov)[:, -1], np.asarray(sens.d_cov_se)[:, -1]
        z["d<v>/dkT"].append(dm[0, v] / dm_se[0, v])
        z["d<v>/dγ"].append(dm[1, v] / dm_se[1, v])
        z["dVar v/dγ"].append(dc[1, v, v] / dc_se[1, v, v])
        z["d(m Var v)/dkT"].append((MASS * dc[0, v, v] - 1) / (MASS * dc_se[0, v, v]))
        z["d(I Var ω)/dkT"].append((INERTIA * dc[0, omega, omega] - 1) / (INERTIA * dc_se[0, omega, omega]))
    print(f"\nderivative z-scores over {n_keys} keys, {n_paths} paths each, soft sleigh γ = 2, t = 20")
    print("| derivative | Gibbs | z mean | z sd |\n|---|---:|---:|---:|")
    for label, values in z.items():
        expected = 1 if label.startswith("d(") else 0
        print(f"| {label} | {expected} | {np.mean(values):+.2f} | {np.std(values, ddof=1):.2f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--paths", type=int, default=4096)
    parser.add_argument("--max-steps", type=int, default=30000)
    parts = ("all", "work-precision", "large-gamma", "stiffness", "naive-table", "calibration")
    parser.add_argument("--part", choices=parts, default="all")
    parser.add_argument("--tol", type=float, default=0.02, help="accuracy of the Gibbs statistics (stiffness)")
    parser.add_argument("--x64", action="store_true", help="float64 states (float32 loses γ ≳ 10⁵: docstring)")
    args = parser.parse_args()
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    key = jax.random.key(39)
    if args.part in ("all", "work-precision"):
        work_precision(args.paths, args.max_steps, key)
    if args.part in ("all", "large-gamma"):
        large_gamma(args.paths, key)
    if args.part in ("all", "stiffness"):
        stiffness(args.paths, key, args.tol)
    if args.part in ("all", "naive-table"):
        naive_table(args.paths, key)
    if args.part in ("all", "calibration"):
        calibration(args.paths, key)


if __name__ == "__main__":
    main()
