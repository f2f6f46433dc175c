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
# # A ball rolling on a randomly vibrating plane
#
# A homogeneous ball (mass $m$, radius $r$, moment of inertia $J = \kappa m r^2$)
# rolls without slipping on a horizontal plane that vibrates randomly *in its own
# plane*.  In the frame of the plane, let $x$ be the position of the ball's centre
# and $u = \dot x$ its velocity relative to the plane.  The plane's acceleration
# acts as an inertial force on the centre; eliminating the contact force with the
# rolling constraint gives, independently for each axis (S0 (3.1)),
#
# $$
# \mathrm{d}u = -2\varepsilon\, u\,\mathrm{d}t + \delta\sqrt{\nu}\,\mathrm{d}W,
# \qquad \mathrm{d}x = u\,\mathrm{d}t .
# $$
#
# The constants:
#
# | symbol | meaning |
# |---|---|
# | $\delta = \dfrac{m}{m + J/r^2} = \dfrac{1}{1+\kappa}$ | the share of the inertial force that accelerates the centre (the rest spins the ball up); $\kappa = 2/5$, so $\delta = 5/7$, for a homogeneous ball |
# | $\varepsilon$ | rolling-resistance rate, $2\varepsilon = c/(m + J/r^2)$, in 1/s |
# | $\nu$ | intensity of the white-noise acceleration of the plane, per axis |
#
# The radius does not appear: only $\kappa$ does.  The model is linear with
# additive noise, so from rest ($x = u = 0$) the state is Gaussian with zero mean
# and the covariances
#
# $$
# \begin{aligned}
# k_{uu}(t) &= \frac{\nu\delta^2}{4\varepsilon}\bigl(1 - e^{-4\varepsilon t}\bigr)
#   &&\xrightarrow{t\to\infty}\ \frac{\nu\delta^2}{4\varepsilon},\\
# k_{xu}(t) &= \frac{\nu\delta^2}{8\varepsilon^2}\bigl(1 - e^{-2\varepsilon t}\bigr)^2
#   &&\xrightarrow{t\to\infty}\ \frac{\nu\delta^2}{8\varepsilon^2},\\
# k_{xx}(t) &= \frac{\nu\delta^2}{4\varepsilon^2}\Bigl[t - \frac{1 - e^{-2\varepsilon t}}{\varepsilon}
#   + \frac{1 - e^{-4\varepsilon t}}{4\varepsilon}\Bigr]
#   &&\approx\ \frac{\nu\delta^2 t}{4\varepsilon^2}\quad(t\to\infty).
# \end{aligned}
# $$
#
# The velocity settles to a stationary Ornstein–Uhlenbeck process while the
# position spreads without bound: this *fluctuation drift* is diffusive with
# effective diffusion coefficient $D = \tfrac12\,\mathrm{d}k_{xx}/\mathrm{d}t \to
# \nu\delta^2/(8\varepsilon^2)$ — the same number as the limit of $k_{xu}$, as the
# Green–Kubo relation $D = \int_0^\infty \langle u(0)u(\tau)\rangle\,\mathrm{d}\tau
# = k_{uu}(\infty)/(2\varepsilon)$ says.  Keeping the next term,
# $k_{xx} \approx \frac{\nu\delta^2}{4\varepsilon^2}\bigl(t - \frac{3}{4\varepsilon}\bigr)$:
# the leading asymptote of S0 overshoots by the constant $3\nu\delta^2/(16\varepsilon^3)$.
#
# This notebook checks `nhsde` against these formulas:
#
# 1. **Figure 1** — $k_{xx}(t)$, $k_{xu}(t)$, $k_{uu}(t)$ from a Monte-Carlo ensemble
#    (±2 standard errors) against the closed forms and the $t\to\infty$ asymptotes,
#    with the deviations in units of the standard error.
# 2. **Figure 2** — $\partial k_{xx}(t_1)/\partial\varepsilon$ and
#    $\partial k_{xx}(t_1)/\partial\nu$ by `jax.grad` *through the simulation*,
#    over a grid of $\varepsilon$, against `jax.grad` of the closed form.
# 3. **Figure 3** — the histogram of $u_x(t_1)$ against the Gaussian density
#    $\mathcal N(0, k_{uu}(t_1))$.
#
# Figures are written as PNG files into `$NHSDE_NOTEBOOK_OUT`
# (default `notebooks/_output`).

# %%
import os
import time

