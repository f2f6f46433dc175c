# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Constraints at finite temperature
#
# A Chaplygin sleigh sits in a heat bath at temperature $kT$.  Its knife edge at
# $P$, a distance $a$ behind the centre of mass, lets $P$ move only along the blade:
# speed $v$ along it, angular velocity $\omega$, $J = I + ma^2$.  Which random
# forces does the bath exert?
#
# - **Naive model** (S0's, `model="naive"`): the ideal constraint, with friction
#   $\varepsilon$ and its fluctuation–dissipation noise on the constrained equations,
#
#   $$
#   dv = (a\omega^2 - 2\varepsilon v)\,dt + \sqrt{4\varepsilon kT/m}\,dW_1, \qquad
#   d\omega = \left(-\tfrac{ma}{J} v\omega - 2\varepsilon\omega\right)dt + \sqrt{4\varepsilon kT/J}\,dW_2 .
#   $$
#
#   Taking means at stationarity, $\langle v\rangle = a\langle\omega^2\rangle/(2\varepsilon) > 0$:
#   the sleigh moves forward in a bath at one temperature (Jagla, Bloch & Rojo,
#   "Nonholonomic constraints at finite temperature", arXiv 2603.14424).
# - **Soft model** (`model="soft"`): the knife is a viscous contact, the force
#   $-\gamma w$ on the slip $w$ across the blade, with its own noise
#   $\sqrt{2\gamma kT}\,dW_c$.  An ordinary Langevin system: its stationary law is
#   Gibbs, $\exp(-T/kT)$ with $T = \tfrac12 m\bigl(v^2 + (w + a\omega)^2\bigr) + \tfrac12 I\omega^2$, so
#
#   $$
#   \langle v\rangle = 0, \qquad m\langle v^2\rangle = m\langle (w + a\omega)^2\rangle = I\langle\omega^2\rangle = kT
#   \quad\text{at every } \gamma .
#   $$
#
# This notebook measures both with `nhsde.scenes.ChaplyginSleighInBath` (and the
# rolling disk, `VerticalRollingDiskInBath`):
#
# 1. **Figure 1** — the paradox: $\langle v\rangle(t)$ of both models from their
#    equilibrium laws, without and with a small load $F$ pulling the sleigh back;
#    the work $F\langle v\rangle$ drawn from one bath.
# 2. **Figure 2** — the Gibbs check: histograms of the soft sleigh's $v$ and
#    $T/kT$ against the Gibbs densities, and the rolling disk's two models.
# 3. **Figure 3** — $\gamma\to\infty$: at $kT = 0$ the ideal sleigh's tanh/sech
#    relaxation (error $\propto 1/\gamma$); at finite $kT$ the soft sleigh's
#    statistics against $\gamma$, next to the naive model's.
# 4. **Figure 4** — work against precision for $\gamma \in \{1, 10^2, 10^4, 10^6\}$:
#    `solver="exponential"` against Euler–Maruyama, which is refused past its
#    stability limit.
#
# The guide page "Constraints at finite temperature" derives the models; the
# tests (`tests/test_finite_temperature*.py`) and `benchmarks/finite_temperature.py`
# check them on more paths.  Figures are written as PNG files into
# `$NHSDE_NOTEBOOK_OUT` (default `notebooks/_output`).

# %%
import os
import time
import warnings

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from scipy import stats

import nhsde
from nhsde import plot
from nhsde.scenes import ChaplyginSleighInBath, VerticalRollingDiskInBath

# the exponential solver's once-per-solve matrices in float64 (states stay float32 below): at γ = 10⁶ a float32
# e^{Ah} loses the slow modes' part of the noise (benchmarks/RESULTS.md, "the exact noise of the linear flow")
jax.config.update("jax_enable_x64", True)
T_START = time.perf_counter()
print(
    f"nhsde {nhsde.__version__}, jax {jax.__version__} on {jax.devices()[0].platform}; figures -> {plot.figure_dir()}"
)

# %%
# The run's size: NHSDE_NOTEBOOK_SIZE=full (the default; the stored outputs) or small (the test suite's quick
# run: every cell and figure, an eighth of the paths, so the standard errors are about 2.8 times as wide, and
# fewer explicit-solver steps in the work-precision figure).
SIZE = os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")
if SIZE not in ("full", "small"):
    raise ValueError(f"NHSDE_NOTEBOOK_SIZE={SIZE!r}; allowed: 'full', 'small'")
SMALL = SIZE == "small"
print(f"size: {SIZE}")

# %% [markdown]
# ## Parameters and the measuring protocol
#
# $\varepsilon = kT = 0.5$, $m = I = a = 1$ (so $J = 2$).  Every ensemble runs to
# $t_1 = 8$ with the state saved every 0.5; the stationary statistics are per-path
# averages over $t \in [4, 8]$, with standard errors across paths (so the
# correlation of the saved times along a path is accounted for).  The soft sleigh
# starts from its Gibbs law $N(0, kT\,M^{-1})$ ($M$ the mass matrix of
# $(v, w, \omega)$), the naive one from $\exp(-H/kT)$ on the constraint,
# $v \sim N(0, kT/m)$, $\omega \sim N(0, kT/J)$: the question is whether each
# model *stays* there.  All ensembles use `solver="exponential"` at
# $\Delta t = 0.01$: exact in the linear damping and its noise, so its stationary
# law does not depend on how stiff the contact is.  One compiled program serves
# every run of one model: $\gamma$, $kT$, the load and $\Delta t$ are data.

