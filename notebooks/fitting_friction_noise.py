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
# # Fitting friction and noise from data
#
# An experiment gives trajectories; the model has a friction rate $\varepsilon$
# and a noise intensity $\nu$.  `nhsde.fit` estimates them — or any other
# parameter leaf — by comparing the *statistics* of the data with those of the
# model: the means $m(t)$ and covariances $K(t)$ of the observed components at
# the observation times, stacked into one vector
#
# $$
# s = \bigl[m(t_1), K(t_1)_{\triangle}, m(t_2), K(t_2)_{\triangle}, \dots\bigr].
# $$
#
# For $n$ observed paths, $s_{\text{obs}}$ is asymptotically Gaussian about
# $s(\theta)$ with a covariance $\Sigma$ that the paths themselves estimate
# (through their influence functions, cross-time correlations included).  The
# estimate maximises that Gaussian likelihood,
#
# $$
# \hat\theta = \arg\min_\theta \tfrac12\,
#   \bigl(s_{\text{obs}} - s(\theta)\bigr)^{\mathsf T}\Sigma^{-1}\bigl(s_{\text{obs}} - s(\theta)\bigr),
# $$
#
# minimised with optax's L-BFGS in $\log\theta$.  The model statistics $s(\theta)$
# come from one of three routes:
#
# | model | $s(\theta)$ from | noise of the model |
# |---|---|---|
# | `fit.ClosedForm` | a closed form (here S0 (3.1) for the ball) | none |
# | `fit.MomentEquations` | the normal-approximation moment equations (S0 §6) | none; exact for linear systems, biased otherwise |
# | `fit.Simulated` | `nhsde.simulate` with a fixed key, differentiated by JAX | Monte-Carlo, $\approx\Sigma\, n_{\text{obs}}/n_{\text{sim}}$ |
#
# The standard errors come from the Fisher information $H = G^{\mathsf T}\Sigma^{-1}G$,
# $G = \partial s/\partial\theta$, plus the model's own Monte-Carlo noise:
# $\operatorname{Cov}\hat\theta = H^{-1} + H^{-1}G^{\mathsf T}\Sigma^{-1}\Sigma_{\text{model}}\Sigma^{-1}GH^{-1}$.
# The residual $\chi^2$ on $\dim s - \dim\theta$ degrees of freedom says whether the
# model fits at all.
#
# This notebook
#
# 1. fits the ball on the vibrating plane three ways and draws the fitted
#    covariances over the data (**Figure 1**) and the likelihood landscape with the
#    optimizer's path and the confidence ellipses (**Figure 2**);
# 2. checks that the reported standard errors are honest, over 40 independent
#    data sets (**Figure 3**);
# 3. fits the nonlinear noisy Chaplygin sleigh through the simulator and through
#    the moment equations (**Figure 4**).
#
# Figures are written as PNG files into `$NHSDE_NOTEBOOK_OUT` (default
# `notebooks/_output`).

# %%
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from scipy import stats

import nhsde
from nhsde import fit, plot
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances

T_START = time.perf_counter()


def z_scores(result, truth):
    return (result.values - np.asarray(truth)) / result.se


print(f"nhsde {nhsde.__version__}, jax {jax.__version__}; figures -> {plot.figure_dir()}")

# %%
# The run's size: NHSDE_NOTEBOOK_SIZE=full (the default; the sizes the text quotes, the stored outputs)
# or small (the test suite's quick run: every cell and figure with a quarter of the observed and
# simulated paths and 10 data sets of 256 paths for the calibration, so the error bars are twice as wide).
SIZE = os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")
if SIZE not in ("full", "small"):
    raise ValueError(f"NHSDE_NOTEBOOK_SIZE={SIZE!r}; allowed: 'full', 'small'")
SMALL = SIZE == "small"
print(f"size: {SIZE}")

# %% [markdown]
# ## 1. The ball: synthetic data
#
# $2048$ paths of the ball from rest with $\varepsilon = 0.8$, $\nu = 1.5$
# (SRA1, $\Delta t = 0.02$, whose weak error here is far below the Monte-Carlo
# error), observed in $(x, u_x)$ at $t = 0.5, 1, \dots, 4$: $8 \times 5 = 40$
# statistics.  The initial state is not random, so $t = 0$ is left out.

# %%
EPS, NU = 0.8, 1.5
NAMES = ("x", "u_x")
N_OBS, N_SIM = (512, 1024) if SMALL else (2048, 4096)  # observed paths, paths of the simulated model
DELTA = float(BallOnVibratingPlane().params.delta)