import jax
import jax.numpy as jnp
import matplotlib
import matplotlib.pyplot as plt
import matplotlib.ticker
import numpy as np

import nhsde
from nhsde import plot
from nhsde.scenes import BallOnVibratingPlane, ball_covariances

T_START = time.perf_counter()


def z_score(mc, se, exact):
    """(Monte Carlo − exact) / standard error; NaN where the standard error is 0."""
    mc, se, exact = (np.asarray(a, dtype=float) for a in (mc, se, exact))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(se > 0, (mc - exact) / se, np.nan)


print(
    f"nhsde {nhsde.__version__}, jax {jax.__version__} on {jax.devices()[0].platform}; figures -> {plot.figure_dir()}"
)

# %%
# The run's size: NHSDE_NOTEBOOK_SIZE=full (the default; the sizes the text quotes, the stored outputs)
# or small (the test suite's quick run: every cell and figure, with a quarter of the paths and 3 of
# the 6 gradient points, so the error bars are twice as wide).
SIZE = os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")
if SIZE not in ("full", "small"):
    raise ValueError(f"NHSDE_NOTEBOOK_SIZE={SIZE!r}; allowed: 'full', 'small'")
SMALL = SIZE == "small"
print(f"size: {SIZE}")

# %% [markdown]
# ## Parameters
#
# A homogeneous ball ($\kappa = 2/5$), moderate friction and unit noise
# intensity.  With $\varepsilon = 0.6$ the velocity variance relaxes on the time
# scale $1/(4\varepsilon) \approx 0.42$ and $k_{xu}$ on $1/(2\varepsilon) \approx 0.83$,
# so by $t_1 = 5$ both are stationary to better than 0.5 %, while the offset
# $3/(4\varepsilon) = 1.25$ of $k_{xx}$ is still clearly visible.  (Avoid
# $\varepsilon = 1/2$ for such plots: there the two limits $\nu\delta^2/(4\varepsilon)$
# and $\nu\delta^2/(8\varepsilon^2)$ coincide.)
#
# We integrate with SRA1, a stochastic Runge–Kutta method of strong order 1.5
# for additive noise; its weak error on these second moments is far below the
# Monte-Carlo error at $\Delta t = 0.005$.

# %%
EPS, NU, KAPPA = 0.6, 1.0, 0.4
T1, DT = 5.0, 0.005
SOLVER = "sra1"
N_PATHS = 1024 if SMALL else 4096

scene = BallOnVibratingPlane(eps=EPS, nu=NU, inertia_ratio=KAPPA)
system = scene.build()
DELTA = float(scene.params.delta)
print(f"state {system.layout.names}; delta = 1/(1+kappa) = {DELTA:.6f}")
print(
    f"eps = {EPS}, nu = {NU}: k_uu(inf) = {NU * DELTA**2 / (4 * EPS):.5f}, "
    f"k_xu(inf) = D = {NU * DELTA**2 / (8 * EPS**2):.5f}"
)

# %% [markdown]
# ## 1. Covariances from an ensemble
#
# 4096 paths from rest, the whole state saved at 26 equally spaced times.
# `ens.cov[n, i, j]` is the sample covariance of state components `i`, `j` at
# `ens.ts[n]`, and `ens.cov_se` its Monte-Carlo standard error.  We use the $x$
# axis; the $y$ axis is an independent copy (checked below).

# %%
t0 = time.perf_counter()
ens = nhsde.simulate(
    system,
    scene.initial_state(),
    jax.random.key(0),
    n_paths=N_PATHS,
    t1=T1,
    dt=DT,
    solver=SOLVER,
    save=nhsde.Save(n=26),
)
jax.block_until_ready(ens.cov)
print(f"{N_PATHS} paths x {round(T1 / DT)} steps in {time.perf_counter() - t0:.1f} s (incl. compilation)")

ts = np.asarray(ens.ts)
ix, iu = ens.names.index("x"), ens.names.index("u_x")
iy, iv = ens.names.index("y"), ens.names.index("u_y")
closed = dict(zip(("xx", "xu", "uu"), (np.asarray(k) for k in ball_covariances(ens.ts, EPS, NU, DELTA))))
pairs = {"xx": (ix, ix), "xu": (ix, iu), "uu": (iu, iu)}
mc = {k: np.asarray(ens.cov[:, i, j]) for k, (i, j) in pairs.items()}
se = {k: np.asarray(ens.cov_se[:, i, j]) for k, (i, j) in pairs.items()}
z = {k: z_score(mc[k], se[k], closed[k]) for k in pairs}
# For Gaussian data the sample covariance has Var(k_ij) ≈ (k_ii k_jj + k_ij²)/n: an
# independent check of the error bars themselves (last column ≈ 1).
se_gauss = {
    "xx": np.sqrt(2 * closed["xx"] ** 2 / N_PATHS),
    "xu": np.sqrt((closed["xx"] * closed["uu"] + closed["xu"] ** 2) / N_PATHS),
    "uu": np.sqrt(2 * closed["uu"] ** 2 / N_PATHS),
}

