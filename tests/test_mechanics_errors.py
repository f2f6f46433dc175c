"""Bad specs and bad use raise clear errors naming the problem."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nhsde import AbstractParameters, mechanics as mech, parameter
from nhsde.scenes import BeghinPlate, ContactOscillator, VerticalRollingDisk


class P(AbstractParameters):
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True)


def kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * v @ v


def contact(q, pi, t, p):
    return jnp.stack([jnp.ones((), q.dtype), jnp.zeros((), q.dtype), q[1]])[None, :]


def spec(**kw):
    base: dict[str, Any] = {
        "coordinates": ("x", "y", "z"),
        "params": P(),
        "kinetic_energy": kinetic,
        "constraints": contact,
    }
    return mech.MechanicalSpec(**{**base, **kw})


Q0 = jnp.array([0.1, 0.5, -0.2])


def test_constraint_matrix_of_wrong_shape():
    with pytest.raises(ValueError, match=r"constraints\(q, pi, t, p\) returned shape \(1, 4\); expected \(m, 3\)"):
        spec(constraints=lambda q, pi, t, p: jnp.ones((1, 4)))
    with pytest.raises(ValueError, match=r"constraint_bias.*returned shape \(2,\); expected \(1,\)"):
        spec(constraint_bias=lambda q, pi, t, p: jnp.zeros(2))
    with pytest.raises(ValueError, match="leave no motion"):
        spec(constraints=lambda q, pi, t, p: jnp.eye(3))


def test_rank_deficient_constraints():
    twice = spec(constraints=lambda q, pi, t, p: jnp.concatenate([contact(q, pi, t, p), 2 * contact(q, pi, t, p)]))
    with pytest.raises(ValueError, match=r"has rank 1 < 2 rows: the constraints are not independent"):
        mech.formulate(twice, "multipliers", reference=Q0)
    with pytest.raises(ValueError, match="are dependent; cannot pivot|rank 1 < 2"):
        mech.choose_dependent(twice, Q0)
    form = mech.formulate(twice, "multipliers")  # no reference: caught at run time instead
    with pytest.raises(Exception, match="constraint rows are dependent"):
        form.accelerations(Q0, jnp.array([-0.5, 0.3, 1.0]))


@pytest.mark.parametrize(
    "t_fn, what",
    [
        (lambda q, v, pi, t, p: 0.5 * (v[0] ** 2 + v[1] ** 2), "singular"),  # no inertia along z
        (lambda q, v, pi, t, p: 0.5 * (v[0] ** 2 + v[1] ** 2 - v[2] ** 2), "indefinite"),
    ],
)
def test_singular_or_indefinite_mass_matrix(t_fn, what):
    bad = spec(kinetic_energy=t_fn)
    with pytest.raises(ValueError, match="mass matrix at q=.* is singular or indefinite"):
        mech.formulate(bad, "reduced", dependent=("x",), reference=Q0)
    form = mech.formulate(bad, "gauss")
    with pytest.raises(Exception, match="mass matrix is singular or indefinite at this state"):
        form.accelerations(Q0, jnp.array([-0.5, 0.3, 1.0]))


def test_non_quadratic_kinetic_energy():
    with pytest.raises(ValueError, match="kinetic_energy is not quadratic"):
        mech.formulate(spec(kinetic_energy=lambda q, v, pi, t, p: 0.5 * v @ v + (v @ v) ** 2), "reduced", reference=Q0)


def test_dependent_velocity_choice_that_makes_b_prime_singular():
    s = ContactOscillator().spec()  # constraint ẋ + y ż = 0 has no ẏ
    with pytest.raises(ValueError, match=r"dependent=\('y',\) makes B' singular .* Choose other dependent"):
        mech.formulate(s, "reduced", dependent=("y",), reference=Q0)
    with pytest.raises(ValueError, match=r"dependent=\('z',\) makes B' singular"):
        mech.formulate(s, "reduced", dependent=("z",), reference=jnp.array([0.1, 0.0, 0.3]))  # y = 0: a_z = 0
    with pytest.raises(ValueError, match=r"expected 1 distinct names among the coordinates"):
        mech.formulate(s, "reduced", dependent=("x", "y"))
    with pytest.raises(ValueError, match="needs a reference configuration"):
        mech.formulate(s, "reduced")
    form = mech.formulate(s, "reduced", dependent=("z",))
    with pytest.raises(Exception, match="dependent-velocity choice makes B' singular at this state"):
        form.accelerations(jnp.array([0.1, 0.0, 0.3]), jnp.zeros(3))


@pytest.mark.parametrize(
    "field, fn",
    [
        ("kinetic_energy", lambda q, v, pi, t, p: 0.5 * float(v[0]) ** 2),
        ("potential", lambda q, pi, t, p: np.sin(q[0])),
        ("constraints", lambda q, pi, t, p: jnp.ones((1, 3)) if q[1] > 0 else jnp.zeros((1, 3))),
    ],
)
def test_functions_that_are_not_jax_traceable(field, fn):
    with pytest.raises(TypeError, match=rf"MechanicalSpec: {field}\(.*\) is not JAX-traceable"):
        spec(**{field: fn})


def test_other_misuse():
    with pytest.raises(TypeError, match="params=dict; expected an AbstractParameters"):
        spec(params={"mass": 1.0})
    with pytest.raises(ValueError, match="exactly one of kinetic_energy"):
        spec(mass_matrix=lambda q, pi, t, p: jnp.eye(3))
    with pytest.raises(ValueError, match="distinct non-empty names"):
        spec(coordinates=("x", "x", "z"))
    with pytest.raises(ValueError, match="route='lagrange'; allowed: reduced, hamiltonian, multipliers, gauss"):
        mech.formulate(spec(), "lagrange")
    with pytest.raises(ValueError, match="stabilization=1.0 applies to routes 'multipliers' and 'gauss' only"):
        mech.formulate(spec(), "reduced", dependent=("x",), stabilization=1.0)
    with pytest.raises(ValueError, match="needs ideal constraints"):
        mech.formulate(BeghinPlate(realisation="servo").spec(), "hamiltonian", dependent=("alpha",))
    with pytest.raises(ValueError, match="realisation='glue'"):
        BeghinPlate(realisation="glue")
    with pytest.raises(ValueError, match="route='voronets'"):
        VerticalRollingDisk(route="voronets")
    form = mech.formulate(spec(), "multipliers")
    with pytest.raises(ValueError, match=r"violates the constraints.*project_velocity"):
        form.state(Q0, jnp.ones(3))
    with pytest.raises(ValueError, match=r"q has shape \(2,\); expected \(3,\)"):
        form.accelerations(jnp.zeros(2), jnp.zeros(3))
    with pytest.raises(ValueError, match="eps=-1.0 is not allowed"):
        VerticalRollingDisk(eps=-1.0)


def test_the_spec_mass_matrix_form_is_equivalent():
    by_matrix = spec(kinetic_energy=None, mass_matrix=lambda q, pi, t, p: p.mass * jnp.eye(3, dtype=q.dtype))
    v = mech.project_velocity(by_matrix, Q0, jnp.array([0.3, -0.1, 0.7]))
    a = mech.formulate(by_matrix, "multipliers").accelerations(Q0, v)
    b = mech.formulate(spec(), "multipliers").accelerations(Q0, v)
    np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)


def test_parameters_are_leaves_that_gradients_reach():
    """∂q̈/∂m by autodiff through a route equals the finite difference (and ε, ν of scenes are leaves)."""
    s = VerticalRollingDisk(eps=0.3, nu=0.2).spec()
    q = jnp.array([0.0, 0.0, 0.2, 0.4])
    v = jnp.array([jnp.cos(0.4), jnp.sin(0.4), 1.0, 0.5])  # rolling at θ̇ = 1 (R = 1)

    @jax.jit
    def theta_ddot(eps):
        form = mech.formulate(eqx.tree_at(lambda sp: sp.params.eps, s, eps), "multipliers", dependent=("x", "y"))
        return form.accelerations(q, v)[2]

    grad = jax.jit(jax.grad(theta_ddot))(jnp.asarray(0.3))
    h = 1e-6
    fd = (theta_ddot(jnp.asarray(0.3 + h)) - theta_ddot(jnp.asarray(0.3 - h))) / (2 * h)
    assert abs(float(grad) + 2.0) < 1e-12  # θ̈ = −2ε θ̇ with θ̇ = 1: ∂/∂ε = −2
    np.testing.assert_allclose(grad, fd, rtol=1e-7)