ball_true = BallOnVibratingPlane(eps=EPS, nu=NU).build()
data = nhsde.simulate(
    ball_true,
    jnp.zeros(4),
    jax.random.key(1),
    n_paths=N_OBS,
    t1=4.0,
    dt=0.02,
    solver="sra1",
    save=nhsde.Save(names=NAMES, n=9, paths=True),
)
observed = fit.Observations.from_paths(data.ts[1:], data.paths[:, 1:], NAMES)
print(f"{observed.size} statistics from {observed.n_paths} paths at t = {observed.ts.tolist()}")


def ball_closed_form(p, ts):
    """(mean, cov) of (x, u_x) from rest, S0 (3.1)."""
    kxx, kxu, kuu = ball_covariances(ts, p.eps, p.nu, p.delta)
    cov = jnp.stack([jnp.stack([kxx, kxu], -1), jnp.stack([kxu, kuu], -1)], -2)
    return jnp.zeros(ts.shape + (2,), ts.dtype), cov


# %% [markdown]
# ## 2. Three fits
#
# All start far off, at $\varepsilon = 0.3$, $\nu = 0.5$.  The simulated model
# uses its own key (4096 paths, the data's solver and step); with the data's key
# it would reproduce the data's noise and the fit would be spuriously exact.

# %%
start = BallOnVibratingPlane(eps=0.3, nu=0.5).build()
fits = {}
for label, model in [
    ("closed form", fit.ClosedForm(ball_closed_form)),
    ("simulator", fit.Simulated(jnp.zeros(4), jax.random.key(2), n_paths=N_SIM, steps=0.02, solver="sra1")),
]:
    t0 = time.perf_counter()
    fits[label] = fit.estimate(start, observed, model)
    print(f"\n--- {label} ({time.perf_counter() - t0:.1f} s incl. compilation)\n{fits[label]}")
    print(f"(estimate − truth)/SE = {np.array2string(z_scores(fits[label], (EPS, NU)), precision=2)}")
ratio = fits["simulator"].se / fits["closed form"].se
print(
    f"\nSE(simulator)/SE(closed form) = {np.array2string(ratio, precision=3)}; "
    f"expected about sqrt(1 + n_obs/n_sim) = {np.sqrt(1 + N_OBS / N_SIM):.3f}"
)

# %% [markdown]
# **Figure 1.** The observed covariances (markers, ±2 SE bands) with the closed
# forms at the estimates of the closed-form fit (solid) and at the truth (dashed).

# %%
tf = jnp.linspace(0.0, 4.0, 200)
est = dict(zip(("eps", "nu"), fits["closed form"].values))
k_fit = [np.asarray(k) for k in ball_covariances(tf, est["eps"], est["nu"], DELTA)]
k_true = [np.asarray(k) for k in ball_covariances(tf, EPS, NU, DELTA)]
ts_obs = observed.ts
se_cov = np.sqrt(np.diag(observed.covariance)).reshape(len(ts_obs), -1)[:, 2:]  # after the 2 means: xx, xu, uu

fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
for col, (label, (i, j)) in enumerate({"k_xx": (0, 0), "k_xu": (0, 1), "k_uu": (1, 1)}.items()):
    ax = axes[col]
    plot.band(
        ax,
        ts_obs,
        observed.cov[:, i, j],
        se_cov[:, col],
        label=f"data, {N_OBS} paths",
        theory=k_fit[col],
        theory_ts=tf,
        theory_label=rf"fit: $\hat\varepsilon={est['eps']:.3f}$, $\hat\nu={est['nu']:.3f}$",
    )
    ax.plot(tf, k_true[col], "k--", lw=0.8, label=rf"truth: $\varepsilon={EPS}$, $\nu={NU}$")
    ax.set_title(f"${label[0]}_{{{label[2:]}}}(t)$")
    ax.set_xlabel("t")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
fig.suptitle("Ball on a vibrating plane: observed covariances and the fitted closed form")
fig.tight_layout()
_ = plot.save(fig, "fitting_ball_covariances.png")

# %% [markdown]
# **Figure 2.** The $\chi^2$ landscape of the closed-form model over
# $(\varepsilon, \nu)$, the L-BFGS path from the start (`FitResult.history`), and
# the 2-SE confidence ellipses of both fits.  The ellipses are tilted: a larger
# $\nu$ and a larger $\varepsilon$ give similar stationary velocity variances
# $\nu\delta^2/(4\varepsilon)$, so the two estimates are positively correlated; the
# transient of the covariances is what separates them.

# %%
s_obs = observed.statistics()
sigma_inv = np.linalg.inv(observed.covariance)


@jax.jit
def chi2_grid(eps, nu):
    def one(e, n):
        p = ball_true.params.replace(eps=e, nu=n)
        r = fit.statistic_vector(*ball_closed_form(p, jnp.asarray(ts_obs))) - s_obs
        return r @ sigma_inv @ r

    return jax.vmap(jax.vmap(one, in_axes=(0, None)), in_axes=(None, 0))(eps, nu)


