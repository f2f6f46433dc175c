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
# # Speed against accuracy: work-precision diagrams
#
# Which solver and step should a study use?  For each solver of `nhsde.SOLVERS`
# and each step $\Delta t$, `work_precision` (the function behind
# `benchmarks/work_precision.py`) measures
#
# - the **strong error** at $t_1$: the RMS over paths of
#   $|Z_{\Delta t}(t_1) - Z_{\text{ref}}(t_1)|$ against a fine reference solve on
#   *the same Brownian path* (`brownian_dt` shared);
# - the **weak error** of a statistic against its exact value, with the
#   Monte-Carlo standard error $\sqrt{\operatorname{Var}/N}$ of that statistic —
#   a weak error below it is not resolved;
# - the wall time of the compiled run.
#
# Two scenes with exact weak references:
#
# | scene | statistic | exact value |
# |---|---|---|
# | ball on the vibrating plane (linear, additive noise) | $k_{xx}(t_1)$ | the closed form of S0 (3.1) |
# | noisy Chaplygin sleigh (nonlinear) | $\mathbb E[H](t_1)$ | $H_0 e^{-4\varepsilon t_1} + \nu(1 - e^{-4\varepsilon t_1})/(4\varepsilon)$ (Itô's formula) |
#
# The run here is small (8192 paths, three solvers, three steps);
# `python benchmarks/work_precision.py` runs the full study.  Figures go to
# `$NHSDE_NOTEBOOK_OUT` (default `notebooks/_output`).

# %%
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import nhsde
from nhsde import cheapest_setting, plot, work_precision
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances

T_START = time.perf_counter()


print(
    f"nhsde {nhsde.__version__}, jax {jax.__version__}; solvers {list(nhsde.SOLVERS)}; figures -> {plot.figure_dir()}"
)

# %%
# The run's size: NHSDE_NOTEBOOK_SIZE=full (the default; the sizes the text quotes, the stored outputs)
# or small (the test suite's quick run: every cell and the figure for two solvers at two steps on 1024
# paths; each solver and step is compiled anew, which is most of this notebook's time).
SIZE = os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")
if SIZE not in ("full", "small"):
    raise ValueError(f"NHSDE_NOTEBOOK_SIZE={SIZE!r}; allowed: 'full', 'small'")
SMALL = SIZE == "small"
print(f"size: {SIZE}")

# %% [markdown]
# ## The two cases
#
# The ball from rest with $\varepsilon = \nu = 1$, $t_1 = 2$, statistic
# $k_{xx}(t_1)$.  The sleigh with $\varepsilon = 0.5$, $\nu = 1$ from
# $v = 1$, $\omega = 0.5$, $t_1 = 2$, statistic $\mathbb E[H](t_1)$ through the
# scene's `energy` observable.  SRA1 needs additive noise, which both have.

# %%
N_PATHS = 1024 if SMALL else 8192
DTS = [2.0**-k for k in ((3, 4) if SMALL else (3, 4, 5))]
# For additive noise (both scenes) Milstein and Euler–Heun take exactly the Euler–Maruyama
# step, so they are left out here; the full benchmark measures them too.
SOLVERS = ["euler", "sra1"] if SMALL else ["euler", "sra1", "exponential"]

ball = BallOnVibratingPlane(eps=1.0, nu=1.0)
sleigh = ChaplyginSleigh(eps=0.5, nu=1.0)
sp = sleigh.params
J = float(sp.inertia + sp.mass * sp.offset**2)
H0 = 0.5 * (float(sp.mass) * 1.0 + J * 0.25)
CASES = {
    "ball": {
        "system": ball.build(),
        "y0": ball.initial_state().astype(jnp.float64),
        "t1": 2.0,
        "statistic": lambda ens: (ens.cov[-1, 0, 0], ens.cov_se[-1, 0, 0]),
        "reference": float(ball_covariances(jnp.float64(2.0), 1.0, 1.0, float(ball.params.delta))[0]),
        "save": nhsde.Save(names=("x",), n=2),
        "label": r"$k_{xx}(t_1)$",
    },
    "sleigh": {
        "system": sleigh.build(),
        "y0": sleigh.initial_state().astype(jnp.float64).at[4].set(0.5),
        "t1": 2.0,
        "statistic": lambda ens: (ens.mean[-1, 0], ens.mean_se[-1, 0]),
        "reference": H0 * np.exp(-4 * 0.5 * 2.0) + 1.0 * (1 - np.exp(-4 * 0.5 * 2.0)) / (4 * 0.5),
        "save": nhsde.Save(names=("energy",), n=2),
        "label": r"$\mathbb{E}[H](t_1)$",
    },
}

