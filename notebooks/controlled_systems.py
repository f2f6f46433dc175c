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
# # Controlled systems: Gauss's principle, multipliers, and Beghin's plate
#
# Rumyantsev (S1) studies systems whose constraints depend on a control $u(t)$
# (*parametric* constraints) and systems whose constraints are kept by a motor
# (Beghin's *servo-constraints*).  `nhsde.mechanics` takes such a system as a
# specification — kinetic energy, potential, constraints as JAX functions — and
# derives the equations of motion itself, by four independent routes.  Here we
# look at two of them side by side:
#
# * **multipliers** (S1 (2.3)): $M\ddot q + h = A^\mathsf{T}\lambda$ together with the
#   differentiated constraints $A\ddot q = r$;
# * **Gauss's principle** (S1 (2.10)): the real accelerations minimise the
#   *compulsion* $Z(\ddot q) = \tfrac12(\ddot q - M^{-1}F)^\mathsf{T} M (\ddot q - M^{-1}F)$
#   over the accelerations the constraints allow.
#
# and at what Beghin's servo-constraint changes compared with the same relation
# kept by contact.

# %%
import os

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt

from nhsde import mechanics as mech, plot
from nhsde.scenes import BeadOnRotatingRod, BeghinPlate

jax.config.update("jax_enable_x64", True)


def solve(form, y0, ts, extra=None):
    """High-accuracy solve of a form's drift; ``extra(t, y)`` is integrated alongside."""
    p = form.spec.params

    def field(t, z, args):
        y = z[:-1]
        return jnp.concatenate([form.drift(t, y, p), extra(t, y)[None]])

    sol = dfx.diffeqsolve(
        dfx.ODETerm(field),
        dfx.Tsit5(),
        ts[0],
        ts[-1],
        1e-3,
        jnp.concatenate([y0, jnp.zeros(1)]),
        saveat=dfx.SaveAt(ts=ts),
        stepsize_controller=dfx.PIDController(rtol=1e-10, atol=1e-10),
        max_steps=100_000,
    )
    return sol.ys[:, :-1], sol.ys[:, -1]


# %%
# The run's size: NHSDE_NOTEBOOK_SIZE=full (the default; the stored outputs) or small (the test suite's
# quick run).  Both run the same here: this notebook's time is compiling its few integrations, which
# take milliseconds once compiled, so a smaller run would save nothing.
SIZE = os.environ.get("NHSDE_NOTEBOOK_SIZE", "full")
if SIZE not in ("full", "small"):
    raise ValueError(f"NHSDE_NOTEBOOK_SIZE={SIZE!r}; allowed: 'full', 'small'")
print(f"size: {SIZE} (the same work at either size)")

# %% [markdown]
# ## 1. A bead on a rod turned by a control
#
# The rod turns at the prescribed angle $u(t) = \Omega t + A\sin wt$; the bead is
# held on it by the parametric constraint $f = -x\sin u + y\cos u = 0$ (S1 (1.1)).
# Differentiating, $\dot u$ enters the velocity constraint and $\ddot u$ the
# accelerations (S1 (1.4)–(1.5)), and the reaction $\lambda\nabla f$ works on the
# real motion: the energy changes by exactly that work (S1 (2.5)–(2.6)),
# $$ T(t) - T(0) = \int_0^t \lambda\,\nabla f\cdot\dot q\,\mathrm d\tau,
# \qquad \lambda = m\,(2\dot r\dot u + r\ddot u). $$

# %%
rod = BeadOnRotatingRod(spin=0.7, wobble=0.4, wobble_rate=1.3, eps=0.0)  # frictionless: ΔT is the reaction's work alone
spec, p = rod.spec(), rod.params
by_multipliers = mech.formulate(spec, "multipliers")
by_gauss = mech.formulate(spec, "gauss")
q0, qd0 = rod.configuration()
ts = jnp.linspace(0.0, 3.0, 151)


def power(t, y):
    q, v, _ = by_multipliers.velocities(t, y, p)
    return by_multipliers.reactions(q, v, t=t) @ v