# %%
EPS, KT, MASS, INERTIA, OFFSET = 0.5, 0.5, 1.0, 1.0, 1.0
J = INERTIA + MASS * OFFSET**2
GAMMA = 10.0  # the soft knife of sections 1-2 (contact rate γ(1/m + a²/I) = 20/s)
LOAD = 0.1
T1, DT, N_SAVE = 8.0, 0.01, 17  # saved every 0.5
N_PATHS = 1024 if SMALL else 8192
KEY = jax.random.key(39)
PARAMS = dict(eps=EPS, kT=KT, mass=MASS, inertia=INERTIA, offset=OFFSET)


def gibbs_start(model, n, key=jax.random.fold_in(KEY, 1)):
    """The equilibrium law of the velocities: soft ``N(0, kT M⁻¹)`` on ``(v, w, ω)``; naive ``exp(−H/kT)``."""
    if model == "soft":
        mass = np.array([[MASS, 0, 0], [0, MASS, MASS * OFFSET], [0, MASS * OFFSET, J]])
        cov = KT * np.linalg.inv(mass)
    else:
        cov = KT * np.diag([1 / MASS, 1 / J])
    z = np.asarray(jax.random.normal(key, (n, len(cov))), np.float64)
    return jnp.asarray(z @ np.linalg.cholesky(cov).T, jnp.float32)


def sleigh(model, *, t1=T1, n_save=N_SAVE, n_paths=N_PATHS, dt=DT, solver="exponential", y0=None, **params):
    """Paths ``(n_paths, n_save, d)`` (float64 copy) of the sleigh without its position, and the save times."""
    scene = ChaplyginSleighInBath(model=model, drift=False, **{**PARAMS, **params})
    y0 = gibbs_start(model, n_paths) if y0 is None else y0
    ens = nhsde.simulate(
        scene.build(),
        y0,
        KEY,
        n_paths=n_paths,
        t1=t1,
        dt=dt,
        solver=solver,
        save=nhsde.Save(n=n_save, paths=True),
    )
    return np.asarray(ens.paths, np.float64), np.asarray(ens.ts)


def window(paths, ts, start=4.0):
    return paths[:, ts >= start - 1e-9, :]


def mean_se(x):
    """Mean over paths of the per-path time averages of ``x`` (``(paths, times)``), and its standard error."""
    per_path = np.asarray(x).mean(axis=1)
    return float(per_path.mean()), float(per_path.std(ddof=1) / np.sqrt(per_path.size))


def fmt(m_se, digits=3):
    return f"{m_se[0]:+.{digits}f} ± {m_se[1]:.{digits}f}"


def sleigh_statistics(model, y):
    """The Gibbs statistics (``/kT``) of the windowed paths ``y``."""
    v = y[..., 0]
    if model == "soft":
        w, omega = y[..., 1], y[..., 2]
        out = {
            "<v>": v,
            "m<v²>/kT": MASS * v**2 / KT,
            "m<(w+aω)²>/kT": MASS * (w + OFFSET * omega) ** 2 / KT,
            "I<ω²>/kT": INERTIA * omega**2 / KT,
            "J<ω²>/kT": J * omega**2 / KT,
            "J<ω_s²>/kT": J * (omega + MASS * OFFSET * w / J) ** 2 / KT,
            "(mI/J)<w²>/kT": (MASS * INERTIA / J) * w**2 / KT,
        }
    else:
        omega = y[..., 1]
        out = {
            "<v>": v,
            "m<v²>/kT": MASS * v**2 / KT,
            "I<ω²>/kT": INERTIA * omega**2 / KT,
            "J<ω²>/kT": J * omega**2 / KT,
        }
    return {k: mean_se(x) for k, x in out.items()}


print(f"{N_PATHS} paths, t1 = {T1}, dt = {DT}, statistics over t in [4, {T1}]")

# %% [markdown]
# ## 1. The paradox: forward drift, and work from one bath
#
# Both models from their equilibrium laws, first free ($F = 0$), then pulled back
# by a small load $F$ (the scene's `load`: $\dot v$ gains $-F/m$).  The mean
# balance of $v$ is exact in both models:
#
# $$
# 2\varepsilon\langle v\rangle = \langle a\omega^2\rangle - F/m \ \ \text{(naive)},\qquad
# 2\varepsilon\langle v\rangle = \langle \omega(w + a\omega)\rangle - F/m \ \ \text{(soft)} .
# $$
#
# The naive drive $a\omega^2$ is never negative; the soft one, $\omega(w + a\omega)$,
# is a product of two independent Gibbs modes and averages to zero.  The power
# extracted against the load is $F\langle v\rangle$: the second law forbids it to
# be positive for any Langevin system in contact with one bath (the soft model),
# and the naive model, whose constrained flow compresses phase space, escapes
# the argument.

# %%
t0 = time.perf_counter()
runs = {}
for model in ("naive", "soft"):
    for load in (0.0, LOAD):
        runs[model, load] = sleigh(model, gamma=GAMMA, load=load)
