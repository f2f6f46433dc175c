"""Surfaces by their inverse Gauss map, bodies, and bad input: clear errors or projections that report."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde.analysis as A
import nhsde.bodies as B
from nhsde.scenes import BodyOnVibratingPlane, RollingBody, stationary_nutation_density

DIRECTIONS = jnp.asarray(B.fibonacci_directions(64))

SURFACES = {
    "sphere": B.Sphere(radius=1.3, offset=(0.1, -0.2, 0.3)),
    "ellipsoid": B.Ellipsoid(semi_axes=(1.0, 1.5, 2.2), offset=(0.1, 0.0, -0.2)),
    "revolution": B.BodyOfRevolution(lambda u, s: s[0] + s[1] * u + s[2] * u**2, shape=(1.0, 0.2, 0.1)),
    "disk": B.Disk(radius=0.8, offset=(0.0, 0.0, 0.1)),
}


@pytest.mark.parametrize("name", list(SURFACES))
def test_gauss_map_normal_is_gamma_and_radii_are_non_negative(name):
    """S2 (1.5): dr ⊥ γ (the tangent plane at r(γ) is normal to γ), and the surface is convex."""
    surface = SURFACES[name]
    jac = jax.vmap(jax.jacfwd(surface.contact_point))(DIRECTIONS)
    assert float(jnp.max(jnp.abs(jnp.einsum("ni,nij->nj", DIRECTIONS, jac)))) < 1e-12
    radii = jax.vmap(surface.curvature_radii)(DIRECTIONS)
    assert float(jnp.min(radii)) > -1e-12


def test_closed_form_radii():
    """Sphere: both radii R; ellipsoid at the pole e₃: a₁²/a₃, a₂²/a₃; disk: 0 across the rim and R/sinθ along it."""
    np.testing.assert_allclose(SURFACES["sphere"].curvature_radii(DIRECTIONS[0]), [1.3, 1.3], rtol=1e-12)
    np.testing.assert_allclose(
        SURFACES["ellipsoid"].curvature_radii(jnp.array([0.0, 0.0, 1.0])), [1.0 / 2.2, 1.5**2 / 2.2], rtol=1e-12
    )
    g = jnp.array([np.sin(0.7), 0.0, np.cos(0.7)])
    np.testing.assert_allclose(B.Disk(radius=0.8).curvature_radii(g), [0.0, 0.8 / np.sin(0.7)], atol=1e-12)


def test_body_of_revolution_matches_the_sphere_it_describes():
    """A ball of radius R with the centre of mass c below its centre along e₃ has the profile Z(u) = R − c u."""
    profile = B.BodyOfRevolution(lambda u, s: s[0] - s[1] * u, shape=(1.3, 0.4))
    ball = B.Sphere(radius=1.3, offset=(0.0, 0.0, -0.4))
    np.testing.assert_allclose(
        jax.vmap(profile.contact_point)(DIRECTIONS), jax.vmap(ball.contact_point)(DIRECTIONS), rtol=1e-12, atol=1e-12
    )
    up = jnp.array([0.0, 0.0, 1.0])  # regular through the pole, where Euler angles are singular
    assert bool(jnp.all(jnp.isfinite(jax.jacfwd(jax.jacfwd(profile.contact_point))(up))))


def test_implicit_surface_matches_the_closed_form_with_derivatives():
    """f(x) = (x, B⁻¹x) − 1 solved by Newton's method: r(γ), ∂r/∂γ and ∂²r/∂γ² equal the ellipsoid's."""
    a = jnp.array([1.0, 1.5, 2.2])
    implicit = B.ImplicitSurface(lambda x, s: jnp.sum(x**2 / s**2) - 1.0, shape=a, size=3.0)
    exact = B.Ellipsoid(semi_axes=a)
    g = DIRECTIONS[:8]

    @jax.jit
    def derivatives(surface):
        r = jax.vmap(surface.contact_point)(g)
        d1 = jax.vmap(jax.jacfwd(surface.contact_point))(g)
        d2 = jax.vmap(jax.jacfwd(jax.jacfwd(surface.contact_point)))(g)
        return r, d1, d2

    for ours, theirs, tol in zip(derivatives(implicit), derivatives(exact), (1e-12, 1e-10, 1e-8)):
        np.testing.assert_allclose(ours, theirs, rtol=tol, atol=tol)


def test_non_convex_surfaces_are_refused():
    with pytest.raises(ValueError, match="not convex: parallel radius"):
        B.BodyOfRevolution(lambda u, s: 1.0 + 0.6 * u**4, shape=())  # waisted: parallels curve inwards
    with pytest.raises(ValueError, match="centre of mass must be inside"):
        B.BodyOfRevolution(lambda u, s: 0.2 - u, shape=())
    with pytest.raises(ValueError, match="convex"):  # waisted: no contact point (or a negative radius) somewhere
        B.ImplicitSurface(lambda x, s: x[0] ** 2 + x[1] ** 2 - 0.3 * x[2] ** 2 + 0.1 * x[2] ** 4 - 1.0, size=4.0)
    with pytest.raises(ValueError, match="f\\(0\\)"):
        B.ImplicitSurface(lambda x, s: 1.0 - jnp.sum(x**2), size=3.0)
    with pytest.raises(TypeError, match="height"):
        B.BodyOfRevolution(2.0)


def test_bad_bodies_are_refused():
    sphere = B.Sphere(radius=1.0)
    with pytest.raises(ValueError, match="not symmetric positive definite"):
        B.RigidBody(mass=1.0, inertia=(1.0, -2.0, 3.0), surface=sphere)
    with pytest.raises(ValueError, match="not symmetric positive definite"):
        B.RigidBody(mass=1.0, inertia=[[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], surface=sphere)
    with pytest.raises(ValueError, match="mass=0"):
        B.RigidBody(mass=0.0, inertia=(1.0, 1.0, 1.0), surface=sphere)
    with pytest.raises(ValueError, match="radius=-1"):
        B.Sphere(radius=-1.0)
    with pytest.raises(TypeError, match="surface"):
        B.RigidBody(mass=1.0, inertia=(1.0, 1.0, 1.0), surface="ball")
    with pytest.raises(ValueError, match="shape \\(2,\\)"):
        B.RigidBody(mass=1.0, inertia=(1.0, 1.0), surface=sphere)


def test_impossible_rolling_problems_are_refused():
    body = B.RigidBody(mass=1.0, inertia=(1.0, 2.0, 3.0), surface=B.Sphere(radius=1.0))
    with pytest.raises(ValueError, match="gravity=9.8 on a sphere"):
        RollingBody(body=body, curvature=0.5, gravity=9.8)
    with pytest.raises(ValueError, match="does not fit inside"):
        RollingBody(body=body, curvature=-2.0)  # a ball of radius 1 inside a shell of radius 0.5
    cavity = B.RigidBody(mass=1.0, inertia=(1.0, 2.0, 3.0), surface=B.SphericalCavity(radius=1.0))
    with pytest.raises(ValueError, match="SphericalCavity"):
        RollingBody(body=cavity)
    with pytest.raises(ValueError, match="contact='sliding'"):
        RollingBody(body=body, contact="sliding")
    with pytest.raises(ValueError, match="drift=True"):
        RollingBody(body=body, curvature=0.5, drift=True)


def test_initial_states_off_the_constraints_raise_or_are_projected_with_a_report():
    scene = RollingBody(body=B.RigidBody(mass=1.0, inertia=(1.0, 2.0, 3.0), surface=B.Sphere(radius=1.0)))
    with pytest.raises(ValueError, match="\\|γ\\| = 1: off by 0.1"):
        scene.initial_state([1.0, 0.0, 0.0], [0.0, 0.0, 1.1])
    with pytest.raises(ValueError, match="no-spin constraint"):
        scene.initial_state([1.0, 0.0, 0.5], [0.0, 0.0, 1.0])
    with pytest.warns(UserWarning, match="no-spin constraint.*correction 0.5"):
        y = scene.initial_state([1.0, 0.0, 0.5], [0.0, 0.0, 1.0], project=True)
    np.testing.assert_allclose(y, [1.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    classic = RollingBody(body=scene.params.body, contact="classic", drift=True)
    with pytest.raises(ValueError, match="pass alpha"):
        classic.initial_state([0.0, 0.0, 1.0], [0.0, 0.0, 1.0])
    with pytest.warns(UserWarning, match="\\(α, γ\\) = 0"):
        y = classic.initial_state([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], alpha=[1.0, 0.0, 0.2], project=True)
    np.testing.assert_allclose(y[6:], [1.0, 0.0, 0.0, 0.0, 0.0])
    disk = RollingBody(body=B.RigidBody(mass=1.0, inertia=(1.0, 1.0, 2.0), surface=B.Disk(radius=1.0)))
    with pytest.raises(ValueError, match="lies flat"):
        disk.initial_state([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])


def test_catalogue_formulas_refuse_the_wrong_body():
    y = jnp.array([0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
    unbalanced = RollingBody(
        body=B.RigidBody(mass=1.0, inertia=(1.0, 2.0, 3.0), surface=B.Sphere(radius=1.0, offset=(0.0, 0.0, 0.3)))
    )
    with pytest.raises(ValueError, match="balanced ball"):
        B.balanced_ball_measure(y, unbalanced.params)
    asymmetric = RollingBody(
        body=B.RigidBody(mass=1.0, inertia=(1.0, 2.0, 3.0), surface=B.Ellipsoid(semi_axes=(1.0, 1.0, 2.0)))
    )
    with pytest.raises(ValueError, match="dynamically symmetric"):
        B.revolution_measure(y, asymmetric.params)
    with pytest.raises(ValueError, match="I = μE"):
        B.spherical_inertia_measure(y, asymmetric.params)
    with pytest.raises(ValueError, match="z = 0 or I₁ = I₂"):
        B.flat_base_measure(jnp.zeros(4), B.FlatBaseParameters(inertia=(1.0, 2.0, 3.0), z=-0.5))
    vibrating = BodyOnVibratingPlane(body=asymmetric.params.body)
    with pytest.raises(ValueError, match="dynamically symmetric body of revolution"):
        stationary_nutation_density(vibrating.params, 0.3)


def test_rolling_field_is_differentiable_in_the_physical_parameters():
    """The vector field is a pure function of pytree parameters: jax.grad reaches mass, inertia and radius
    (checked against central finite differences)."""
    scene = RollingBody(
        body=B.RigidBody(mass=1.3, inertia=(1.0, 2.0, 3.0), surface=B.Sphere(radius=0.9, offset=(0.1, 0.0, 0.2))),
        gravity=9.8,
    )
    y = jnp.array([0.3, -0.2, 0.0, 0.0, 0.0, 1.0])
    y = y.at[:3].set(y[:3] - (y[:3] @ y[3:]) * y[3:])

    def out(radius):
        p = scene.params
        p = p.replace(body=p.body.replace(surface=p.body.surface.replace(radius=radius)))
        return jnp.sum(scene.vector_field(0.0, y, p)[:3] ** 2)

    h = 1e-6
    value_and_grad = jax.jit(jax.value_and_grad(out))
    fd = (value_and_grad(0.9 + h)[0] - value_and_grad(0.9 - h)[0]) / (2 * h)
    np.testing.assert_allclose(value_and_grad(0.9)[1], fd, rtol=1e-6)


def test_contact_point_drift_of_a_rolling_ball():
    """drift=True keeps α and the contact point: a homogeneous ball rolling about a horizontal axis moves its
    contact point along a straight line at speed R|ω| (classic rolling, S2 (1.4))."""
    radius, w = 0.7, 1.3
    scene = RollingBody(
        body=B.RigidBody(mass=1.0, inertia=(0.196, 0.196, 0.196), surface=B.Sphere(radius=radius)),
        contact="classic",
        gravity=9.8,
        drift=True,
    )
    assert scene.layout.names[6:] == ("alpha_1", "alpha_2", "alpha_3", "x", "y")
    assert scene.layout.indices("dependent_coordinate") == (9, 10)
    y0 = scene.initial_state([0.0, w, 0.0], [0.0, 0.0, 1.0], alpha=[1.0, 0.0, 0.0])
    flow = A.solve_flow(scene.vector_field, y0[None], scene.params, t1=10.0, n_save=3)
    np.testing.assert_allclose(flow.ys[0, :, 9], radius * w * flow.ts, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(flow.ys[0, :, 10], 0.0, atol=1e-12)