ys, work = eqx.filter_jit(solve)(by_multipliers, by_multipliers.state(q0, qd0), ts, power)
q, v = ys[:, :2], ys[:, 2:]
energy = jax.vmap(lambda q, v, t: spec.energy(q, v, jnp.zeros(0), t, p))(q, v, ts)
lam = jax.jit(jax.vmap(lambda q, v, t: by_multipliers.multipliers(q, v, t=t)))(q, v, ts)[:, 0]
# the reaction by Gauss's principle: what the constraint adds to the free accelerations, projected on ∇f
acc_gauss = jax.jit(jax.vmap(lambda q, v, t: by_gauss.accelerations(q, v, t=t)))(q, v, ts)
normal = jnp.stack([-jnp.sin(p.control(ts)), jnp.cos(p.control(ts))], 1)
lam_gauss = p.mass * jnp.sum(acc_gauss * normal, 1)
print(
    f"max |ΔT − W| = {float(jnp.max(jnp.abs(energy - energy[0] - work))):.2e};  "
    f"max |λ(multipliers) − λ(Gauss)| = {float(jnp.max(jnp.abs(lam - lam_gauss))):.2e}"
)

fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
ax[0].plot(ts, energy - energy[0], lw=3, alpha=0.4, label="$T(t) - T(0)$")
ax[0].plot(ts, work, "k--", label=r"work of the reaction $\int\lambda\nabla f\cdot\dot q$")
ax[0].set_xlabel("t")
ax[0].legend()
ax[0].set_title("the control pumps energy through the reaction")
ax[1].plot(ts, lam, lw=3, alpha=0.4, label="multipliers (S1 (2.3))")
ax[1].plot(ts, lam_gauss, "k--", label="Gauss's principle (S1 (2.10))")
ax[1].set_xlabel("t")
ax[1].set_ylabel(r"$\lambda$")
ax[1].legend()
ax[1].set_title("the reaction by two routes")
fig.tight_layout()
_ = plot.save(fig, "rod_energy_work.png", dpi=110)

# %% [markdown]
# ## 2. Gauss's principle, drawn
#
# For the bead the accelerations form a plane; the constraint leaves a line of
# admissible accelerations.  The compulsion's level sets are ellipses (circles
# here: $M = mI$) about the acceleration of the *released* bead, $M^{-1}F$.  The
# real acceleration is where the admissible line touches the smallest ellipse —
# the point the multipliers give.

# %%
t_star = 1.0
i = int(jnp.argmin(jnp.abs(ts - t_star)))
qi, vi, ti = q[i], v[i], ts[i]
a_real = by_gauss.accelerations(qi, vi, t=ti)
rows, _ = spec.velocity_constraints(qi, jnp.zeros(0), ti, p)
tangent = jnp.array([rows[0, 1], -rows[0, 0]])
grid = jnp.linspace(-3.0, 3.0, 121)
aa, bb = jnp.meshgrid(grid + a_real[0], grid + a_real[1])
z = jax.jit(jax.vmap(jax.vmap(lambda a, b: by_gauss.compulsion(qi, vi, jnp.stack([a, b]), t=ti))))(aa, bb)
line = a_real[None, :] + jnp.linspace(-3, 3, 2)[:, None] * tangent[None, :]
fig, ax = plt.subplots(figsize=(5, 4.6))
ax.contour(aa, bb, z, levels=15, cmap="viridis")
ax.plot(line[:, 0], line[:, 1], "k-", label=r"admissible: $\nabla f\cdot\ddot q = r$")
ax.plot(*a_real, "ro", label="least compulsion")
ax.plot(*by_multipliers.accelerations(qi, vi, t=ti), "kx", ms=10, label="multipliers")
ax.set_xlabel(r"$\ddot x$")
ax.set_ylabel(r"$\ddot y$")
ax.set_aspect("equal")
ax.legend(loc="lower left", fontsize=8)
ax.set_title(f"compulsion Z at t = {float(ti):.2f}")
fig.tight_layout()
_ = plot.save(fig, "gauss_compulsion.png", dpi=110)