print(f"4 ensembles of {N_PATHS} paths in {time.perf_counter() - t0:.1f} s (incl. compiling 2 programs)")

ts = runs["soft", 0.0][1]
print(f"{'model':>6} {'F':>4} | {'<v>':>14} | {'(<drive> - F/m)/(2ε)':>20} | {'F<v> (power)':>18}")
balance = {}
for (model, load), (paths, _) in runs.items():
    y = window(paths, ts)
    v = y[..., 0]
    drive = OFFSET * y[..., 1] ** 2 if model == "naive" else y[..., 2] * (y[..., 1] + OFFSET * y[..., 2])
    predicted = (drive - load / MASS) / (2 * EPS)
    balance[model, load] = mean_se(v), mean_se(predicted), mean_se(v - predicted), mean_se(load * v)
    power = fmt(balance[model, load][3], 4) if load else "—"
    print(f"{model:>6} {load:4.1f} | {fmt(mean_se(v)):>14} | {fmt(mean_se(predicted)):>20} | {power:>18}")
for model in ("naive", "soft"):
    diff = balance[model, 0.0][2]
    print(f"{model}, F = 0: <v> - balance = {fmt(diff, 4)} ({diff[0] / diff[1]:+.1f} SE; the mean balance: 0)")

for model in ("naive", "soft"):
    print(f"\n{model} model, F = 0, statistics / kT (Gibbs: 1; <v>: 0):")
    for name, value in sleigh_statistics(model, window(runs[model, 0.0][0], ts)).items():
        print(f"  {name:>15} = {fmt(value)}")

power_naive, power_soft = balance["naive", LOAD][3], balance["soft", LOAD][3]
print(
    f"\nwork against F = {LOAD}: naive F<v> = {fmt(power_naive, 4)} ({power_naive[0] / power_naive[1]:+.1f} SE), "
    f"soft F<v> = {fmt(power_soft, 4)} ({power_soft[0] / power_soft[1]:+.1f} SE); "
    f"soft linear response -F²/(2εm) = {-(LOAD**2) / (2 * EPS * MASS):+.4f}"
)

# %% [markdown]
# The naive sleigh leaves its equilibrium law within a few friction times
# $1/(2\varepsilon)$ and settles at $\langle v\rangle = a\langle\omega^2\rangle/(2\varepsilon) > 0$,
# with $m\langle v^2\rangle > kT > J\langle\omega^2\rangle$: equipartition between
# its two modes fails, although $\langle H\rangle = kT$.  The soft sleigh stays at
# Gibbs: $\langle v\rangle = 0$ and every quadratic mode at $kT$ within its
# standard error ($J\langle\omega^2\rangle/kT = J/I = 2$ there: the slip is a
# thermal degree of freedom at any finite $\gamma$).  Under the load the naive
# sleigh still moves forward, doing work $F\langle v\rangle > 0$ many standard
# errors from zero, drawn from a single bath; the soft one is pushed back
# ($F\langle v\rangle < 0$, of the size linear response predicts, $-F^2/(2\varepsilon m)$).

# %%
fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), sharey=True)
for ax, load in zip(axes, (0.0, LOAD)):
    for model, color in (("naive", "C3"), ("soft", "C0")):
        paths = runs[model, load][0]
        v = paths[..., 0]
        m, se = v.mean(axis=0), v.std(axis=0, ddof=1) / np.sqrt(v.shape[0])
        label = "naive (ideal knife, friction noise)" if model == "naive" else f"soft (viscous knife γ = {GAMMA:g})"
        ax.fill_between(ts, m - 2 * se, m + 2 * se, color=color, alpha=0.25, lw=0)
        ax.plot(ts, m, "o-", color=color, ms=3, label=label + ", ±2 SE")
        level = balance[model, load][0][0]
        ax.axhline(level, color=color, ls=":", lw=1)
    naive_paths = runs["naive", load][0]
    identity = ((OFFSET * naive_paths[..., 1] ** 2 - load / MASS) / (2 * EPS)).mean(axis=0)
    ax.plot(ts, identity, "k--", lw=1, label=r"naive $(a\langle\omega^2\rangle - F/m)/(2\varepsilon)$")
    ax.axhline(0, color="k", lw=0.6)
    ax.axvspan(4, T1, color="0.93", zorder=0)
    ax.set_xlabel("t")
    ax.set_title(f"load F = {load:g}" + ("" if load == 0 else f": power F<v> naive {power_naive[0]:+.4f}"))
    ax.grid(alpha=0.3)
axes[0].set_ylabel(r"$\langle v\rangle$ (speed of the knife along the blade)")
axes[0].legend(fontsize=8, loc="center right")
fig.suptitle(
    rf"Chaplygin sleigh in a bath, $\varepsilon = kT = {EPS}$, $m = I = a = 1$, {N_PATHS} paths "
    "(shaded: the stationary window)"
)
fig.tight_layout()
_ = plot.save(fig, "finite_temperature_drift.png")

