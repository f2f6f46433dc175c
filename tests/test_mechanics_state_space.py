"""Ding's state-space equations (S3): singular for S3's constrained point, with the rank S3 §4.2 predicts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nhsde import AbstractParameters, mechanics as mech, parameter
from nhsde.scenes import ContactOscillator


def _point_states(spec, key, n=5):
    kq, kv = jax.random.split(key)
    qs, raw = jax.random.normal(kq, (n, spec.n)), jax.random.normal(kv, (n, spec.n))
    return qs, jax.jit(jax.vmap(lambda q, v: mech.project_velocity(spec, q, v)))(qs, raw)


@pytest.mark.parametrize("gravity", [0.0, 9.81])
def test_constrained_point_is_singular_with_rank_s_minus_g(gravity):
    """A unit-mass point with ẋ + y ż = 0, free or in gravity: S = 6 − 1 = 5, rank M_αβ = S − g = 4, and the
    (2n + g) = 7 multiplier equations (25) have rank 6 (their λ-column is orthogonal to every row)."""
    spec = ContactOscillator(eps=0.0, nu=0.0, mass=1.0, stiffness=0.0, gravity=gravity).spec()
    space = mech.state_space(spec, dependent=("x",))
    for q, v in zip(*_point_states(spec, jax.random.key(1))):
        report = space.report(q, v)
        assert (report.S, report.g, report.rank_brackets) == (5, 1, 0)
        assert report.rank_generalised == 4 and report.singular
        assert report.rank_multiplier == 6
        sv = report.singular_values
        assert sv[-1] < 1e-12 * sv[0] and sv[-2] > 1e-3 * sv[0]  # one clean zero, not a near-miss
        m_gen, _ = space.generalised_system(jnp.concatenate([q, v[1:]]))
        np.testing.assert_allclose(m_gen, -m_gen.T, atol=1e-14)  # M_αβ antisymmetric (S3 §4.2)
        matrix, _ = space.multiplier_system(q, v)
        np.testing.assert_allclose(matrix, -matrix.T, atol=1e-14)
    with pytest.raises(mech.SingularStateSpaceError, match=r"rank M_αβ = 4 < S = 5"):
        space.velocity(jnp.concatenate([q, v[1:]]))


class TwoConstraintParameters(AbstractParameters):
    mass: jnp.ndarray = parameter(default=1.0, lower=0.0, strict=True)


def _unit_kinetic(q, v, pi, t, p):
    return 0.5 * p.mass * v @ v


def _two_rows(q, pi, t, p):
    one, zero = jnp.ones((), q.dtype), jnp.zeros((), q.dtype)
    return jnp.stack([jnp.stack([one, zero, q[1]]), jnp.stack([zero, one, -q[0]])])


def test_rank_follows_the_brackets_of_the_constraints():
    """Constraints ẋ + y ż = 0, ẏ − x ż = 0 have the bracket {Φ₁, Φ₂} = 2ż/m ≠ 0: rank M = S − g + rank C
    = 4 − 2 + 2 = 4, so these state-space equations are regular and solvable — and differ from nonholonomic
    mechanics: the reactions act in velocity space too, so q̇ ≠ v (S3 (25))."""
    spec = mech.MechanicalSpec(
        coordinates=("x", "y", "z"),
        params=TwoConstraintParameters(),
        kinetic_energy=_unit_kinetic,
        constraints=_two_rows,
    )
    space = mech.state_space(spec, dependent=("x", "y"))
    q, v = (a[0] for a in _point_states(spec, jax.random.key(3), n=1))
    report = space.report(q, v)
    assert (report.S, report.g, report.rank_brackets, report.rank_generalised) == (4, 2, 2, 4)
    assert not report.singular and report.rank_multiplier == 8
    xi = jnp.concatenate([q, v[2:]])
    xi_dot = space.velocity(xi)
    m_gen, k = space.generalised_system(xi)
    np.testing.assert_allclose(m_gen @ xi_dot, k, atol=1e-12)
    (_, v_now), (q_dot, _) = jax.jvp(space.manifold_point, (xi, jnp.zeros(())), (xi_dot, jnp.ones(())))
    assert float(jnp.max(jnp.abs(q_dot - v_now))) > 1e-6


def test_state_space_refuses_random_parameters():
    spec = mech.MechanicalSpec(
        coordinates=("x", "y", "z"),
        params=TwoConstraintParameters(),
        kinetic_energy=_unit_kinetic,
        constraints=_two_rows,
        random_parameters=("pi",),
        random_drift=lambda pi, t, p: -pi,
    )
    with pytest.raises(ValueError, match="S3 treats deterministic systems"):
        mech.state_space(spec, dependent=("x", "y"))
