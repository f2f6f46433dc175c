"""The Chaplygin ball under a random couple: additive noise, its exact stationary law, CLI registration."""

import jax
import jax.numpy as jnp
import numpy as np

import nhsde
from nhsde.runs import main
from nhsde.scenes import SCENES, ChaplyginBall


def test_stationary_energy_and_uniform_orientation():
    """Stationary f = c(1 − D(γ, Aγ))^{−1/2} e^{−αH}, α = 4ε/ν: E[H] = 3ν/(8ε) and γ uniform (E[γ₃²] = 1/3).

    1024 paths from rest, SRA1 (additive noise), dt = 0.01; per-path time averages
    over t = 10…20 are iid across paths: each within 4 standard errors.
    """
    eps, nu = 0.5, 1.0
    scene = ChaplyginBall(eps=eps, nu=nu, mass=1.0, radius=1.0, inertia_1=0.2, inertia_2=0.4, inertia_3=0.6)
    system = scene.build()
    assert system.additive_noise and system.noise_dim == 3
    ens = nhsde.simulate(
        system,
        scene.initial_state(),
        jax.random.key(0),
        n_paths=1024,
        t1=20.0,
        dt=0.01,
        solver="sra1",
        save=nhsde.Save(names=("energy", "gamma_3"), n=21, paths=True),
    )
    late = np.asarray(ens.paths[:, 10:])
    for values, exact in ((late[..., 0], 3 * nu / (8 * eps)), (late[..., 1] ** 2, 1.0 / 3.0)):
        per_path = values.mean(axis=1)
        se = per_path.std(ddof=1) / np.sqrt(per_path.size)
        assert abs(per_path.mean() - exact) < 4 * se, (per_path.mean(), exact, se)


def test_contact_point_drift_is_offered_and_registered_for_the_cli(capsys):
    full = ChaplyginBall(drift=True).build()
    assert full.layout.names[-2:] == ("x", "y") and full.layout.indices("dependent_coordinate") == (9, 10)
    assert full.additive_noise
    y = ChaplyginBall(drift=True).initial_state().at[:3].set(jnp.array([0.0, 0.4, 0.0]))
    # rolling about the body axis e₂ (= OY at rest) moves the centre along OX by R ω
    v = full.drift(0.0, y, full.params)
    omega_2 = 0.4 / (0.4 + 1.0)  # M = Ĩω, Ĩ₂₂ = I₂ + mR² with γ = e₃
    np.testing.assert_allclose(v[9:], [1.0 * omega_2, 0.0], atol=1e-12)
    assert SCENES["chaplygin-ball"] is ChaplyginBall
    assert main(["scenes"]) == 0
    assert "chaplygin-ball" in capsys.readouterr().out