# %% [markdown]
# ## 2. The Gibbs check, and the rolling disk
#
# In the soft model $v \sim N(0, kT/m)$ and $T/kT \sim \Gamma(3/2)$ (three
# independent quadratic modes).  The histograms use the states at $t = 4$ and
# $t = 8$ of every path (correlated by at most $e^{-0.7\cdot 4} \approx 0.06$: the
# slowest velocity relaxation rate is above 0.7/s), with a Pearson $\chi^2$ over 20
# equiprobable bins (19 degrees of freedom, so about $19 \pm 6$ for the right law).
#
# **The rolling disk** (`VerticalRollingDiskInBath`: radius $R$, mass $m$,
# inertia $I$ about the axle and $J$ about the vertical) behaves differently.  Its
# naive model, rolling without slipping plus friction noise, has a
# volume-preserving constrained flow, so its stationary law is
# $\exp(-T_c/kT)$, $T_c = \tfrac12 (I + mR^2)\dot\theta^2 + \tfrac12 J\dot\varphi^2$:
# Gibbs *conditioned on no slip*.  It does not drift.  What it misses are the
# contact's thermal slip modes: $I\langle\dot\theta^2\rangle/kT = I/(I + mR^2) = 1/3$
# (with the defaults $m = R = 1$, $I = 1/2$, $J = 1/4$) instead of the soft
# contact's 1, and $\langle T\rangle = kT$ instead of $2kT$.  Both disks start at
# rest; the window is again $t \in [4, 8]$ (slowest rate $2\varepsilon = 1$/s).

# %%
soft_y = runs["soft", 0.0][0]
pick = np.isin(np.round(ts, 6), (4.0, 8.0))
v_soft, v_naive = soft_y[:, pick, 0].ravel(), runs["naive", 0.0][0][:, pick, 0].ravel()
w_soft, om_soft = soft_y[:, pick, 1].ravel(), soft_y[:, pick, 2].ravel()
energy_soft = (0.5 * (MASS * (v_soft**2 + (w_soft + OFFSET * om_soft) ** 2) + INERTIA * om_soft**2)) / KT
v_law, t_law = stats.norm(scale=np.sqrt(KT / MASS)), stats.gamma(1.5)


def chi_square(x, law, bins=20):
    """Pearson χ² of the samples ``x`` against ``law`` over equiprobable bins, and its p-value."""
    inner = law.ppf(np.linspace(0, 1, bins + 1)[1:-1])
    counts = np.bincount(np.searchsorted(inner, x), minlength=bins)
    expected = x.size / bins
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    return chi2, float(stats.chi2.sf(chi2, bins - 1))


print(f"{v_soft.size} samples per model (t = 4, 8)")
for label, x, law in (
    ("soft v vs N(0, kT/m)", v_soft, v_law),
    ("soft T/kT vs Gamma(3/2)", energy_soft, t_law),
    ("naive v vs N(0, kT/m)", v_naive, v_law),
):
    chi2, p = chi_square(x, law)
    print(f"  {label:>26}: chi2 = {chi2:9.1f}, p = {p:.3g}")

DISK = dict(eps=EPS, kT=KT, mass=1.0, radius=1.0, roll_inertia=0.5, turn_inertia=0.25)
ROLLING = DISK["roll_inertia"] + DISK["mass"] * DISK["radius"] ** 2
t0 = time.perf_counter()
disk = {}
for model in ("soft", "naive"):
    scene = VerticalRollingDiskInBath(model=model, drift=False, gamma=GAMMA, **DISK)
    y0 = jnp.zeros(scene.build().state_dim, jnp.float32)
    ens = nhsde.simulate(
        scene.build(),
        y0,
        KEY,
        n_paths=N_PATHS,
        t1=T1,
        dt=DT,
        solver="exponential",
        save=nhsde.Save(n=N_SAVE, paths=True),
    )
    disk[model] = np.asarray(ens.paths, np.float64)
print(f"2 disk ensembles in {time.perf_counter() - t0:.1f} s (incl. compiling 2 programs)")

ys, yn = window(disk["soft"], ts), window(disk["naive"], ts)
m_, r_, i_, j_ = DISK["mass"], DISK["radius"], DISK["roll_inertia"], DISK["turn_inertia"]
soft_T = 0.5 * (m_ * (ys[..., 0] ** 2 + ys[..., 1] ** 2) + i_ * ys[..., 2] ** 2 + j_ * ys[..., 3] ** 2)
naive_T = 0.5 * (ROLLING * yn[..., 0] ** 2 + j_ * yn[..., 1] ** 2)
disk_rows = [
    ("I<θ̇²>/kT", mean_se(i_ * ys[..., 2] ** 2 / KT), mean_se(i_ * yn[..., 0] ** 2 / KT), "1 | I/(I+mR²) = 1/3"),
    (
        "m<v²>/kT",
        mean_se(m_ * ys[..., 0] ** 2 / KT),
        mean_se(m_ * (r_ * yn[..., 0]) ** 2 / KT),
        "1 | mR²/(I+mR²) = 2/3",
    ),
    ("m<w²>/kT", mean_se(m_ * ys[..., 1] ** 2 / KT), (0.0, 0.0), "1 | 0"),
    ("J<φ̇²>/kT", mean_se(j_ * ys[..., 3] ** 2 / KT), mean_se(j_ * yn[..., 1] ** 2 / KT), "1 | 1"),
    ("<T>/kT", mean_se(soft_T / KT), mean_se(naive_T / KT), "2 | 1"),
    ("<v> (naive: <Rθ̇>)", mean_se(ys[..., 0]), mean_se(r_ * yn[..., 0]), "0 | 0"),
]
print(f"\n{'disk':>20} | {f'soft, γ = {GAMMA:g}':>16} | {'naive':>16} | theory soft | naive")
for name, s, n, theory in disk_rows:
    print(f"{name:>20} | {fmt(s)} | {fmt(n)} | {theory}")
