"""The stochastic system every part of nhsde consumes: S0 (1.15).

``dZ = a(Z, t; θ) dt + b(Z, t; θ) dW`` with ``W`` a standard Wiener process of
dimension ``noise_dim``.  S0 writes the noise as white noise ``V = dW/dt`` of
intensity ``ν``, ``E[V(t) V(s)ᵀ] = ν δ(t − s)``; nhsde folds ``√ν`` into ``b``,
so ``b`` here is S0's ``b·√ν`` and ``W`` has unit intensity.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._brownian import AbstractDriver, Wiener
from ._misc import real_state

__all__ = ["ROLES", "ItoStratonovichDrift", "StateLayout", "StochasticSystem"]

ROLES = (
    "random_parameter",  # π of S0 (1.2): shaping-filter states of coloured noise
    "independent_coordinate",  # q'
    "dependent_coordinate",  # q'': positions whose statistics are the drift
    "momentum",  # p' of the Hamiltonian form (1.13)
    "velocity",  # q̇' of the Lagrangian form (1.12)
)
_COORDINATES = ("independent_coordinate", "dependent_coordinate")


class StateLayout(eqx.Module):
    """Names and roles of the state components, in order.

    Arguments:
        names: one distinct name per state component.
        roles: one of :data:`ROLES` per component (``"dependent_coordinate"`` marks the ``q''`` whose statistics
            are the drift).
        angles: the coordinates the vector fields read through periodic functions (``sin``, ``cos``).  At a
            magnitude ``|θ|`` the precision resolves an angle to ``eps·|θ|`` only, and the rotation's gyroscopic
            terms carry rounding of that size relative: a path fails where an angle passes
            ``ANGLE_RESOLUTION / eps`` (8.4e3 rad in float32, 4.5e12 in float64).

    Examples:
        >>> import nhsde
        >>> layout = nhsde.StateLayout(("x", "u"), ("dependent_coordinate", "velocity"))
        >>> layout.size, layout.index("u"), layout.indices("dependent_coordinate")
        (2, 1, (0,))
    """

    names: tuple[str, ...]
    roles: tuple[str, ...]
    angles: tuple[str, ...] = ()

    def __check_init__(self):
        if len(self.names) != len(self.roles):
            raise ValueError(f"StateLayout: {len(self.names)} names but {len(self.roles)} roles.")
        for angle in self.angles:
            if angle not in self.names or self.roles[self.names.index(angle)] not in _COORDINATES:
                raise ValueError(f"StateLayout: angles={self.angles!r}; {angle!r} is not a coordinate of {self.names}.")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"StateLayout: duplicate state names in {self.names}.")
        for role in self.roles:
            if role not in ROLES:
                raise ValueError(f"StateLayout: unknown role {role!r}; roles are {ROLES}.")

    @property
    def size(self) -> int:
        return len(self.names)

    def indices(self, role: str) -> tuple[int, ...]:
        if role not in ROLES:
            raise ValueError(f"unknown role {role!r}; roles are {ROLES}.")
        return tuple(i for i, r in enumerate(self.roles) if r == role)

    def index(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"no state component {name!r}; the state is {self.names}.")
        return self.names.index(name)


VectorField = Callable[[Float[Array, ""], Float[Array, " d"], PyTree], Array]


class ItoStratonovichDrift(eqx.Module):
    """``a ∓ ½ Σ_j (∂b_j/∂Z) b_j``: Itô → Stratonovich (sign −1) or back (+1)."""

    drift: VectorField
    diffusion: VectorField
    sign: float

    def __call__(self, t, y, params):
        b = self.diffusion(t, y, params)
        # (∂b/∂Z · b)_i = Σ_{j,k} ∂b_ij/∂Z_k b_kj; jvp of Z ↦ b(Z) e_j along b_j per column.
        eye = jnp.eye(b.shape[1], dtype=b.dtype)
        cols = jax.vmap(lambda e, bj: jax.jvp(lambda z: self.diffusion(t, z, params) @ e, (y,), (bj,))[1])(eye, b.T)
        return self.drift(t, y, params) + self.sign * 0.5 * jnp.sum(cols, axis=0)


class StochasticSystem(eqx.Module):
    """An Itô (or Stratonovich) SDE ``dZ = a dt + b dW``, S0 (1.15).

    - ``drift(t, y, params) -> (d,)`` is ``a``; ``diffusion(t, y, params) -> (d, m)``
      is ``b`` (with S0's ``√ν`` folded in).  Both are pure functions with
      diffrax's ``f(t, y, args)`` signature; ``params`` is passed as ``args``.
    - ``params`` holds every physical parameter (``eps``, ``nu``, …) as a leaf.
    - ``layout`` names the state components and their roles (π, q', q'', p', q̇').
    - ``observables`` are extra named outputs ``f(t, y, params) -> ()`` computed
      from the state on request (e.g. the ball's angular velocity), so they cost
      no state.
    - ``noise`` is the driving process ``W`` (S0 (1.3)): :class:`~nhsde.noise.Wiener`
      by default (a normal system); drivers with jumps make Poisson or general systems.
    - ``linear_drift(params) -> A`` optionally names the stiff linear part of the
      drift ``a = A Z + N(Z)`` (viscous friction), for the exponential solver.
    - ``additive_noise`` declares that ``b`` does not depend on ``y``, which
      admits additive-noise solvers and makes Itô and Stratonovich coincide.

    Arguments:
        drift_fn: ``a(t, y, params) -> (d,)``, a pure function (static: give a module-level function, not one
            that closes over parameters).
        diffusion_fn: ``b(t, y, params) -> (d, noise_dim)``.
        params: a pytree of the physical parameters (usually an :class:`~nhsde.AbstractParameters`).
        layout: the :class:`StateLayout` of the ``d`` state components.
        noise_dim: the dimension ``m`` of ``W``.
        interpretation: ``"ito"`` or ``"stratonovich"``: the calculus ``drift_fn`` is written in.
        additive_noise: ``b`` does not depend on ``y``.
        observables: ``(name, f(t, y, params) -> ())`` pairs.
        noise: the driving process (default :class:`~nhsde.noise.Wiener`).
        linear_drift: ``params -> A`` of the linear part of the drift, or ``None``.

    Examples:
        The Ornstein–Uhlenbeck velocity ``du = −θ u dt + √ν dW``:

        >>> import jax.numpy as jnp
        >>> import nhsde
        >>> class OUParameters(nhsde.AbstractParameters):
        ...     theta: jnp.ndarray = nhsde.parameter(default=1.0, lower=0.0, doc="relaxation rate θ")
        ...     nu: jnp.ndarray = nhsde.parameter(default=1.0, lower=0.0, doc="noise intensity ν")
        >>> def drift(t, y, p):
        ...     return -p.theta * y
        >>> def diffusion(t, y, p):
        ...     return nhsde.sqrt_intensity(p.nu) * jnp.ones((1, 1), y.dtype)
        >>> system = nhsde.StochasticSystem(
        ...     drift_fn=drift,
        ...     diffusion_fn=diffusion,
        ...     params=OUParameters(theta=2.0),
        ...     layout=nhsde.StateLayout(("u",), ("velocity",)),
        ...     noise_dim=1,
        ...     additive_noise=True,
        ... )
        >>> system.state_dim, system.observable_names()
        (1, ('u',))
        >>> print(system.drift(0.0, jnp.array([0.5]), system.params))
        [-1.]
        >>> faster = system.replace_params(theta=4.0)
        >>> print(faster.drift(0.0, jnp.array([0.5]), faster.params))
        [-2.]
    """

    drift_fn: VectorField = eqx.field(static=True)
    diffusion_fn: VectorField = eqx.field(static=True)
    params: PyTree
    layout: StateLayout = eqx.field(static=True)
    noise_dim: int = eqx.field(static=True)
    interpretation: Literal["ito", "stratonovich"] = eqx.field(static=True, default="ito")
    additive_noise: bool = eqx.field(static=True, default=False)
    observables: tuple[tuple[str, Callable], ...] = eqx.field(static=True, default=())
    noise: AbstractDriver = Wiener()
    linear_drift: Callable | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.interpretation not in ("ito", "stratonovich"):
            raise ValueError(f"interpretation={self.interpretation!r}; allowed: 'ito' or 'stratonovich'.")
        if self.noise_dim < 1:
            raise ValueError(f"noise_dim={self.noise_dim}; must be ≥ 1.")
        clash = set(self.layout.names) & {name for name, _ in self.observables}
        if clash:
            raise ValueError(f"observable names {sorted(clash)} clash with state names.")

    @property
    def state_dim(self) -> int:
        return self.layout.size

    def state(self, y, name: str = "y0"):
        """``y`` as one floating-point state of this system; a wrong shape raises naming ``name``."""
        y = real_state(name, y)
        if y.shape != (self.state_dim,):
            raise ValueError(
                f"{name} has shape {y.shape}; expected ({self.state_dim},) for the state {self.layout.names}."
            )
        return y

    def drift(self, t, y, args):
        return self.drift_fn(t, y, args)

    def diffusion(self, t, y, args):
        return self.diffusion_fn(t, y, args)

    def observable_names(self) -> tuple[str, ...]:
        return self.layout.names + tuple(name for name, _ in self.observables)

    def observe(self, names: tuple[str, ...]) -> Callable:
        """``f(t, y, params) -> (len(names),)`` evaluating state components or observables."""
        table = dict(self.observables)
        for name in names:
            if name not in self.layout.names and name not in table:
                raise ValueError(f"save: unknown name {name!r}; this system offers {self.observable_names()}.")

        def fn(t, y, params):
            return jnp.stack(
                [y[self.layout.index(n)] if n in self.layout.names else table[n](t, y, params) for n in names]
            )

        return fn

    def converted(self, interpretation: Literal["ito", "stratonovich"]) -> StochasticSystem:
        """The same process written in the other calculus.

        Stratonovich drift = Itô drift − ½ Σ_j (∂b_j/∂Z) b_j (S0 §2, Remark).
        Additive noise needs no correction and returns ``self`` relabelled.
        """
        if interpretation not in ("ito", "stratonovich"):
            raise ValueError(f"interpretation={interpretation!r}; allowed: 'ito' or 'stratonovich'.")
        if interpretation == self.interpretation:
            return self
        if not self.noise.continuous:
            raise ValueError("a system driven by jumps has no Stratonovich form (S0 §2, Remark); use an Itô solver.")
        drift = self.drift_fn
        if not self.additive_noise:
            sign = -1.0 if interpretation == "stratonovich" else 1.0
            drift = ItoStratonovichDrift(self.drift_fn, self.diffusion_fn, sign)
        return dataclasses.replace(self, drift_fn=drift, interpretation=interpretation)

    def replace_params(self, **changes) -> StochasticSystem:
        """A copy with some physical parameters changed (``eps=…, nu=…``)."""
        return eqx.tree_at(lambda s: s.params, self, self.params.replace(**changes))
