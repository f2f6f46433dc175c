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
# # A heavy body of revolution on a vibrating rough plane: stationary densities (S0 §5, Statement 2)
#
# The body rolls without slipping on a plane vibrating with white-noise
# acceleration of intensity `ν`, against viscous friction `Φ₁ = mεU_e²`.  For a
# dynamically symmetric body of revolution the frictionless motion has the
# invariant measure `N(θ) = 1/δ(θ)` (S0 §5), and S0 Statement 2 gives the
# stationary law `c N e^{−αH}`.  The flux balance fixes `α = 4ε/(mν)` (see
# `nhsde.scenes.BodyOnVibratingPlane`).  Its nutation marginal is
# `c N(θ) sin θ (det Ĩ)^{1/2} e^{−αU(θ)}`.
#
# Below: a homogeneous oblate spheroid at two temperatures `1/α`, from ensembles
# started in the stationary law and from rest (θ sampled at t = 20, 22, …, 40);
# then Routh's sphere (a ball with
# its centre of mass on the axis), whose Jellett integral `J = (Ĩω, r)` the
# vibration cannot change: from rest (`J = 0`) it does not reach S0's law.

# %%
import os
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import nhsde
import nhsde.bodies as B
from nhsde import plot
from nhsde.scenes import (
    BodyOnVibratingPlane,
    sample_stationary,
    stationary_nutation_density,
)

jax.config.update("jax_enable_x64", True)
start = time.time()
EDGES = np.linspace(0.0, np.pi, 25)
THETA = np.linspace(0.0, np.pi, 400)


def nutation_samples(scene, y0, key, t1=40.0, burn_in=20.0):
    """θ at t = burn_in, burn_in + 2, …, t1 for every path (Heun's method, second order in the drift, dt = 0.01:
    Euler–Heun biases the stationary E[H] by about −6 % at this step)."""
    ens = nhsde.simulate(
        scene.build(),
        y0,
        jax.random.key(key),
        n_paths=y0.shape[0],
        t1=t1,
        dt=0.01,
        solver="heun2",
        save=nhsde.Save(names=("theta",), n=int(t1 / 2) + 1, paths=True),
    )
    return np.asarray(ens.paths[:, int(burn_in / 2) :, 0])


def histogram(ax, theta, label, **kw):
    """Density histogram with ±2 standard-error bars from per-path fractions (paths are independent)."""
    frac = np.stack([((theta >= EDGES[k]) & (theta < EDGES[k + 1])).mean(axis=1) for k in range(len(EDGES) - 1)], 1)
    width = np.diff(EDGES)
    mean, se = frac.mean(0) / width, frac.std(0, ddof=1) / np.sqrt(frac.shape[0]) / width
    centres = 0.5 * (EDGES[1:] + EDGES[:-1])
    ax.errorbar(centres, mean, yerr=2 * se, fmt="o", ms=3, capsize=2, label=label, **kw)


# %%
# The run's size: NHSDE_NOTEBOOK_SIZE=full (the default; the stored outputs) or small (the test
# suite's quick run: every cell and figure with 128 paths per ensemble instead of 1024, so the
# histograms' error bars are about three times as wide).
SIZE = os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")
if SIZE not in ("full", "small"):
    raise ValueError(f"NHSDE_NOTEBOOK_SIZE={SIZE!r}; allowed: 'full', 'small'")
N_PATHS = 128 if SIZE == "small" else 1024
print(f"size: {SIZE}, {N_PATHS} paths per ensemble")

# %% [markdown]
# ## The spheroid at two temperatures

# %%
spheroid = B.RigidBody(mass=1.0, inertia=(0.272, 0.272, 0.4), surface=B.Ellipsoid(semi_axes=(1.0, 1.0, 0.6)))
fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
for ax, (eps, nu) in zip(axes, [(1.0, 2.0), (1.0, 4.0)]):
    scene = BodyOnVibratingPlane(body=spheroid, eps=eps, nu=nu, gravity=1.0)
    alpha = float(scene.params.alpha)
    ax.plot(THETA, np.asarray(stationary_nutation_density(scene.params, THETA)), "k-", label="S0 Statement 2")
    y0 = sample_stationary(scene.params, jax.random.key(1), N_PATHS)
    histogram(ax, nutation_samples(scene, y0, key=2), "ensemble from the stationary law")
    rest = jnp.broadcast_to(scene.initial_state(), (N_PATHS, 6))
    histogram(ax, nutation_samples(scene, rest, key=3), "ensemble from rest")
    ax.set_title(f"oblate spheroid, α = 4ε/(mν) = {alpha:g}")
    ax.set_xlabel("nutation angle θ")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)
fig.tight_layout()
_ = plot.save(fig, "nutation_density_spheroid.png", dpi=110)

# %% [markdown]
# ## Routh's sphere: Jellett's integral survives the vibration
#
# All forces act at the centre of mass, so their moments about the contact
# point are orthogonal to `r` and never change `J = (Ĩω, r)`; for Routh's sphere
# `J` is also an integral of the frictionless motion.  From rest the ensemble
# stays on `J = 0` and settles to a different law.

# %%
routh = B.RigidBody(mass=1.0, inertia=(0.4, 0.4, 0.3), surface=B.Sphere(radius=1.0, offset=(0.0, 0.0, -0.3)))
scene = BodyOnVibratingPlane(body=routh, eps=1.0, nu=2.0, gravity=1.0)
fig, ax = plt.subplots(figsize=(6, 4.2))
ax.plot(THETA, np.asarray(stationary_nutation_density(scene.params, THETA)), "k-", label="S0 Statement 2")
histogram(
    ax,
    nutation_samples(scene, sample_stationary(scene.params, jax.random.key(4), N_PATHS), key=5),
    "from the stationary law",
)
histogram(
    ax,
    nutation_samples(scene, jnp.broadcast_to(scene.initial_state(), (N_PATHS, 6)), key=6),
    "from rest: J = 0 forever",
)
ax.set_title("Routh's sphere (R = 1, centre of mass 0.3 below the centre)")
ax.set_xlabel("nutation angle θ")
ax.set_ylabel("density")
ax.legend(fontsize=8)
fig.tight_layout()
plot.save(fig, "nutation_density_routh_sphere.png", dpi=110)
print(f"total {time.time() - start:.1f} s")