theta_soft = disk["soft"][:, pick, 2].ravel()
theta_naive = disk["naive"][:, pick, 0].ravel()
for label, x, law in (
    ("soft θ̇ vs N(0, kT/I)", theta_soft, stats.norm(scale=np.sqrt(KT / i_))),
    ("naive θ̇ vs N(0, kT/(I+mR²))", theta_naive, stats.norm(scale=np.sqrt(KT / ROLLING))),
    ("naive θ̇ vs N(0, kT/I)", theta_naive, stats.norm(scale=np.sqrt(KT / i_))),
):
    chi2, p = chi_square(x, law)
    print(f"  {label:>28}: chi2 = {chi2:9.1f}, p = {p:.3g}")

# %% [markdown]
# Left: the sleigh's forward speed.  The soft model's histogram lies on the
# Gibbs density; the naive model's is shifted forward and its $\chi^2$ is far
# outside the range of the right law.  Middle: the soft sleigh's kinetic energy
# against $\Gamma(3/2)$.  Right: the disk's rolling rate $\dot\theta$ — each model
# on its own law, and the two laws far apart (widths $\sqrt{kT/I}$ and
# $\sqrt{kT/(I + mR^2)}$).

# %%
fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
ax = axes[0]
grid = np.linspace(-3.5, 3.5, 300) * np.sqrt(KT / MASS)
ax.hist(v_soft, bins=60, density=True, color="C0", alpha=0.5, label=f"soft, γ = {GAMMA:g}")
ax.hist(v_naive, bins=60, density=True, color="C3", alpha=0.4, label="naive")
ax.plot(grid, v_law.pdf(grid), "k-", lw=1.5, label=r"Gibbs $N(0, kT/m)$")
ax.axvline(0, color="k", lw=0.6)
ax.set_xlabel("v")
ax.set_ylabel("density")
ax.set_title("sleigh: forward speed")
ax.legend(fontsize=8)
ax = axes[1]
grid = np.linspace(0, 8, 300)
ax.hist(energy_soft, bins=80, range=(0, 8), density=True, color="C0", alpha=0.5, label=f"soft, γ = {GAMMA:g}")
ax.plot(grid, t_law.pdf(grid), "k-", lw=1.5, label=r"Gibbs $\Gamma(3/2)$")
ax.set_xlabel("T / kT")
ax.set_title("sleigh: kinetic energy (soft model)")
ax.legend(fontsize=8)
ax = axes[2]
grid = np.linspace(-3.5, 3.5, 300) * np.sqrt(KT / i_)
ax.hist(theta_soft, bins=60, density=True, color="C0", alpha=0.5, label=f"soft contact, γ = {GAMMA:g}")
ax.hist(theta_naive, bins=60, density=True, color="C3", alpha=0.4, label="naive (rolls without slipping)")
ax.plot(grid, stats.norm(scale=np.sqrt(KT / i_)).pdf(grid), "k-", lw=1.5, label=r"Gibbs $N(0, kT/I)$")
ax.plot(grid, stats.norm(scale=np.sqrt(KT / ROLLING)).pdf(grid), "k--", lw=1.2, label=r"$N(0, kT/(I + mR^2))$")
ax.set_xlabel(r"$\dot\theta$")
ax.set_title("rolling disk: rolling rate")
ax.legend(fontsize=8)
for ax in axes:
    ax.grid(alpha=0.3)
fig.suptitle(rf"Stationary samples at $t = 4, 8$ ({v_soft.size} per model), $\varepsilon = kT = {EPS}$")
fig.tight_layout()
_ = plot.save(fig, "finite_temperature_gibbs.png")

# %% [markdown]
# ## 3. The stiff contact, $\gamma \to \infty$
#
# **At $kT = 0$** (and $\varepsilon = 0$) the ideal sleigh keeps its energy and
# relaxes to straight-line motion: from $v = 0$, $\omega = \omega_0$,
# $v = V\tanh(kt)$, $\omega = \omega_0\,\mathrm{sech}(kt)$, with $V = \omega_0\sqrt{J/m}$,
# $k = amV/J$.  The soft sleigh's slip relaxes on the contact time scale $m/\gamma$,
# so its distance from that law is first order in $1/\gamma$.  We integrate it with
# the exponential solver at $\Delta t = 10^{-3}$ (and, at full size, $2.5\cdot 10^{-4}$; float64,
# $\lambda\Delta t$ up to $2\cdot 10^{3}$ at $\gamma = 10^6$: explicit solvers are
# refused there): below the $1/\gamma$ line the step's own error, first order in
# $\Delta t$, takes over.
#
# **At finite $kT$** the soft sleigh's stationary law is Gibbs at every $\gamma$:
# its limit is not the naive model.  The slow variables, $v$ and the angular
# momentum about the knife $L_P = J\omega_s$, $\omega_s = \omega + (ma/J)\,w$ (which
# the contact force does not change), are those of an ideal sleigh in
# equipartition, $m\langle v^2\rangle = J\langle\omega_s^2\rangle = kT$, with no
# drift; the slip keeps its thermal variance, $(mI/J)\langle w^2\rangle = kT$, and
# decorrelates ever faster.  The naive model has neither.

