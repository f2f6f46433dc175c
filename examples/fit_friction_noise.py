"""Recover friction ε and noise intensity ν from synthetic data with nhsde.fit.

1. The ball on a vibrating plane (S0 (3.1)): 2048 observed trajectories of
   (x, u_x) at eight times; ε and ν fitted through the closed-form covariances
   and through the simulator (optax L-BFGS on the differentiable ``simulate``).
2. The noisy Chaplygin sleigh (nonlinear): 2048 observed trajectories of
   (v, ω); ε and ν fitted through the simulator.

Each estimate is printed with its standard error (Fisher information of the
Gaussian likelihood of the observed means and covariances), its distance
from the truth in standard errors, and the goodness of fit: the p-value of the
fit's χ² on its degrees of freedom, P(χ²_dof ≥ χ²) if the model is right.  A
p-value near 0 (below 0.01, say) means a misfit larger than the Monte-Carlo
noise of the data and of the model explains: a model that differs from the
data's (another solver or step, a missing term), or error bars that leave out
correlations; a p-value that is merely small (0.03 happens one fit in 33)
is no evidence against the model.  Run: ``python examples/fit_friction_noise.py``
(one to two minutes on two CPU cores).
"""

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

import nhsde
from nhsde import fit
from nhsde.scenes import BallOnVibratingPlane, ChaplyginSleigh, ball_covariances

jax.config.update("jax_enable_x64", True)


def report(title, result, truth):
    print(f"\n{title}\n{result}")
    z = (result.values - np.asarray(truth)) / result.se
    print(
        "truth:",
        ", ".join(f"{n}={t}" for n, t in zip(result.names, truth)),
        "| (estimate − truth)/SE:",
        np.array2string(z, precision=2),
    )
    p_value = scipy.stats.chi2.sf(result.chi2, result.dof)
    verdict = "a misfit beyond the noise" if p_value < 0.01 else "consistent with the noise"
    print(f"goodness of fit: chi2 = {result.chi2:.1f} on {result.dof} dof, p = {p_value:.3g} ({verdict})")


def ball():
    eps, nu, names = 0.8, 1.5, ("x", "u_x")
    truth = BallOnVibratingPlane(eps=eps, nu=nu).build()
    data = nhsde.simulate(
        truth,
        jnp.zeros(4),
        jax.random.key(1),
        n_paths=2048,
        t1=4.0,
        dt=0.02,
        solver="sra1",
        save=nhsde.Save(names=names, n=9, paths=True),
    )
    observed = fit.Observations.from_paths(data.ts[1:], data.paths[:, 1:], names)  # t = 0 is not random
    start = BallOnVibratingPlane(eps=0.3, nu=0.5).build()

    def closed_form(p, ts):
        kxx, kxu, kuu = ball_covariances(ts, p.eps, p.nu, p.delta)
        cov = jnp.stack([jnp.stack([kxx, kxu], -1), jnp.stack([kxu, kuu], -1)], -2)
        return jnp.zeros(ts.shape + (2,), ts.dtype), cov

    report("ball, closed-form covariances:", fit.estimate(start, observed, fit.ClosedForm(closed_form)), (eps, nu))
    # The model simulates with another key, the data's solver and step (SRA1: its weak error at
    # dt = 0.02 is far below the Monte-Carlo error, so the closed form applies to the data too).
    model = fit.Simulated(jnp.zeros(4), jax.random.key(2), n_paths=4096, steps=0.02, solver="sra1")
    report("ball, through the simulator:", fit.estimate(start, observed, model), (eps, nu))


def sleigh():
    eps, nu, y0 = 0.5, 0.8, jnp.array([1.0, 0.5])
    truth = ChaplyginSleigh(eps=eps, nu=nu, drift=False).build()
    data = nhsde.simulate(truth, y0, jax.random.key(3), n_paths=2048, t1=3.0, dt=0.02, save=nhsde.Save(n=7, paths=True))
    observed = fit.Observations.from_paths(data.ts[1:], data.paths[:, 1:], ("v", "omega"))
    start = ChaplyginSleigh(eps=0.2, nu=0.3, drift=False).build()
    model = fit.Simulated(y0, jax.random.key(4), n_paths=4096, steps=0.02)
    report("Chaplygin sleigh, through the simulator:", fit.estimate(start, observed, model), (eps, nu))


if __name__ == "__main__":
    ball()
    sleigh()