eg = np.linspace(0.25, 1.1, 120)
ng = np.linspace(0.4, 2.0, 120)
chi2 = np.asarray(chi2_grid(jnp.asarray(eg), jnp.asarray(ng)))
fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
ax = axes[0]
cs = ax.contourf(eg, ng, np.log10(chi2), levels=30, cmap="viridis")
fig.colorbar(cs, ax=ax, label=r"$\log_{10}\chi^2$")
hist = fits["closed form"].history
ax.plot(hist[:, 1], hist[:, 2], "w.-", lw=1, ms=6, label="L-BFGS path")
ax.plot(EPS, NU, "r*", ms=12, label="truth")
ax.set(xlabel=r"$\varepsilon$", ylabel=r"$\nu$", title="closed-form model: $\\chi^2$ and the optimizer's path")
ax.legend(fontsize=8, loc="upper left")
ax = axes[1]
for k, (label, res) in enumerate(fits.items()):
    plot.confidence_ellipse(ax, res.values, res.cov, n_sigma=2.0, color=f"C{k}", lw=1.5, label=f"{label}: 2 SE")
    ax.plot(*res.values, "o", color=f"C{k}")
ax.plot(EPS, NU, "r*", ms=12, label="truth")
ax.set(xlabel=r"$\varepsilon$", ylabel=r"$\nu$", title="estimates and their 2-SE ellipses")
ax.grid(alpha=0.3)
ax.legend(fontsize=8)
fig.tight_layout()
_ = plot.save(fig, "fitting_ball_landscape.png")

# %% [markdown]
# ## 3. Are the error bars honest?
#
# One estimate within 2 SE of the truth says little.  Here 40 independent data
# sets of 1024 paths are each fitted (closed-form model: fast).  If the reported
# covariances are right, the standardised errors $(\hat\theta - \theta)/\mathrm{SE}$
# are standard normal and $\sum (\hat\theta-\theta)^{\mathsf T}\operatorname{Cov}^{-1}(\hat\theta-\theta)$
# is $\chi^2$ with $2 \times 40$ degrees of freedom; the fits' own $\chi^2$ values
# should average about their degrees of freedom.

# %%
N_SETS, N_EACH = (10, 256) if SMALL else (40, 1024)
many = nhsde.simulate(
    ball_true,
    jnp.zeros(4),
    jax.random.key(3),
    n_paths=N_SETS * N_EACH,
    t1=4.0,
    dt=0.02,
    solver="sra1",
    save=nhsde.Save(names=NAMES, n=9, paths=True),
)
zs, maha, chi2s = [], 0.0, []
t0 = time.perf_counter()
for s in range(N_SETS):
    obs_s = fit.Observations.from_paths(many.ts[1:], many.paths[s * N_EACH : (s + 1) * N_EACH, 1:], NAMES)
    res = fit.estimate(start, obs_s, fit.ClosedForm(ball_closed_form))
    d = res.values - np.array([EPS, NU])
    zs.append(d / res.se)
    maha += d @ np.linalg.solve(res.cov, d)
    chi2s.append(res.chi2)
zs = np.array(zs)
lo, hi = stats.chi2.ppf([0.025, 0.975], 2 * N_SETS)
print(f"{N_SETS} fits in {time.perf_counter() - t0:.1f} s")
print(f"sum of Mahalanobis distances {maha:.1f}; 95 % range of chi2({2 * N_SETS}): [{lo:.1f}, {hi:.1f}]")
print(
    f"z(eps): mean {zs[:, 0].mean():+.2f}, sd {zs[:, 0].std(ddof=1):.2f};  "
    f"z(nu): mean {zs[:, 1].mean():+.2f}, sd {zs[:, 1].std(ddof=1):.2f}  (ideal 0, 1)"
)
print(f"fit chi2: mean {np.mean(chi2s):.1f} on {res.dof} degrees of freedom")

# %%
fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
for k, name in enumerate((r"$\varepsilon$", r"$\nu$")):
    plot.density(
        axes[k], zs[:, k], stats.norm.pdf, bins=8, range=(-3, 3), label=f"{N_SETS} fits", theory_label="N(0, 1)"
    )
    axes[k].set(title=f"standardised error of {name}", xlabel=r"$(\hat\theta-\theta)/\mathrm{SE}$")
plot.density(
    axes[2],
    np.array(chi2s),
    stats.chi2(res.dof).pdf,
    bins=8,
    label=f"{N_SETS} fits",
    theory_label=rf"$\chi^2_{{{res.dof}}}$",
)
axes[2].set(title="goodness of fit", xlabel=r"$\chi^2$ of each fit")
fig.suptitle("Calibration of the reported standard errors (grey: ±2 SE of a histogram of that many fits)")
fig.tight_layout()
_ = plot.save(fig, "fitting_calibration.png")

