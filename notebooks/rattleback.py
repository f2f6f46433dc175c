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
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # The rattleback: stability that depends on the sense of spin (S4 Remark 4.4)
#
# Kane & Levinson's rattleback (1982): an ellipsoid `a, b, c = 0.2, 0.03, 0.02` m,
# centre of mass `h = 0.01` m below the centre, `m = 1` kg, central moments
# `A, B, C = 2e-4, 1.6e-3, 1.7e-3` and product of inertia `D = −2e-5` kg·m², rolling
# without slipping on a horizontal plane: `nhsde.scenes.Rattleback`, a classic
# `RollingBody` in `(ω, γ)`.  In the library's axes `e₃ = γ` points up at rest, so
# `ω₃ > 0` is a counter-clockwise spin seen from above; Kane & Levinson's `b₃`
# points down, and the inertia entry becomes `I₁₂ = −D`.
#
# Steady spin `ω = nγ, γ = e₃` lies in a two-parameter family (`n` and `|γ|`):
# two zero roots.  The other four are the pitch (≈ 107 rad/s) and roll
# (≈ 34 rad/s) oscillations.  The equations are reversible
# (`(ω, γ, t) → (−ω, γ, −t)`), so the roots at `−n` are minus those at `n`: if one
# sense is asymptotically stable the other is unstable (S4 Remark 4.4).

# %%
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from nhsde import plot
from nhsde.analysis import integral_drift, jacobian, linear_stability, solve_flow
from nhsde.scenes import Rattleback

jax.config.update("jax_enable_x64", True)
start = time.time()
kl = Rattleback()
variant = Rattleback(inertia=(8e-4, 1.6e-3, 1.7e-3), semi_axes=(0.2, 0.03, 0.025), height=0.005)


def pitch_and_roll(scene, spins):
    """The pitch and the roll root (``Im μ > 0``; the pitch has the larger frequency) at each spin rate."""
    jac = eqx.filter_jit(jax.vmap(lambda n: jacobian(scene.vector_field, scene.spin(n), scene.params)))(spins)
    eig = np.linalg.eigvals(np.asarray(jac))
    key = np.where(eig.imag > 1.0, eig.imag, np.inf)  # one root of each conjugate pair; the zero roots last
    upper = np.take_along_axis(eig, np.argsort(key, axis=1), axis=1)
    return upper[:, 1], upper[:, 0]


# %%
# The run's size: NHSDE_NOTEBOOK_SIZE=full (the default; the stored outputs) or small (the test
# suite's quick run: every cell and figure, the long integrations over 20 s instead of 60 s, so the
# second reversal and most of the slow growth and decay are cut off).
SIZE = os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")
if SIZE not in ("full", "small"):
    raise ValueError(f"NHSDE_NOTEBOOK_SIZE={SIZE!r}; allowed: 'full', 'small'")
T_LONG = 20.0 if SIZE == "small" else 60.0
N_SAVE = int(100 * T_LONG) + 1  # saved every 0.01 s
print(f"size: {SIZE}, long integrations over {T_LONG:g} s")

# %% [markdown]
# ## Growth rates in both senses
#
# For Kane & Levinson's body both senses are unstable: counter-clockwise the
# pitch grows (and the roll decays), clockwise the roll grows ten times more
# slowly (and the pitch decays).  Without dissipation the rattleback reverses
# either way; counter-clockwise is the fast "rattle".  A rounder variant
# (`c = 0.025`, `h = 0.005`, `A = 8e-4`) spun clockwise faster than about
# 19 rad/s has all four roots in the left half-plane: asymptotically stable
# one way, unstable the other.

# %%
print(" |n|   counter-clockwise                      clockwise")
for n in (1.0, 2.0, 5.0, 10.0):
    ccw = linear_stability(kl.vector_field, kl.spin(n), kl.params, n_family=2)
    cw = linear_stability(kl.vector_field, kl.spin(-n), kl.params, n_family=2)
    print(
        f"{n:4.0f}   {float(ccw.growth_rate):.4f} 1/s ({ccw.verdict})   {float(cw.growth_rate):.4f} 1/s ({cw.verdict})"
    )
for n in (-50.0, 50.0):
    st = linear_stability(variant.vector_field, variant.spin(n), variant.params, n_family=2)
    print(f"variant n = {n:+.0f}: {st.verdict}, roots {np.round(np.asarray(st.roots), 4)}")

fig, axes = plt.subplots(1, 2, figsize=(11, 4))
for ax, scene, top, name in ((axes[0], kl, 20.0, "Kane & Levinson"), (axes[1], variant, 60.0, "variant")):
    spins = jnp.linspace(-top, top, 241)
    pitch, roll = pitch_and_roll(scene, spins)
    ax.plot(spins, pitch.real, "C0", label="pitch")
    ax.plot(spins, roll.real, "C3", label="roll")
    ax.legend(fontsize=8)
    ax.axhline(0, color="grey", lw=0.5)
    ax.set_xlabel("spin n (rad/s), > 0 counter-clockwise from above")
    ax.set_ylabel("Re μ (1/s)")
    ax.set_title(f"{name}: real parts of the four roots")
axes[1].set_ylim(-2, 2)
fig.tight_layout()
_ = plot.save(fig, "rattleback_growth_rates.png", dpi=110)