print(f"\n{'t':>5} {'k':>5} {'Monte Carlo':>12} {'± SE':>9} {'closed form':>12} {'(MC-CF)/SE':>11} {'SE/SE_gauss':>12}")
for n in range(5, len(ts), 5):
    for k in pairs:
        print(
            f"{ts[n]:5.2f} {'k_' + k:>5} {mc[k][n]:12.5f} {se[k][n]:9.5f} {closed[k][n]:12.5f} {z[k][n]:+11.2f} "
            f"{se[k][n] / se_gauss[k][n]:12.2f}"
        )
for k in pairs:
    zk = z[k][1:]
    print(
        f"k_{k}: max |z| over {zk.size} save times = {np.nanmax(np.abs(zk)):.2f}, rms z = {np.sqrt(np.nanmean(zk**2)):.2f}"
    )

# isotropy / independence of the two axes
k_yy, k_xy = np.asarray(ens.cov[-1, iy, iy]), np.asarray(ens.cov[-1, ix, iy])
print(
    f"t1: k_yy/k_xx = {k_yy / mc['xx'][-1]:.3f}, "
    f"k_yy vs closed form: {z_score(k_yy, ens.cov_se[-1, iy, iy], closed['xx'][-1]):+.2f} SE, "
    f"k_xy = {k_xy:+.4f} ({z_score(k_xy, ens.cov_se[-1, ix, iy], 0.0):+.2f} SE)"
)

# %% [markdown]
# Top row: ensemble estimates (markers, ±2 SE band) against the closed forms
# (solid) and the $t\to\infty$ asymptotes of S0 (dashed).  For $k_{xx}$ the dotted
# line adds the constant term, $\frac{\nu\delta^2}{4\varepsilon^2}(t - \frac{3}{4\varepsilon})$.
# Bottom row: the deviation in standard errors; about 95 % of the points should
# lie within ±2 (neighbouring times are strongly correlated, since they share
# paths).  The column `SE/SE_gauss` above compares `ens.cov_se` with the
# Gaussian-theory standard error $\sqrt{(k_{ii}k_{jj} + k_{ij}^2)/n}$ computed from
# the closed forms; it should be close to 1, otherwise the bands are too wide or
# too narrow.

# %%
tf = np.linspace(0.0, T1, 400)
closed_f = dict(zip(("xx", "xu", "uu"), (np.asarray(k) for k in ball_covariances(jnp.asarray(tf), EPS, NU, DELTA))))
g = NU * DELTA**2
asym = {
    "xx": g * tf / (4 * EPS**2),
    "xu": np.full_like(tf, g / (8 * EPS**2)),
    "uu": np.full_like(tf, g / (4 * EPS)),
}
labels = {
    "xx": (r"$k_{xx}(t)$", r"$\nu\delta^2 t/(4\varepsilon^2)$"),
    "xu": (r"$k_{xu}(t)$", r"$\nu\delta^2/(8\varepsilon^2)$"),
    "uu": (r"$k_{uu}(t)$", r"$\nu\delta^2/(4\varepsilon)$"),
}

fig, axes = plt.subplots(2, 3, figsize=(13, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1.3]})
for col, k in enumerate(pairs):
    ax = axes[0, col]
    ax.plot(tf, closed_f[k], "C0-", lw=1.5, label="closed form")
    ax.plot(tf, asym[k], "k--", lw=1, label=f"S0 asymptote {labels[k][1]}")
    if k == "xx":
        ax.plot(tf, g / (4 * EPS**2) * (tf - 3 / (4 * EPS)), "k:", lw=1, label=r"with $-3/(4\varepsilon)$ offset")
        ax.set_ylim(bottom=min(0.0, ax.get_ylim()[0]))
    ax.fill_between(ts, mc[k] - 2 * se[k], mc[k] + 2 * se[k], color="C1", alpha=0.3, lw=0, label="MC ±2 SE")
    ax.plot(ts, mc[k], "C1o", ms=3.5, label=f"MC, {N_PATHS} paths")
    ax.set_title(labels[k][0])
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    axz = axes[1, col]
    axz.axhspan(-2, 2, color="0.9")
    axz.axhline(0, color="k", lw=0.8)
    axz.plot(ts, z[k], "C1o-", ms=3, lw=0.8)
    axz.set_xlabel("t")
    axz.set_ylim(-4, 4)
    axz.grid(alpha=0.3)
