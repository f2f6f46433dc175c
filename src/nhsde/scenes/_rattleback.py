"""The rattleback (celt): an ellipsoid with skewed inertia rolling without slipping on a plane, S4 Remark 4.4.

Kane & Levinson's body (Int. J. Non-Linear Mech. 17 (1982) 175) held as a classic
:class:`~nhsde.scenes.RollingBody`: semi-axes ``a, b, c``, centre of mass a
distance ``h`` below the centre on the ``c`` axis, central moments ``A, B, C``
about the ``a, b, c`` axes and the product of inertia ``D`` in the ``a``–``b`` plane.

Axes.  Kane & Levinson's ``b₃`` points from the centre to the contact point at
rest (down), with the centre of mass at ``+h b₃``; their ``D`` is the entry of the
inertia matrix (kinetic energy ``½(Aω₁² + Bω₂² + Cω₃² + 2Dω₁ω₂)``, i.e.
``D = −∫x₁x₂ dm``).  The library's axes have ``e₃ = γ`` up at rest:
``e₁ = b₁``, ``e₂ = −b₂``, ``e₃ = −b₃`` (the half turn about the long axis), so

    I = [[A, −D, 0], [−D, B, 0], [0, 0, C]],   c_offset = (0, 0, −h),   ω₃ = −ω₃^{KL}.

``ω₃ > 0`` in the library's axes is a counter-clockwise spin seen from above.

Steady spin ``ω = nγ, γ = e₃`` (S4 (4.10)): the linearisation in ``(ω, γ) ∈ ℝ⁶``
has two zero roots (the family is two-dimensional: the spin rate ``n`` and the
scale ``|γ|``; equivalently the first integrals ``E`` and ``γ²``) and four
others, the roll (≈ 34 rad/s) and pitch (≈ 107 rad/s) oscillations.  The
field is reversible (``(ω, γ, t) → (−ω, γ, −t)``), so the four roots at ``−n``
are minus those at ``n`` (S4 Remark 4.4).  Growth rates ``max Re μ`` (1/s) for
Kane & Levinson's parameters:

    |n| (rad/s)            1       2       5       10
    counter-clockwise    0.426   0.851   2.121   4.193   (pitch grows, roll decays)
    clockwise            0.042   0.084   0.203   0.357   (roll grows, pitch decays)

Both senses are linearly unstable (without dissipation the spin reverses
either way, again and again); counter-clockwise ten times faster: the pitching
"rattle" and reversal within seconds.  Other parameters (e.g. ``A = 8e-4``,
``c = 0.025``, ``h = 0.005``) make a fast clockwise spin asymptotically stable.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._misc import is_concrete
from ..bodies import Ellipsoid, RigidBody, RollingField, RollingParameters
from ._base import AbstractRollingBodyScene
from ._rolling import RollingBody

__all__ = ["Rattleback"]


class Rattleback(AbstractRollingBodyScene):
    """Kane & Levinson's rattleback rolling without slipping (classic contact) on a horizontal plane.

    Keyword arguments in Kane & Levinson's form (SI units): ``semi_axes = (a, b, c)``,
    ``height = h`` (centre of mass below the centre), ``mass``, ``inertia = (A, B, C)``
    central moments, ``product = D`` their product of inertia, ``gravity``.  They
    become the leaves of :class:`~nhsde.bodies.RollingParameters`, with the inertia
    matrix ``[[A, −D, 0], [−D, B, 0], [0, 0, C]]`` in the library's axes (module docstring).
    The scene holds that :class:`~nhsde.scenes.RollingBody` (``rolling``) and adds :meth:`spin`.
    """

    rolling: RollingBody

    def __init__(
        self,
        *,
        semi_axes=(0.2, 0.03, 0.02),
        height=0.01,
        mass=1.0,
        inertia=(2e-4, 1.6e-3, 1.7e-3),
        product=-2e-5,
        gravity=9.81,
    ):
        semi_axes, height, product = jnp.asarray(semi_axes), jnp.asarray(height), jnp.asarray(product)
        inertia = jnp.asarray(inertia)
        if inertia.shape != (3,):
            raise ValueError(f"Rattleback: inertia has shape {inertia.shape}; expected the (3,) moments (A, B, C).")
        if is_concrete(semi_axes, height) and semi_axes.shape == (3,) and not abs(float(height)) < float(semi_axes[2]):
            raise ValueError(
                f"Rattleback: height={float(height):g}; the centre of mass must lie inside the body, "
                f"|height| < c = {float(semi_axes[2]):g}."
            )
        zero = jnp.zeros_like(product)
        matrix = jnp.stack(
            [
                jnp.stack([inertia[0], -product, zero]),
                jnp.stack([-product, inertia[1], zero]),
                jnp.stack([zero, zero, inertia[2]]),
            ]
        )
        offset = jnp.stack([jnp.zeros_like(height), jnp.zeros_like(height), -height])
        body = RigidBody(mass=mass, inertia=matrix, surface=Ellipsoid(semi_axes=semi_axes, offset=offset))
        self.rolling = RollingBody(body=body, contact="classic", gravity=gravity)

    @property
    def params(self) -> RollingParameters:
        return self.rolling.params

    @property
    def vector_field(self) -> RollingField:
        return self.rolling.vector_field

    def energy(self, y):
        """``E = ½(ω, Ĩω) + U(γ)``."""
        return self.rolling.energy(y)

    def initial_state(self, omega, gamma, *, project: bool = False):
        """The state ``(ω, γ)``, checked as by :meth:`RollingBody.initial_state`."""
        return self.rolling.initial_state(omega, gamma, project=project)

    def spin(self, n, tilt=0.0, azimuth=0.0):
        """The state ``(ω, γ) = (nγ, γ)``: spin ``n`` about the vertical, the ``c`` axis tilted by ``tilt``.

        ``γ = (sin θ cos φ, sin θ sin φ, cos θ)`` in the body axes, ``θ = tilt``,
        ``φ = azimuth`` (``0``: the long axis ``a`` dips, a pitch; ``π/2``: a roll).
        ``tilt = 0`` is the steady spin; ``n > 0`` is counter-clockwise seen from above.  The body turns
        about the vertical through the contact point, which a pitch tilt moves by ``(a²/c)·tilt``
        (2 m × tilt here): keep ``|n|·(a²/c)·tilt`` small for a small perturbation.
        """
        dtype = jnp.result_type(float)  # float64 under jax_enable_x64, else float32
        n, tilt, azimuth = (jnp.asarray(x, dtype) for x in (n, tilt, azimuth))
        gamma = jnp.stack([jnp.sin(tilt) * jnp.cos(azimuth), jnp.sin(tilt) * jnp.sin(azimuth), jnp.cos(tilt)])
        return jnp.concatenate([n * gamma, gamma])