# %%
ts_relax = np.linspace(0.0, 8.0, 81)
speed = np.sqrt(J / MASS)
rate_k = OFFSET * MASS * speed / J
exact_v, exact_omega = speed * np.tanh(rate_k * ts_relax), 1 / np.cosh(rate_k * ts_relax)
GAMMAS_RELAX = (10.0, 1e2, 1e3, 1e4, 1e6)
DTS_RELAX = (1e-3,) if SMALL else (1e-3, 2.5e-4)
relax_error, relax_paths = {}, {}
t0 = time.perf_counter()
for dt in DTS_RELAX:
    for gamma in GAMMAS_RELAX:
        y, _ = sleigh(
            "soft",
            t1=8.0,
            n_save=81,
            n_paths=64,
            dt=dt,
            y0=jnp.array([0.0, 0.0, 1.0]),
            gamma=gamma,
            eps=0.0,
            kT=0.0,
        )
        relax_paths[gamma, dt] = y[0]
        relax_error[gamma, dt] = max(np.abs(y[0, :, 0] - exact_v).max(), np.abs(y[0, :, 2] - exact_omega).max())
print(f"kT = 0 relaxation: {len(relax_error)} solves in {time.perf_counter() - t0:.1f} s (incl. compiling 1 program)")
print("largest |error| over t in [0, 8] against tanh/sech, in v and ω:")
print(f"{'gamma':>8} " + " ".join(f"{f'dt = {dt:g}':>12}" for dt in DTS_RELAX))
for gamma in GAMMAS_RELAX:
    print(f"{gamma:8.0e} " + " ".join(f"{relax_error[gamma, dt]:12.2e}" for dt in DTS_RELAX))
ratio = relax_error[10.0, DTS_RELAX[-1]] / relax_error[1e2, DTS_RELAX[-1]]
print(f"error(γ = 10) / error(γ = 100) = {ratio:.1f} (first order in 1/γ: 10)")

# %%
GAMMAS_LIMIT = (1.0, 10.0, 1e2, 1e3, 1e4, 1e6)
limit = {}
t0 = time.perf_counter()
for gamma in GAMMAS_LIMIT:
    paths, _ = sleigh("soft", gamma=gamma)
    limit[gamma] = sleigh_statistics("soft", window(paths, ts))
limit["naive"] = sleigh_statistics("naive", window(runs["naive", 0.0][0], ts))
print(f"{len(GAMMAS_LIMIT)} soft ensembles in {time.perf_counter() - t0:.1f} s")
NAMES = ("<v>", "m<v²>/kT", "I<ω²>/kT", "J<ω²>/kT", "J<ω_s²>/kT", "(mI/J)<w²>/kT")
print(f"{'model':>12} | " + " | ".join(f"{n:>15}" for n in NAMES))
for key_, row in limit.items():
    label = key_ if key_ == "naive" else f"soft γ={key_:g}"
    cells = []
    for n in NAMES:
        if n in row:
            cells.append(f"{fmt(row[n]):>15}")
        else:
            cells.append(f"{'(= J<ω²>/kT)' if n == 'J<ω_s²>/kT' else '(0: no slip)':>15}")
    print(f"{label:>12} | " + " | ".join(cells))
print("Gibbs (soft, every γ): <v> = 0, m<v²> = I<ω²> = J<ω_s²> = (mI/J)<w²> = kT, J<ω²> = (J/I) kT")

# %% [markdown]
# Left: the soft sleigh at $kT = 0$, $\gamma = 10$ (where the contact's lag is
# visible) and $\gamma = 10^6$, against the tanh/sech law.  Middle: the largest
# error over $t \in [0, 8]$ against $\gamma$ — on the $1/\gamma$ line until it
# meets the floor of the step's own error, first order in $\Delta t$
# (a quarter of the step, a quarter of the floor).  Right: the stationary statistics of the soft
# sleigh at $kT = 0.5$ against $\gamma$ (Gibbs: 0 and 1, dotted), with the naive
# model's values as dashed lines: the soft model does not move towards them.

# %%
fig, axes = plt.subplots(1, 3, figsize=(16, 4.4))
ax = axes[0]
ax.plot(ts_relax, exact_v, "k-", lw=2.5, alpha=0.35, label=r"ideal: $V\tanh(kt)$, $\omega_0\,\mathrm{sech}(kt)$")
ax.plot(ts_relax, exact_omega, "k-", lw=2.5, alpha=0.35)
for gamma, color in ((10.0, "C1"), (1e6, "C0")):
    y = relax_paths[gamma, DTS_RELAX[-1]]
    ax.plot(ts_relax, y[:, 0], "--", color=color, label=f"soft γ = {gamma:g}: v")
    ax.plot(ts_relax, y[:, 2], ":", color=color, label=f"soft γ = {gamma:g}: ω")