axes[1, 0].set_ylabel("(MC − exact) / SE")
fig.suptitle(
    rf"Ball on a vibrating plane: $\varepsilon={EPS}$, $\nu={NU}$, $\delta={DELTA:.4f}$, "
    rf"{SOLVER}, $\Delta t={DT}$"
)
fig.tight_layout()
_ = plot.save(fig, "ball_covariances.png")

# %% [markdown]
# ## 2. Sensitivities by differentiating through the simulation
#
# The Brownian increments are generated from the key alone, so they do not depend
# on $(\varepsilon, \nu)$: differentiating the sample covariance through the
# solver (`jax.grad` of `simulate`, reverse mode) is the *pathwise* estimator of
# $\partial k_{xx}/\partial\theta$.  The scene is built *inside* the
# differentiated function so that `eps` and `nu` are traced leaves.
#
# To attach a standard error to each gradient we `vmap` over 16 independent keys
# (16 batches of 256 paths) and take the mean and standard error over batches.
# Both axes are independent copies of (3.1), so each batch uses
# $\tfrac12(k_{xx} + k_{yy})$ at $t_1$, which halves the variance for free.  Only
# the position is saved, at $t_0$ and $t_1$.
#
# What to expect: $k_{xx}$ is linear in $\nu$, so $\partial k_{xx}/\partial\nu = k_{xx}/\nu$
# exactly; the $\varepsilon$-derivative is the non-trivial check.  From the
# large-$t$ form, $\partial k_{xx}/\partial\varepsilon \approx
# -\frac{\nu\delta^2 t}{2\varepsilon^3} + \frac{9\nu\delta^2}{16\varepsilon^4}$
# (dotted).
#
# The same 16 keys are used at every $\varepsilon$ (common random numbers), so the
# Monte-Carlo errors are strongly correlated along the grid: expect a smooth
# curve slightly offset from the exact one rather than independent scatter.  And
# since every path's $x$ is proportional to $\sqrt\nu$, the pathwise
# $\partial k_{xx}/\partial\nu$ equals $k_{xx}/\nu$ path by path: its deviations
# in SE units are those of $k_{xx}$ itself (printed last).

# %%
N_BATCH, BATCH_PATHS = (8, 128) if SMALL else (16, 256)
EPS_GRID = np.geomspace(0.3, 3.0, 3 if SMALL else 6)
NU_G = NU


def kxx_t1(eps, nu, key):
    """½(k_xx + k_yy)(t1) from BATCH_PATHS paths; differentiable in eps and nu."""
    sc = BallOnVibratingPlane(eps=eps, nu=nu, inertia_ratio=KAPPA)
    e = nhsde.simulate(
        sc.build(),
        sc.initial_state(),
        key,
        n_paths=BATCH_PATHS,
        t1=T1,
        dt=DT,
        solver=SOLVER,
        save=nhsde.Save(names=("x", "y"), n=2),
    )
    return 0.5 * (e.cov[-1, 0, 0] + e.cov[-1, 1, 1])


@jax.jit
def mc_value_and_grad(eps, nu, keys):
    vg = jax.value_and_grad(kxx_t1, argnums=(0, 1))
    k, (d_eps, d_nu) = jax.vmap(vg, in_axes=(None, None, 0))(eps, nu, keys)
    return k, d_eps, d_nu


def kxx_closed(eps, nu):
    return ball_covariances(T1, eps, nu, DELTA)[0]


closed_grad = jax.jit(jax.vmap(jax.grad(kxx_closed, argnums=(0, 1)), in_axes=(0, None)))


def mean_se(a):
    a = np.asarray(a, dtype=float)
    return a.mean(), a.std(ddof=1) / np.sqrt(a.size)