# %% [markdown]
# ## Measurements

# %%
rows = {}
for name, case in CASES.items():
    t0 = time.perf_counter()
    rows[name] = work_precision(
        case["system"],
        case["y0"],
        jax.random.key(0),
        t1=case["t1"],
        solvers=SOLVERS,
        dts=DTS,
        statistic=case["statistic"],
        reference=case["reference"],
        n_paths=N_PATHS,
        save=case["save"],
    )
    print(f"\n[{name}] exact {case['reference']:.6g}; measured in {time.perf_counter() - t0:.0f} s")
    print(f"{'solver':<12}{'dt':>8}{'strong':>11}{'weak':>11}{'MC se':>10}{'ms':>9}")
    for r in rows[name]:
        print(
            f"{r.solver:<12}{r.dt:>8.4g}{r.strong_error:>11.3g}{r.weak_error:>11.3g}{r.weak_se:>10.2g}"
            f"{1e3 * r.seconds:>9.2f}"
        )

# %% [markdown]
# **Figure 1.** Strong error (top) and weak error (bottom) against wall time,
# one line per solver over the three steps.  Grey: the Monte-Carlo error of the
# weak statistic — below it the weak error is noise, not bias.  The strong
# orders show as slopes: Euler–Maruyama and the exponential integrator converge
# with order 1 (additive noise), SRA1 with at least its order 1.5 (about 2 on
# these two problems), on the nonlinear sleigh as on the linear ball.  All runs
# share one key, so their weak errors share one Monte-Carlo error and differ
# by their bias alone: Euler's shrinks with the step on the sleigh, SRA1's is
# within about two Monte-Carlo errors already at the coarsest step.

# %%
fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharex="col")
for col, (name, rs) in enumerate(rows.items()):
    for k, solver in enumerate(SOLVERS):
        sel = [r for r in rs if r.solver == solver]
        seconds = [r.seconds for r in sel]
        axes[0, col].loglog(seconds, [r.strong_error for r in sel], "o-", color=f"C{k}", label=solver)
        axes[1, col].loglog(seconds, [max(r.weak_error, 1e-16) for r in sel], "o-", color=f"C{k}", label=solver)
        for r in sel:
            axes[0, col].annotate(f"{r.dt:g}", (r.seconds, r.strong_error), fontsize=6, alpha=0.7)
    se = float(np.median([r.weak_se for r in rs]))
    axes[1, col].axhspan(1e-16, se, color="0.85", label=f"MC error {se:.2g}")
    weakest = min(max(r.weak_error, 1e-16) for r in rs)
    axes[1, col].set_ylim(bottom=min(se / 20, weakest / 2))
    axes[0, col].set(title=f"{name}: strong error at $t_1$ (labels: $\\Delta t$)", ylabel="RMS error")
    axes[1, col].set(
        title=f"{name}: weak error of {CASES[name]['label']}", xlabel="wall time [s]", ylabel="|statistic − exact|"
    )
    for ax in axes[:, col]:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
fig.suptitle(f"Work-precision, {N_PATHS} paths, $\\Delta t \\in$ {DTS}")
fig.tight_layout()
_ = plot.save(fig, "work_precision.png")

# %% [markdown]
# ## The cheapest adequate setting
#
# `cheapest_setting` picks the fastest measured row that meets an accuracy;
# a weak error counts as `weak_error + 2·weak_se`, so no accuracy finer than the
# Monte-Carlo error is claimed.

# %%
for name, rs in rows.items():
    for kind, tol in (("strong", 1e-1), ("strong", 1e-2), ("weak", 0.05 * abs(CASES[name]["reference"]))):
        try:
            r = cheapest_setting(rs, tol, kind=kind)
            print(f"{name}: {kind} error ≤ {tol:.3g}: {r.solver}, dt = {r.dt:g} ({1e3 * r.seconds:.2f} ms)")
        except ValueError as e:
            print(f"{name}: {kind} error ≤ {tol:.3g}: {e}")

# %%
print(f"\nnotebook ran in {time.perf_counter() - T_START:.0f} s")