ax.set_xlabel("t")
ax.set_title(r"$kT = 0$: relaxation to straight-line motion")
ax.legend(fontsize=8)
ax = axes[1]
g = np.array(GAMMAS_RELAX)
for dt, marker in zip(DTS_RELAX, ("s", "o")):
    ax.loglog(g, [relax_error[gamma, dt] for gamma in GAMMAS_RELAX], marker + "-", label=f"exponential, Δt = {dt:g}")
ax.loglog(g, relax_error[1e2, DTS_RELAX[-1]] * 1e2 / g, "k--", lw=1, label=r"$\propto 1/\gamma$")
ax.set_xlabel(r"contact viscosity $\gamma$")
ax.set_ylabel("largest |error| in v, ω")
ax.set_title(r"$kT = 0$: distance from the ideal sleigh")
ax.legend(fontsize=8)
ax = axes[2]
gl = np.array(GAMMAS_LIMIT)
for n, color, target in (
    ("<v>", "C3", 0.0),
    ("m<v²>/kT", "C0", 1.0),
    ("J<ω_s²>/kT", "C2", 1.0),
    ("(mI/J)<w²>/kT", "C4", 1.0),
):
    m = np.array([limit[gamma][n][0] for gamma in GAMMAS_LIMIT])
    se = np.array([limit[gamma][n][1] for gamma in GAMMAS_LIMIT])
    ax.errorbar(gl, m, yerr=2 * se, fmt="o-", color=color, ms=4, capsize=3, label=f"soft {n}")
    ax.axhline(target, color=color, ls=":", lw=1)
    if n in limit["naive"]:
        ax.axhline(limit["naive"][n][0], color=color, ls="--", lw=1.2, label=f"naive {n}")
ax.axhline(limit["naive"]["J<ω²>/kT"][0], color="C2", ls="--", lw=1.2, label="naive J<ω²>/kT (= J<ω_s²>/kT)")
ax.set_xscale("log")
ax.set_xlabel(r"contact viscosity $\gamma$")
ax.set_title(rf"$kT = {KT}$: stationary statistics (±2 SE)")
ax.legend(fontsize=7, loc="center right")
for ax in axes:
    ax.grid(alpha=0.3, which="both")
fig.tight_layout()
_ = plot.save(fig, "finite_temperature_limit.png")

# %% [markdown]
# ## 4. The stiff extreme: work against precision
#
# The contact damps the slip at the rate $\lambda \approx \gamma(1/m + a^2/I)$:
# $2\cdot 10^6$/s at $\gamma = 10^6$.  The scene declares its velocity damping as
# the system's `linear_drift`, so `simulate` refuses an explicit solver past its
# stability limit before the run (Euler–Maruyama: $\lambda\Delta t \ge 2$), and
# `solver="exponential"` treats the damping and its noise exactly and takes any
# step.
#
# The error measured: from the Gibbs law, the largest distance from Gibbs of
# $\langle v\rangle\sqrt{m/kT}$, $m\langle v^2\rangle/kT$, $J\langle\omega_s^2\rangle/kT$
# and $(mI/J)\langle w^2\rangle/kT$ (every time is stationary for the exact
# process, so any departure is the solver's).  The cost: steps per path over the
# same span $t_1 = 8$.  Errors below about two standard errors (the grey band) are
# Monte-Carlo noise, not resolved.  Euler is run from its largest stable step
# $0.25/2^k$ downwards, while the steps per path stay within a budget.

# %%
GAMMAS_WP = (1.0, 1e2, 1e4, 1e6)
DTS_EXP = (0.25, 0.125, 0.0625, 0.03125, 0.01)
MAX_STEPS = 2048 if SMALL else 16384
WP_NAMES = ("<v>", "m<v²>/kT", "J<ω_s²>/kT", "(mI/J)<w²>/kT")


def gibbs_error(paths):
    """The largest |statistic − Gibbs| (``⟨v⟩`` in units of ``√(kT/m)``), the largest SE, the statistics."""
    out = sleigh_statistics("soft", window(paths, ts))
    scale = {n: np.sqrt(MASS / KT) if n == "<v>" else 1.0 for n in WP_NAMES}
    gibbs = {n: 0.0 if n == "<v>" else 1.0 for n in WP_NAMES}
    error = max(abs(out[n][0] - gibbs[n]) * scale[n] for n in WP_NAMES)
    return error, max(out[n][1] * scale[n] for n in WP_NAMES), out


def contact_rate(gamma):
    system = ChaplyginSleighInBath(model="soft", drift=False, gamma=gamma, **PARAMS).build()
    return float(np.max(np.abs(np.linalg.eigvals(np.asarray(system.linear_drift(system.params), np.float64)))))


