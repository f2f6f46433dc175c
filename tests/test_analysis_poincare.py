"""Poincaré sections of S2 (1.17)–(1.18): invariant curves of the integrable ball (Fig. 3), and the
attractor/repeller pair of the unbalanced ball in gravity swapped by the reversing involution (Fig. 7)."""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde.analysis as A
import nhsde.bodies as B
from nhsde.scenes import RollingBody


def test_andoyer_variables_round_trip():
    """S2 (1.17) puts the state on γ² = 1, (ω, γ) = 0 with G = |ω|, L = ω₃; ``andoyer`` inverts it."""
    L, G, l, g = 0.3, 1.7, -2.0, 1.1
    y = A.from_andoyer(L, G, l, g)
    assert abs(float(y[3:] @ y[3:]) - 1) < 1e-15 and abs(float(y[:3] @ y[3:])) < 1e-15
    np.testing.assert_allclose(A.andoyer(y), (L, G, l, g), atol=1e-14)


def test_fig3_integrable_ball_section_lies_on_invariant_curves():
    """Fig. 3 (I = (1, 2, 3), m = 1, R = 3, h = 10, g₀ = 0): every orbit's crossings lie on one level of F₂.

    All crossings are on the section (``E = h`` to 1e-10, ``g = g₀`` to 1e-10) and
    ``F₂ = (Jω × γ)²`` is constant along each orbit to 1e-9 while it ranges over
    more than 10 % between orbits: the section is foliated by the curves ``F₂ = c``.
    """
    scene = RollingBody(body=B.RigidBody(mass=1.0, inertia=(1.0, 2.0, 3.0), surface=B.Sphere(radius=3.0)))
    points = jnp.stack([jnp.linspace(0.3, 2.8, 6), jnp.linspace(-0.8, 0.8, 6)], axis=1)
    section = A.poincare_section(
        scene.vector_field, B.rolling_energy, scene.params, points, h=10.0, g0=0.0, n_crossings=30, dt=0.02
    )
    assert bool(jnp.all(section.valid))
    states = section.states
    energy = jax.vmap(jax.vmap(lambda y: B.rolling_energy(y, scene.params)))(states)
    _, _, _, g = jax.vmap(jax.vmap(A.andoyer))(states)
    assert float(jnp.max(jnp.abs(energy - 10.0))) < 1e-10 * 10.0
    assert float(jnp.max(jnp.abs(g))) < 1e-10
    f2 = jax.vmap(jax.vmap(lambda y: B.balanced_ball_integral(y, scene.params)))(states)
    spread = jnp.max(f2, axis=1) - jnp.min(f2, axis=1)
    assert float(jnp.max(spread / jnp.mean(f2, axis=1))) < 1e-9
    assert float(jnp.max(f2) - jnp.min(f2)) > 0.1 * float(jnp.mean(f2))


@pytest.fixture(scope="module")
def unbalanced_ball_in_gravity():
    """Fig. 7: I = (1, 2, 3), m = 1, R = 3, c = (1, 1.4, 0), g = 9.8, section h = 50, g₀ = π (S2 §A.3)."""
    body = B.RigidBody(mass=1.0, inertia=(1.0, 2.0, 3.0), surface=B.Sphere(radius=3.0, offset=(1.0, 1.4, 0.0)))
    return RollingBody(body=body, gravity=9.8)


def reflect(l, ratio):
    """R(0): ω → −ω acts on the section g₀ = π as (l, L/G) → (l + π, −L/G) (S2 (A.1.7), (A.1.9))."""
    return jnp.mod(l + jnp.pi, 2 * jnp.pi), -ratio