keys = jax.random.split(jax.random.key(1), N_BATCH)
rows = []
t0 = time.perf_counter()
for eps in EPS_GRID:
    k, d_eps, d_nu = mc_value_and_grad(jnp.float32(eps), jnp.float32(NU_G), keys)
    rows.append((eps, *mean_se(k), *mean_se(d_eps), *mean_se(d_nu)))
rows = np.array(rows)
print(
    f"{len(EPS_GRID)} gradients x {N_BATCH * BATCH_PATHS} paths in {time.perf_counter() - t0:.1f} s (incl. compilation)"
)
ex_deps, ex_dnu = (np.asarray(a) for a in closed_grad(jnp.asarray(EPS_GRID), NU_G))
ex_k = np.asarray(jax.vmap(kxx_closed, in_axes=(0, None))(jnp.asarray(EPS_GRID), NU_G))

print(f"\nat t1 = {T1}, nu = {NU_G}:")
print(
    f"{'eps':>6} | {'dk/deps MC':>11} {'± SE':>8} {'exact':>11} {'z':>6} | {'dk/dnu MC':>10} {'± SE':>8} {'exact':>10} {'z':>6}"
)
for (eps, k, k_se, de, de_se, dn, dn_se), e_de, e_dn in zip(rows, ex_deps, ex_dnu):
    print(
        f"{eps:6.3f} | {de:11.5f} {de_se:8.5f} {e_de:11.5f} {z_score(de, de_se, e_de):+6.2f} | "
        f"{dn:10.5f} {dn_se:8.5f} {e_dn:10.5f} {z_score(dn, dn_se, e_dn):+6.2f}"
    )
print("k_xx itself: z = " + ", ".join(f"{z_score(r[1], r[2], e):+.2f}" for r, e in zip(rows, ex_k)))

# %% [markdown]
# Left: $-\partial k_{xx}/\partial\varepsilon$, right: $\partial k_{xx}/\partial\nu$,
# both at $t_1$ on log–log axes (the $\varepsilon$-derivative is negative: more
# friction, less spreading).  Markers: `jax.grad` through 4096 simulated paths
# (±2 SE error bars, mostly smaller than the markers); solid: `jax.grad` of the
# closed form; dotted: the large-$t$ approximation.  The bottom panels show the
# deviations of the (signed) derivatives in standard errors, as in the table.

# %%
eps_f = np.geomspace(EPS_GRID[0] * 0.9, EPS_GRID[-1] * 1.1, 200)
f_deps, f_dnu = (np.asarray(a) for a in closed_grad(jnp.asarray(eps_f), NU_G))
asym_deps = -NU_G * DELTA**2 * T1 / (2 * eps_f**3) + 9 * NU_G * DELTA**2 / (16 * eps_f**4)
asym_dnu = DELTA**2 / (4 * eps_f**2) * (T1 - 3 / (4 * eps_f))

fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1.3]})
# (title, sign shown, closed-form curve, large-t curve, MC mean, MC SE, exact at the grid)
panels = [
    (r"$-\partial k_{xx}(t_1)/\partial\varepsilon$", -1, f_deps, asym_deps, rows[:, 3], rows[:, 4], ex_deps),
    (r"$\partial k_{xx}(t_1)/\partial\nu$", 1, f_dnu, asym_dnu, rows[:, 5], rows[:, 6], ex_dnu),
]
for col, (title, sign, curve, approx, mc_g, mc_se, exact) in enumerate(panels):
    ax = axes[0, col]
    ax.plot(eps_f, sign * curve, "C0-", label="jax.grad of closed form")
    ax.plot(eps_f, sign * approx, "k:", lw=1, label="large-$t$ approximation")
    ax.errorbar(EPS_GRID, sign * mc_g, yerr=2 * mc_se, fmt="C1o", ms=5, capsize=3, label="jax.grad through simulate")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    axz = axes[1, col]
    axz.axhspan(-2, 2, color="0.9")
    axz.axhline(0, color="k", lw=0.8)
    axz.plot(EPS_GRID, z_score(mc_g, mc_se, exact), "C1o-", ms=4, lw=0.8)  # signed derivative, as printed
    axz.set_ylim(-4, 4)
    axz.set_xlabel(r"$\varepsilon$")
    axz.set_xticks([0.3, 0.5, 1.0, 2.0, 3.0])
    axz.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    axz.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    axz.grid(alpha=0.3, which="both")