# %% [markdown]
# ## 3. Beghin's plate: servo-constraint versus contact
#
# A plate hinged to the rim of a disk (S1 Example 3.1).  The relation
# $\alpha - \beta = \pi/2$ between the disk's and the plate's angles is kept either
# by **contact** — an ideal constraint, the two turn as one body, S1 (3.5):
# $$[M(R^2+b^2+k^2) + I_1]\ddot\beta + F(a\sin\beta + R\cos\beta) = 0,$$
# or by a **servomotor** acting on the disk, whose torque does no work on
# displacements with $\delta\alpha = 0$ (S1 (3.2)) — Beghin's equation S1 (3.4):
# $$M(b^2+k^2)\ddot\beta - MRb\dot\beta^2 + Fa\sin\beta = 0 .$$
# The library derives both from the same energies; only the way the relation is
# realised differs.  The servo's torque $\mu$ is the control $u$ of Kirgetov's
# equation (3.6) — Rumyantsev's resolution of the dispute.

# %%
ts = jnp.linspace(0.0, 12.0, 241)
runs = {}
for realisation in ("servo", "contact"):
    plate = BeghinPlate(realisation=realisation, eps=0.0, nu=0.0)
    form = mech.formulate(plate.spec(), "multipliers", dependent=("alpha",))
    bp = plate.params
    q0, qd0 = plate.configuration()
    ys, _ = eqx.filter_jit(solve)(form, form.state(q0, qd0), ts, lambda t, y: jnp.zeros(()))
    mu = jax.jit(jax.vmap(lambda y, form=form: form.multipliers(y[:2], y[2:])))(ys)[:, 0]
    runs[realisation] = (ys[:, 1], mu)


def printed(beta_ddot):
    """Integrate a printed equation β̈ = g(β, β̇) from the same start."""
    sol = dfx.diffeqsolve(
        dfx.ODETerm(lambda t, y, a: jnp.stack([y[1], beta_ddot(y[0], y[1])])),
        dfx.Tsit5(),
        0.0,
        12.0,
        1e-3,
        jnp.array([0.3, 0.5]),
        saveat=dfx.SaveAt(ts=ts),
        stepsize_controller=dfx.PIDController(rtol=1e-10, atol=1e-10),
    )
    return sol.ys[:, 0]


m_, k_, b_, r_, f_, a_, i1 = (
    bp.plate_mass,
    bp.gyration,
    bp.hinge_offset,
    bp.disk_radius,
    bp.force,
    bp.arm,
    bp.disk_inertia,
)
beta_34 = printed(lambda b, w: (m_ * r_ * b_ * w**2 - f_ * a_ * jnp.sin(b)) / (m_ * (b_**2 + k_**2)))
beta_35 = printed(lambda b, w: -f_ * (a_ * jnp.sin(b) + r_ * jnp.cos(b)) / (m_ * (r_**2 + b_**2 + k_**2) + i1))
print(
    f"servo vs (3.4): {float(jnp.max(jnp.abs(runs['servo'][0] - beta_34))):.1e};  "
    f"contact vs (3.5): {float(jnp.max(jnp.abs(runs['contact'][0] - beta_35))):.1e}"
)

fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
ax[0].plot(ts, runs["servo"][0], lw=3, alpha=0.4, label="servo-constraint (library)")
ax[0].plot(ts, beta_34, "k--", lw=1, label="S1 (3.4)")
ax[0].plot(ts, runs["contact"][0], lw=3, alpha=0.4, label="contact (library)")
ax[0].plot(ts, beta_35, "k:", lw=1, label="S1 (3.5)")
ax[0].set_xlabel("t")
ax[0].set_ylabel(r"$\beta$")
ax[0].legend(fontsize=8)
ax[0].set_title("the same relation, two realisations")
ax[1].plot(ts, runs["servo"][1], label=r"servo torque $\mu$ on the disk")
ax[1].plot(ts, runs["contact"][1], label=r"contact: multiplier of $\alpha-\beta=\pi/2$")
ax[1].set_xlabel("t")
ax[1].legend(fontsize=8)
ax[1].set_title("reactions")
fig.tight_layout()
plot.save(fig, "beghin_servo_vs_contact.png", dpi=110)
print("figures in", plot.figure_dir())
