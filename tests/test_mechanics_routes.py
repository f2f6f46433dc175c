"""The four routes from a mechanical spec to the equations of motion agree, scene by scene.

Routes: (a) reduced Voronets equations, (b) Hamiltonian form, (c) multipliers,
(d) Gauss's principle.  They are independent computations (T* and the
nonholonomic term of S0 (1.8); H and its derivatives; Lagrange's equations and a
Schur complement; Nielsen's form and a least-compulsion solve), so
agreement to rounding at random states checks each against the others.  The
noise is compared too: how ``V`` enters the accelerations.

Every route's vmapped vector fields call no LAPACK kernel: their solves are the unrolled ones of
``mechanics._small``.  Two batched LAPACK kernels running at once can each wait for the other's share of XLA's
CPU thread pool, and on a 2-core machine never return (the moment equations' ``jacfwd`` on the rolling disk did).
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nhsde import mechanics as mech
from nhsde.scenes import (
    BallFromLagrangian,
    BeadOnRotatingRod,
    BeghinPlate,
    ChaplyginSleighFromSpec,
    ContactOscillator,
    VerticalRollingDisk,
)

N_STATES = 100


def _sleigh_q(key):
    k1, k2 = jax.random.split(key)
    return jnp.concatenate([jax.random.normal(k1, (2,)), jax.random.uniform(k2, (1,), minval=-1.2, maxval=1.2)])


def _beghin_q(key):
    beta = jax.random.uniform(key, (), minval=-3.0, maxval=3.0)
    return jnp.stack([beta + jnp.pi / 2, beta])


SCENES = {
    "sleigh": (ChaplyginSleighFromSpec(eps=0.3, nu=0.7, mass=1.3, inertia=0.6, offset=0.8), _sleigh_q),
    "disk": (VerticalRollingDisk(eps=0.2, nu=0.5, mass=1.2, radius=0.7, roll_inertia=0.4, turn_inertia=0.3), None),
    "contact-oscillator": (ContactOscillator(eps=0.1, nu=0.3, mass=1.5, stiffness=2.0, gravity=0.0), None),
    "s3-point-in-gravity": (ContactOscillator(eps=0.0, nu=0.2, stiffness=0.0, gravity=9.81), None),
    "beghin-contact": (BeghinPlate(realisation="contact", eps=0.1, nu=0.2), _beghin_q),
    "beghin-servo": (BeghinPlate(realisation="servo", eps=0.1, nu=0.2), _beghin_q),
    "ball": (BallFromLagrangian(eps=0.8, nu=1.3, radius=0.6, inertia_ratio=0.4, mass=2.0), None),
    "rod": (BeadOnRotatingRod(eps=0.2, nu=0.4, spin=0.7, wobble=0.4, wobble_rate=1.3), "rod"),
}
# Each route is an autodiff-heavy graph (seconds to compile): by default two scenes that
# cover nonholonomic (B' depending on q) and servo-constraints; all with -m slow.
FAST = ("disk", "beghin-servo")


def random_states(scene, make_q, key, n=N_STATES):
    """``(q, q̇, t)`` on the constraints (velocities projected in the kinetic metric)."""
    spec = scene.spec()
    size = spec.n
    kq, kv, kt = jax.random.split(key, 3)
    if make_q == "rod":  # on the rod, where the dependent velocity ẏ is well defined (|cos u| > 0.5)
        ts = jax.random.uniform(kt, (4 * n,), minval=0.0, maxval=6.0)
        u = jax.vmap(scene.params.control)(ts)
        ts = ts[np.abs(np.cos(np.asarray(u))) > 0.5][:n]
        r = jax.random.uniform(kq, (n,), minval=0.2, maxval=2.0)
        u = jax.vmap(scene.params.control)(ts)
        qs = jnp.stack([r * jnp.cos(u), r * jnp.sin(u)], axis=1)
    else:
        ts = jax.random.uniform(kt, (n,), minval=0.0, maxval=5.0)
        qs = jax.vmap(make_q)(jax.random.split(kq, n)) if make_q else jax.random.normal(kq, (n, size))
    raw = jax.random.normal(kv, (n, size))
    vs = jax.jit(jax.vmap(lambda q, v, t: mech.project_velocity(spec, q, v, t=t)))(qs, raw, ts)
    assert qs.shape == (n, size) and ts.shape == (n,)
    return qs, vs, ts


@pytest.mark.parametrize("name", [n if n in FAST else pytest.param(n, marks=pytest.mark.slow) for n in SCENES])
def test_routes_give_the_same_accelerations_and_noise(name):
    scene, make_q = SCENES[name]
    spec = scene.spec()
    qs, vs, ts = random_states(scene, make_q, jax.random.key(hash(name) % 2**31))
    results = {}
    for route in mech.ROUTES:
        if route == "hamiltonian" and spec.servo is not None:
            with pytest.raises(ValueError, match="needs ideal constraints"):
                mech.formulate(spec, route, dependent=scene.dependent)
            continue
        form = mech.formulate(spec, route, dependent=scene.dependent)
        both = jax.jit(jax.vmap(lambda q, v, t, f=form: (f.accelerations(q, v, t=t), f.acceleration_noise(q, v, t=t))))
        lowered = both.lower(qs, vs, ts)
        assert not re.findall(r"@lapack_\w+", lowered.as_text()), route
        results[route] = lowered.compile()(qs, vs, ts)
    ref_acc, ref_noise = results["multipliers"]
    # the states are on the constraints and the accelerations keep them there: d/dt (A q̇ + A0) = 0 (S1 (1.5))
    residual, rate = jax.jit(
        jax.vmap(
            lambda q, v, a, t: jax.jvp(
                lambda q, v, t: spec.constraint_residual(q, v, jnp.zeros(0), t, spec.params),
                (q, v, t),
                (v, a, jnp.ones(())),
            )
        )
    )(qs, vs, results["reduced"][0], ts)
    assert float(jnp.max(jnp.abs(residual))) < 1e-13 and float(jnp.max(jnp.abs(rate))) < 1e-11
    scale = 1.0 + np.max(np.abs(np.asarray(ref_acc)), axis=1, keepdims=True)
    assert np.all(np.isfinite(np.asarray(ref_acc))) and np.max(np.abs(np.asarray(ref_noise))) > 0
    for route, (acc, noise) in results.items():
        err = np.max(np.abs(np.asarray(acc - ref_acc)) / scale)
        err_noise = np.max(np.abs(np.asarray(noise - ref_noise)))
        print(f"{name}: {route} vs multipliers: max |Δq̈|/(1+|q̈|) = {err:.2e}, max |Δ noise| = {err_noise:.2e}")
        assert err < 1e-10, (route, err)
        assert err_noise < 1e-10, (route, err_noise)


def test_gauss_acceleration_minimises_the_compulsion():
    """S1 (2.8)–(2.10): for allowed accelerations δ, Z(δ) = Z(d) + ½|δ − d|²_M (Mach's equality), so d is the
    constrained minimum; Z vanishes at the accelerations of the released system."""
    scene, _ = SCENES["sleigh"]
    spec = scene.spec()
    p = spec.params
    form = mech.formulate(spec, "gauss")
    released = mech.formulate(
        mech.MechanicalSpec(
            coordinates=spec.coordinates,
            params=p,
            kinetic_energy=spec.kinetic_energy,
            dissipation=spec.dissipation,
            noise_force=spec.noise_force,
        ),
        "gauss",
    )
    q, v, t = (x[0] for x in random_states(scene, _sleigh_q, jax.random.key(5), n=1))
    steps = jax.random.normal(jax.random.key(6), (50, 3))

    @jax.jit
    def compulsions(q, v, t, steps):
        acc = form.accelerations(q, v, t=t)
        rows, _ = spec.velocity_constraints(q, jnp.zeros(0), t, p)
        allowed = steps @ jnp.linalg.svd(rows)[2][rows.shape[0] :].T @ jnp.linalg.svd(rows)[2][rows.shape[0] :]
        z = jax.vmap(lambda d: form.compulsion(q, v, acc + d, t=t))(allowed)
        free = released.accelerations(q, v, t=t)
        mass = spec.inertia(q, jnp.zeros(0), t, p)
        return z, form.compulsion(q, v, acc, t=t), allowed, mass, form.compulsion(q, v, free, t=t), rows @ free

    z, z0, allowed, mass, z_free, violation = compulsions(q, v, t, steps)
    np.testing.assert_allclose(z - z0, 0.5 * jnp.einsum("ki,ij,kj->k", allowed, mass, allowed), rtol=1e-10)
    assert float(z_free) < 1e-20 < float(z0)
    assert float(jnp.abs(violation[0])) > 1e-3  # the released motion leaves the constraint


def test_pivoting_chooses_a_well_conditioned_dependent_velocity():
    scene = ChaplyginSleighFromSpec()
    spec = scene.spec()
    assert mech.choose_dependent(spec, jnp.array([0.0, 0.0, 0.1])) == ("y",)
    assert mech.choose_dependent(spec, jnp.array([0.0, 0.0, 1.5])) == ("x",)
    form = mech.formulate(spec, "reduced", reference=jnp.array([0.0, 0.0, 1.5]))
    assert form.layout().names == ("x", "y", "theta", "y_dot", "theta_dot")
    assert form.layout().roles[:3] == ("dependent_coordinate", "independent_coordinate", "independent_coordinate")


def test_layouts_and_observables_of_each_route():
    spec = VerticalRollingDisk().spec()
    names = {route: mech.build(spec, route, dependent=("x", "y")).layout for route in mech.ROUTES}
    assert names["reduced"].names == ("x", "y", "theta", "phi", "theta_dot", "phi_dot")
    assert names["hamiltonian"].names[4:] == ("p_theta", "p_phi")
    assert names["hamiltonian"].indices("momentum") == (4, 5)
    assert names["multipliers"].names[4:] == ("x_dot", "y_dot", "theta_dot", "phi_dot")
    assert names["gauss"].indices("dependent_coordinate") == (0, 1)
    system = mech.build(spec, "multipliers", dependent=("x", "y"))
    assert {"energy", "constraint_residual", "lambda_0", "lambda_1"} <= set(system.observable_names())
    assert {"x_dot", "y_dot"} <= set(mech.build(spec, "reduced", dependent=("x", "y")).observable_names())