axes[1, 0].set_ylabel(r"(MC − exact) / SE of $\partial k_{xx}$")
fig.suptitle(rf"Sensitivities of $k_{{xx}}$ at $t_1={T1}$, $\nu={NU_G}$, $\delta={DELTA:.4f}$")
fig.tight_layout()
_ = plot.save(fig, "ball_gradients.png")

# %% [markdown]
# ## 3. The distribution of $u_x(t_1)$
#
# The model is linear with additive noise, so $u_x(t)$ is exactly Gaussian,
# $\mathcal N(0, k_{uu}(t))$.  A small run keeps the per-path values
# (`Save(paths=True)`); we compare the histogram with the density and report the
# sample variance, the excess kurtosis (0 for a Gaussian, SE $\approx\sqrt{24/n}$)
# and the Kolmogorov–Smirnov distance (5 % critical value $\approx 1.36/\sqrt n$).
# With the per-path values at hand we also recompute the standard error of the
# variance directly, $\mathrm{sd}\bigl((u-\bar u)^2\bigr)/\sqrt n$, as a check of
# `ens.cov_se` (for a Gaussian it is $\approx k_{uu}\sqrt{2/n}$).

# %%
N_HIST = 1024 if SMALL else 4096
ens_u = nhsde.simulate(
    system,
    scene.initial_state(),
    jax.random.key(2),
    n_paths=N_HIST,
    t1=T1,
    dt=DT,
    solver=SOLVER,
    save=nhsde.Save(names=("u_x",), n=2, paths=True),
)
u = np.asarray(ens_u.paths[:, -1, 0], dtype=float)
k_uu_t1 = float(ball_covariances(T1, EPS, NU, DELTA)[2])

var_u = u.var(ddof=1)
var_se = float(ens_u.cov_se[-1, 0, 0])
var_se_direct = np.std((u - u.mean()) ** 2) / np.sqrt(N_HIST)
kurt = np.mean((u - u.mean()) ** 4) / u.var() ** 2 - 3.0
u_sorted = np.sort(u)
cdf = np.asarray(jax.scipy.stats.norm.cdf(u_sorted, scale=np.sqrt(k_uu_t1)))
ecdf_hi = np.arange(1, N_HIST + 1) / N_HIST
ks = max(np.max(ecdf_hi - cdf), np.max(cdf - (ecdf_hi - 1 / N_HIST)))
print(f"u_x(t1), {N_HIST} paths:")
print(f"  mean      {u.mean():+.5f}  (SE {float(ens_u.mean_se[-1, 0]):.5f}; exact 0)")
print(
    f"  variance  {var_u:.5f} ± {var_se:.5f}  vs k_uu(t1) = {k_uu_t1:.5f}  "
    f"ratio {var_u / k_uu_t1:.4f}, {z_score(var_u, var_se, k_uu_t1):+.2f} SE"
)
print(
    f"  SE of the variance: ens.cov_se {var_se:.5f}, direct from the paths {var_se_direct:.5f}, "
    f"Gaussian k_uu*sqrt(2/n) {k_uu_t1 * np.sqrt(2 / N_HIST):.5f}  (ratio ens/direct {var_se / var_se_direct:.3f})"
)
print(f"  excess kurtosis {kurt:+.3f}  (SE ~ {np.sqrt(24 / N_HIST):.3f})")
print(f"  KS distance {ks:.4f}  (5% critical value ~ {1.36 / np.sqrt(N_HIST):.4f})")

# %%
fig, ax = plt.subplots(figsize=(6.5, 4))
ax.hist(u, bins=60, density=True, color="C1", alpha=0.6, label=f"$u_x(t_1)$, {N_HIST} paths")
grid_u = np.linspace(-4.5, 4.5, 400) * np.sqrt(k_uu_t1)
ax.plot(
    grid_u,
    np.exp(-(grid_u**2) / (2 * k_uu_t1)) / np.sqrt(2 * np.pi * k_uu_t1),
    "C0-",
    lw=2,
    label=rf"$\mathcal{{N}}(0,\,k_{{uu}}(t_1) = {k_uu_t1:.4f})$",
)
ax.set_xlabel(r"$u_x$")
ax.set_ylabel("density")
ax.set_title(rf"Velocity at $t_1 = {T1}$ ($\varepsilon={EPS}$, $\nu={NU}$)")
ax.legend(fontsize=8)
ax.grid(alpha=0.3)
fig.tight_layout()
_ = plot.save(fig, "ball_u_histogram.png")

# %%
print(f"notebook finished in {time.perf_counter() - T_START:.1f} s")