wp = []  # (gamma, solver, dt, steps per path, seconds, error, se, statistics)
not_run = {}  # γ: steps per path of Euler's largest stable step, beyond the budget
caught = []  # simulate's StationaryVarianceWarning for Euler's coarse steps: the last one is printed below
t0 = time.perf_counter()
for gamma in GAMMAS_WP:
    lam = contact_rate(gamma)
    for dt in DTS_EXP:
        tic = time.perf_counter()
        paths, _ = sleigh("soft", gamma=gamma, dt=dt)
        seconds = time.perf_counter() - tic
        wp.append((gamma, "exponential", dt, round(T1 / dt), seconds, *gibbs_error(paths)))
    dt = 0.25
    while lam * dt >= 2:  # Euler–Maruyama's stability limit on the slip mode
        dt /= 2
    while T1 / dt <= MAX_STEPS and lam * dt >= 0.05:
        tic = time.perf_counter()
        with warnings.catch_warnings(record=True) as record:
            warnings.simplefilter("always", nhsde.StationaryVarianceWarning)
            paths, _ = sleigh("soft", gamma=gamma, dt=dt, solver="euler")
        caught += [str(w.message) for w in record]
        seconds = time.perf_counter() - tic
        wp.append((gamma, "euler", dt, round(T1 / dt), seconds, *gibbs_error(paths)))
        dt /= 2
    if not any(row[0] == gamma and row[1] == "euler" for row in wp):
        not_run[gamma] = T1 / dt
        print(f"γ = {gamma:g}: Euler's largest stable step 0.25/2^k is {dt:.2g}: {T1 / dt:.3g} steps per path, not run")
print(f"work-precision runs in {time.perf_counter() - t0:.1f} s (incl. compiling Euler's program)")
print(
    f"simulate warned on {len(caught)} Euler runs; the last: StationaryVarianceWarning: {caught[-1] if caught else '-'}\n"
)

print(
    f"{'γ':>6} {'solver':>12} {'dt':>9} {'λ dt':>9} {'steps':>6} {'s':>6} | {'error':>7} {'SE':>6} | "
    + " | ".join(f"{n:>15}" for n in WP_NAMES)
)
rates = {gamma: contact_rate(gamma) for gamma in GAMMAS_WP}
for gamma, solver, dt, steps, seconds, error, se, out in wp:
    print(
        f"{gamma:6.0e} {solver:>12} {dt:9.3g} {rates[gamma] * dt:9.3g} {steps:6d} {seconds:6.2f} | {error:7.3f} {se:6.3f} | "
        + " | ".join(f"{fmt(out[n]):>15}" for n in WP_NAMES)
    )

# %% [markdown]
# The refusal, before anything is compiled or run: Euler at $\gamma = 10^6$ and
# $\Delta t = 0.01$ ($\lambda\Delta t \approx 2\cdot 10^4$).

# %%
scene = ChaplyginSleighInBath(model="soft", drift=False, gamma=1e6, **PARAMS)
try:
    nhsde.simulate(scene.build(), gibbs_start("soft", 64), KEY, n_paths=64, t1=T1, dt=0.01, solver="euler")
except ValueError as error:
    print(f"ValueError: {error}")

# %% [markdown]
# Solid lines: the exponential solver, one line per $\gamma$.  Its error does not
# depend on $\gamma$ (from $\gamma = 10^2$ on, where the contact relaxes within a
# step, the lines coincide: the paths share their noise), and at its coarsest
# steps it comes from the Euler treatment of the nonlinear (gyroscopic) terms,
# first order in $\Delta t$, not from the contact.  Dashed: Euler–Maruyama, which exists only where it is
# stable and is accurate only at $\lambda\Delta t \ll 1$: at $\gamma = 10^2$ its
# largest stable steps heat the contact mode (its stationary variance is
# $1/(1 - \lambda\Delta t/2)$ times Gibbs's) and push the sleigh backwards, and at
# $\gamma = 10^4$ and $10^6$ its largest stable step needs more steps per path than
# the budget.

# %%
fig, ax = plt.subplots(figsize=(8, 5))
for color, gamma in zip(("C0", "C1", "C2", "C3"), GAMMAS_WP):
    for solver, style in (("exponential", "o-"), ("euler", "s--")):
        rows = [r for r in wp if r[0] == gamma and r[1] == solver]
        if rows:
            ax.loglog(
                [r[3] for r in rows], [r[5] for r in rows], style, color=color, ms=5, label=f"{solver}, γ = {gamma:g}"
            )
for color, (gamma, steps) in zip(("C2", "C3"), not_run.items()):
    ax.loglog(
        [steps], [1.0], "x", color=color, ms=9, mew=2, label=f"euler, γ = {gamma:g}: largest stable step, not run"
    )
floor = 2 * float(np.median([r[6] for r in wp if r[1] == "exponential"]))
ax.axhspan(1e-4, floor, color="0.9", zorder=0, label="< 2 SE: Monte-Carlo noise")
ax.set_ylim(bottom=1e-3)
ax.set_xlabel(f"steps per path (t1 = {T1:g})")
ax.set_ylabel("largest |statistic − Gibbs|")
ax.set_title(f"Soft sleigh from Gibbs: exponential vs Euler–Maruyama ({N_PATHS} paths, float32 states)")
ax.legend(fontsize=8, ncol=2)
ax.grid(alpha=0.3, which="both")
fig.tight_layout()
_ = plot.save(fig, "finite_temperature_work_precision.png")

# %%
print(f"notebook finished in {time.perf_counter() - T_START:.1f} s")