def test_fig7_reversibility_swaps_the_map_and_its_inverse(unbalanced_ball_in_gravity):
    """Φ⁻¹ ∘ R = R ∘ Φ: the inverse map from R(x) retraces R of the forward orbit from x.

    (From points in the regular regions: in the chaotic layers rounding errors
    grow to O(1) within 20 iterations.)  The attractor and repeller themselves:
    ``test_fig7_attractor_and_repeller_are_mirror_images`` (slow) and the notebook
    ``rubber_rolling_hierarchy.py``.
    """
    scene = unbalanced_ball_in_gravity
    points = jnp.array([[0.45, 0.85], [3.5, 0.58]])
    kw: dict[str, Any] = {"h": 50.0, "g0": np.pi, "n_crossings": 30, "dt": 0.02}
    forward = A.poincare_section(scene.vector_field, B.rolling_energy, scene.params, points, **kw)
    mirrored = jnp.stack(reflect(points[:, 0], points[:, 1]), axis=1)
    backward = A.poincare_section(scene.vector_field, B.rolling_energy, scene.params, mirrored, backward=True, **kw)
    l, ratio = reflect(forward.l, forward.ratio)
    dl = jnp.abs(jnp.mod(backward.l - l + jnp.pi, 2 * jnp.pi) - jnp.pi)
    assert float(jnp.max(dl)) < 1e-7 and float(jnp.max(jnp.abs(backward.ratio - ratio))) < 1e-7


@pytest.mark.slow
def test_fig7_attractor_and_repeller_are_mirror_images(unbalanced_ball_in_gravity):
    """An attractor of Φ near (l, L/G) ≈ (0.45, 0.87) and, found independently with Φ⁻¹, a repeller at its mirror image.

    Forward iterates from two starts and backward iterates from two other starts
    settle; R maps the backward limit set onto the forward one (every mirrored
    point within 0.05 of a forward point).  Phase volume contracts along the
    attractor (mean divergence λ < −0.005 over t = 150) and expands at the same
    rate along the repeller.
    """
    scene, p = unbalanced_ball_in_gravity, unbalanced_ball_in_gravity.params
    kw: dict[str, Any] = {"h": 50.0, "g0": np.pi, "n_crossings": 150, "dt": 0.02}
    forward = A.poincare_section(scene.vector_field, B.rolling_energy, p, jnp.array([[0.45, 0.85], [0.6, 0.75]]), **kw)
    backward = A.poincare_section(
        scene.vector_field, B.rolling_energy, p, jnp.array([[3.7, -0.8], [3.45, -0.92]]), backward=True, **kw
    )
    assert bool(jnp.all(forward.valid)) and bool(jnp.all(backward.valid))
    attractor = jnp.stack([forward.l[:, 75:].ravel(), forward.ratio[:, 75:].ravel()], axis=1)
    ml, mr = reflect(backward.l[:, 75:].ravel(), backward.ratio[:, 75:].ravel())
    mirrored = jnp.stack([ml, mr], axis=1)
    dist = jnp.min(jnp.linalg.norm(mirrored[:, None, :] - attractor[None, :, :], axis=-1), axis=1)
    assert float(jnp.max(dist)) < 0.05, float(jnp.max(dist))

    t1 = 150.0
    on_attractor = A.solve_flow(scene.vector_field, forward.states[:, -1], p, t1=t1, log_volume=True, n_save=2)
    on_repeller = A.solve_flow(scene.vector_field, backward.states[:, -1], p, t1=-t1, log_volume=True, n_save=2)
    rate_attractor = on_attractor.log_volume[:, -1] / t1
    rate_repeller = -on_repeller.log_volume[:, -1] / t1  # forward-time rate along the repeller
    print(
        f"mean divergence: attractor {np.round(np.asarray(rate_attractor), 4)}, repeller "
        f"{np.round(np.asarray(rate_repeller), 4)}; max mirrored distance {float(jnp.max(dist)):.3f}"
    )
    assert bool(jnp.all(rate_attractor < -0.005)), rate_attractor
    np.testing.assert_allclose(rate_repeller, -jnp.mean(rate_attractor), rtol=0.25)