# %% [markdown]
# ## 4. A nonlinear scene: the noisy Chaplygin sleigh
#
# The sleigh's velocities obey
# $\dot v = a\omega^2 - 2\varepsilon v + V_1/\sqrt m$,
# $\dot\omega = -(ma/J)\,v\omega - 2\varepsilon\omega + V_2/\sqrt J$:
# the knife edge couples them quadratically, so there is no closed form for
# their covariances.  2048 paths from $(v, \omega) = (1, 0.5)$ with
# $\varepsilon = 0.5$, $\nu = 0.8$ are observed in $(v, \omega)$ at
# $t = 0.5, \dots, 3$.  We fit through the simulator (Euler–Maruyama at the
# data's step, 4096 paths, another key) and through the moment equations of the
# normal approximation, whose Gaussian closure is not exact here.

# %%
S_EPS, S_NU = 0.5, 0.8
Y0 = jnp.array([1.0, 0.5])
sleigh_true = ChaplyginSleigh(eps=S_EPS, nu=S_NU, drift=False).build()
s_data = nhsde.simulate(
    sleigh_true, Y0, jax.random.key(4), n_paths=N_OBS, t1=3.0, dt=0.02, save=nhsde.Save(n=7, paths=True)
)
s_obs = fit.Observations.from_paths(s_data.ts[1:], s_data.paths[:, 1:], ("v", "omega"))
s_start = ChaplyginSleigh(eps=0.2, nu=0.3, drift=False).build()
s_fits = {}
for label, model in [
    ("simulator", fit.Simulated(Y0, jax.random.key(5), n_paths=N_SIM, steps=0.02)),
    ("moment equations", fit.MomentEquations(Y0, dt=0.05)),
]:
    t0 = time.perf_counter()
    s_fits[label] = fit.estimate(s_start, s_obs, model)
    print(f"\n--- sleigh, {label} ({time.perf_counter() - t0:.1f} s incl. compilation)\n{s_fits[label]}")
    print(
        f"(estimate − truth)/SE = {np.array2string(z_scores(s_fits[label], (S_EPS, S_NU)), precision=2)}, "
        f"chi2 p-value {stats.chi2.sf(s_fits[label].chi2, s_fits[label].dof):.3g}"
    )

# %% [markdown]
# **Figure 4.** Observed means and variances of $v$ and $\omega$ (±2 SE) with
# the model at each estimate: 16384 simulated paths (solid) and the moment
# equations (dotted).  The closure's bias shows as a misfit that the data can
# resolve — compare the two $\chi^2$ values above.

# %%
fine = nhsde.Save(n=31)
curves = {}
for label, res in s_fits.items():
    system = sleigh_true.replace_params(**res.params)
    curves[label] = (
        nhsde.simulate(system, Y0, jax.random.key(6), n_paths=4 * N_SIM, t1=3.0, dt=0.02, save=fine),
        nhsde.statistics.normal_approximation(system, Y0, t1=3.0, dt=0.05, save=fine),
    )
se = np.sqrt(np.diag(s_obs.covariance)).reshape(len(s_obs.ts), -1)  # v, ω, K_vv, K_vω, K_ωω
panels = [
    ("mean of v", s_obs.mean[:, 0], se[:, 0], lambda e: e.mean[:, 0]),
    ("variance of v", s_obs.cov[:, 0, 0], se[:, 2], lambda e: e.cov[:, 0, 0]),
    ("variance of ω", s_obs.cov[:, 1, 1], se[:, 4], lambda e: e.cov[:, 1, 1]),
]
fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
for ax, (title, value, err, pick) in zip(axes, panels):
    plot.band(ax, s_obs.ts, value, err, label=f"data, {N_OBS} paths")
    for k, (label, (sim, mom)) in enumerate(curves.items()):
        ax.plot(sim.ts, pick(sim), "-", color=f"C{k + 2}", lw=1.2, label=f"simulated at the {label} estimate")
        ax.plot(mom.ts, pick(mom), ":", color=f"C{k + 2}", lw=1.2, label=f"moment eqs at the {label} estimate")
    ax.set(title=title, xlabel="t")
    ax.grid(alpha=0.3)
axes[0].legend(fontsize=7)
fig.suptitle(r"Noisy Chaplygin sleigh: data and fitted models ($\varepsilon=0.5$, $\nu=0.8$ true)")
fig.tight_layout()
_ = plot.save(fig, "fitting_sleigh.png")

# %%
print(f"\nnotebook ran in {time.perf_counter() - T_START:.0f} s")