# %% [markdown]
# ## The growth rate on the nonlinear flow
#
# From a tilt of `1e-8` rad the tilt `|γ × e₃|` of the nonlinear flow grows as
# `e^{Re μ t}` (dashed: the linear prediction).  Right: the variant spun clockwise
# at 50 rad/s from a tilt of `1e-4` settles back onto a steady spin (S4 Theorem 4.1),
# the tilt decaying at the rate of its slowest root.


# %%
def tilt(flow):
    ys = np.asarray(flow.ys[0])
    return np.hypot(ys[:, 3], ys[:, 4])


fig, axes = plt.subplots(1, 3, figsize=(14, 4))
for ax, n, t1 in ((axes[0], 5.0, 6.0), (axes[1], -5.0, T_LONG)):
    rate = float(linear_stability(kl.vector_field, kl.spin(n), kl.params, n_family=2).growth_rate)
    flow = solve_flow(
        kl.vector_field, kl.spin(n, 1e-8, 0.7)[None], kl.params, t1=t1, n_save=N_SAVE, rtol=1e-12, atol=1e-14
    )
    ts = np.asarray(flow.ts)
    ax.semilogy(ts, tilt(flow), "C0", lw=0.3, label="tilt |γ × e₃| (nonlinear flow)")
    ax.semilogy(ts, 1e-8 * np.exp(rate * ts), "k--", lw=1, label=f"e^(Re μ t), Re μ = {rate:.4f}/s")
    ax.set_xlabel("t (s)")
    ax.set_title(f"Kane & Levinson, n = {n:+.0f} rad/s ({'counter-' if n > 0 else ''}clockwise)")
    ax.legend(fontsize=7)
axes[0].set_ylabel("tilt (rad)")

slowest = float(linear_stability(variant.vector_field, variant.spin(-50.0), variant.params, n_family=2).roots[0].real)
flow = solve_flow(
    variant.vector_field,
    variant.spin(-50.0, 1e-4, 0.7)[None],
    variant.params,
    t1=T_LONG,
    n_save=N_SAVE,
    rtol=1e-11,
    atol=1e-13,
)
ts, ys = np.asarray(flow.ts), np.asarray(flow.ys[0])
axes[2].semilogy(ts, tilt(flow), "C2", lw=0.3, label="tilt (nonlinear flow)")
axes[2].semilogy(
    ts,
    2 * tilt(flow)[N_SAVE // 3 :].max() * np.exp(slowest * (ts - ts[N_SAVE // 3])),
    "k--",
    lw=1,
    label=f"∝ e^(Re μ t), Re μ = {slowest:.4f}/s",
)
axes[2].set_xlabel("t (s)")
axes[2].set_title("variant, n = −50 rad/s: asymptotically stable")
axes[2].legend(fontsize=7)
spin = np.sum(ys[:, :3] * ys[:, 3:], axis=1)
print(f"variant: spin settles at {spin[-1]:.5f} rad/s (started at −50)")
fig.tight_layout()
_ = plot.save(fig, "rattleback_growth_fit.png", dpi=110)

# %% [markdown]
# ## Spin reversal
#
# Spun at 5 rad/s with the long axis tipped by 1e-3 rad (the state `spin(n, tilt)`
# turns about the vertical through the contact point, which a pitch tilt moves by
# `(a²/c)·tilt = 2 mm`): counter-clockwise, the rattleback pitches, stops at
# t ≈ 3.7 s and spins clockwise at 5 rad/s; the slow roll instability of the
# clockwise spin turns it back at t ≈ 30 s.  Started clockwise, the roll builds
# up for about 22 s before the first reversal.  Energy and `γ²` (the first
# integrals) stay constant to the integration tolerance.

# %%
flow = solve_flow(
    kl.vector_field, jnp.stack([kl.spin(5.0, 1e-3), kl.spin(-5.0, 1e-3)]), kl.params, t1=T_LONG, n_save=N_SAVE
)
ts, ys = np.asarray(flow.ts), np.asarray(flow.ys)
spin = np.sum(ys[..., :3] * ys[..., 3:], axis=-1) / np.linalg.norm(ys[..., 3:], axis=-1)
drift = integral_drift({"E": lambda y, p: kl.energy(y), "γ²": lambda y, p: y[3:] @ y[3:]}, flow, kl.params)
energy0 = np.asarray(jax.vmap(kl.energy)(flow.ys[:, 0]))
print("relative energy drift", np.asarray(drift["E"]) / energy0, " |γ²| drift", np.asarray(drift["γ²"]))

fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
for k, label in enumerate(("counter-clockwise start", "clockwise start")):
    axes[0].plot(ts, spin[k], lw=0.8, label=label)
    envelope = np.degrees(np.arccos(np.clip(ys[k, 1:, 5], -1, 1))).reshape(-1, 20).max(axis=1)  # per 0.2 s
    axes[1].plot(ts[1:].reshape(-1, 20)[:, 10], envelope, lw=0.8, label=label)
axes[0].axhline(0, color="grey", lw=0.5)
axes[0].set_ylabel("spin about the vertical (rad/s)")
axes[0].legend(fontsize=8)
axes[1].set_ylabel("largest tilt per 0.2 s (deg)")
axes[1].set_xlabel("t (s)")
fig.tight_layout()
plot.save(fig, "rattleback_reversal.png", dpi=110)
print(f"total {time.time() - start:.1f} s")
