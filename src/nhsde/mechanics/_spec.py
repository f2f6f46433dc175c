"""A natural mechanical system with linear constraints and random forcing: S0 (1.1)–(1.6).

Every function of a :class:`MechanicalSpec` is a pure JAX function that takes the
physical parameters ``p`` as its last argument (so gradients reach them; nothing
is closed over):

==================  ==============================  ===============================
field               signature                       meaning
==================  ==============================  ===============================
kinetic_energy      ``T(q, q̇, π, t, p) -> ()``      ``T``, quadratic in ``q̇``
mass_matrix         ``M(q, π, t, p) -> (n, n)``     or ``T = ½ q̇ᵀ M q̇``
potential           ``Π(q, π, t, p) -> ()``
dissipation         ``R(q, q̇, π, t, p) -> ()``      Rayleigh function
force               ``Q¹(q, q̇, π, t, p) -> (n,)``   disturbing forces (1.5)
noise_force         ``Q²(q, q̇, π, t, p) -> (n, l)`` random forces ``Q² V``, ``V`` white
constraints         ``a(q, π, t, p) -> (m, n)``     ``a q̇ + a0 = 0`` (1.1)
constraint_bias     ``a0(q, π, t, p) -> (m,)``
holonomic           ``f(q, π, t, p) -> (h,)``       ``f = 0``, S1 (1.1)
random_drift        ``φ(π, t, p) -> (k,)``          ``π̇ = φ + ψ V`` (1.2)
random_diffusion    ``ψ(π, t, p) -> (k, l)``
soft                :class:`SoftConstraint`         viscous contacts ``−γ Aᵀ A q̇``
temperature         ``kT(p) -> ()``                 a heat bath: fluctuation–dissipation noise
==================  ==============================  ===============================

``V`` is standard white noise (unit intensity): S0's intensity ``ν`` belongs in
``Q²`` and ``ψ`` as ``√ν``.  Controlled (parametric) constraints, S1 (1.1)–(1.2),
are constraints whose time dependence comes from a control ``u(t)``, e.g. a method
of the parameters: their rate ``u̇`` enters ``a0`` and ``ü`` the accelerations
(S1 (1.4)–(1.5), (2.4)) through automatic differentiation in ``t``.

The random parameters may enter ``Π``, ``R``, ``Q¹`` and ``Q²`` but not ``T`` or the
constraints: there S0 (1.8) needs the Itô correction ``Δσ`` (products of
differentials of ``∂T/∂q̇`` and ``B'``), which nhsde does not implement, so such
specs are refused.

Finite temperature (THEORY.md §8).  A constraint declared :class:`SoftConstraint` is no constraint: it is the
viscous contact force ``−γ Aᵀ A q̇`` (the Rayleigh function gains ``½ γ |A q̇|²``), so the velocities span all of
``q̇``.  A ``temperature`` ``kT`` puts the system in a heat bath: every dissipative channel gets its
fluctuation–dissipation noise, ``√(2kT) L dW`` with ``L Lᵀ = ∂²R/∂q̇²`` for the dissipation ``R`` (quadratic in
``q̇``) and ``√(2γkT) Aᵀ dW`` at the soft contacts, on channels after those of ``Q²``.  With soft contacts only and
``Q² = 0`` the system is an ordinary Langevin system whose stationary law is Gibbs, ``exp(−H/kT)``; with ideal
constraints and ``temperature`` it is the *naive* thermal model, whose noise reaches the friction but not the
constraint (Jagla, Bloch & Rojo, arXiv 2603.14424: at finite temperature it can violate the second law).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._misc import is_concrete
from .._params import AbstractParameters, sqrt_intensity
from . import _small as small
from ._dependence import depends_on

__all__ = ["MechanicalSpec", "ServoConstraint", "SoftConstraint"]


class ServoConstraint(eqx.Module):
    """Beghin servo-constraints ``c(q, π, t) q̇ + c0 = 0`` (S1 §3).

    They are kept by reactions ``Dᵀ μ`` of an energy source along the rows of
    ``realisation`` ``D(q, π, t, p) -> (s, n)``: the reactions do no work on the
    displacements with ``D δq = 0`` (S1 (3.2)) and, unlike ideal constraints,
    may work on those the constraint allows (S1 (3.1)).
    """

    matrix: Callable = eqx.field(static=True)
    realisation: Callable = eqx.field(static=True)
    bias: Callable | None = eqx.field(static=True, default=None)


class SoftConstraint(eqx.Module):
    """A constraint ``A(q, π, t) q̇ = 0`` realised by a viscous contact of viscosity ``γ`` (THEORY.md §8).

    Not a constraint: the contact force is ``−γ Aᵀ A q̇``, from the Rayleigh term ``½ γ |A q̇|²``, and in a bath
    of temperature ``kT`` (``MechanicalSpec(temperature=…)``) it comes with the noise ``√(2γkT) Aᵀ dW``.  As
    ``γ → ∞`` at ``kT = 0`` the ideal constraint returns, on the contact time scale ``m/γ`` (stiff).

    Arguments:
        matrix: ``A(q, π, t, p) -> (s, n)``, the rows of the constraint.
        viscosity: ``γ(p) -> ()``, the contact viscosity ``γ ≥ 0`` from the parameters (a leaf of ``p``).
    """

    matrix: Callable = eqx.field(static=True)
    viscosity: Callable = eqx.field(static=True)


_POSITION = "(q, pi, t, p)"
_VELOCITY = "(q, qdot, pi, t, p)"


def _traced_shape(name, signature, fn, args):
    try:
        out = jax.eval_shape(fn, *args)
    except Exception as e:  # the user's function failed to trace: say which one and why
        raise TypeError(
            f"MechanicalSpec: {name}{signature} is not JAX-traceable with q of shape {args[0].shape}: "
            f"{type(e).__name__}: {e}. Write it with jax.numpy on its arguments (no numpy, float() or "
            "Python branches on values)."
        ) from e
    if not hasattr(out, "shape"):
        raise TypeError(f"MechanicalSpec: {name}{signature} returned {type(out).__name__}; expected an array.")
    return tuple(out.shape)


def _expect(name, signature, shape, expected):
    if shape != expected:
        raise ValueError(f"MechanicalSpec: {name}{signature} returned shape {shape}; expected {expected}.")


class MechanicalSpec(eqx.Module):
    """Energies, constraints and forces of a nonholonomic system, S0 (1.1)–(1.6).

    ``coordinates`` names the generalised coordinates ``q``; ``random_parameters``
    names ``π``.  See the module docstring for the signature of each function.
    Shapes, traceability and the absence of ``π`` in the kinematics are checked
    when the spec is made; values (a positive-definite mass matrix, independent
    constraints) by :meth:`check` at a configuration.
    """

    coordinates: tuple[str, ...] = eqx.field(static=True)
    angles: tuple[str, ...] = eqx.field(static=True)  # coordinates read through sin/cos (StateLayout.angles)
    params: AbstractParameters
    kinetic_energy: Callable | None = eqx.field(static=True)
    mass_matrix: Callable | None = eqx.field(static=True)
    potential: Callable | None = eqx.field(static=True)
    dissipation: Callable | None = eqx.field(static=True)
    force: Callable | None = eqx.field(static=True)
    noise_force: Callable | None = eqx.field(static=True)
    constraints: Callable | None = eqx.field(static=True)
    constraint_bias: Callable | None = eqx.field(static=True)
    holonomic: Callable | None = eqx.field(static=True)
    servo: ServoConstraint | None = eqx.field(static=True)
    soft: SoftConstraint | None = eqx.field(static=True)
    temperature: Callable | None = eqx.field(static=True)
    random_parameters: tuple[str, ...] = eqx.field(static=True)
    random_drift: Callable | None = eqx.field(static=True)
    random_diffusion: Callable | None = eqx.field(static=True)
    n_ideal: int = eqx.field(static=True)  # rows of a plus holonomic constraints
    n_servo: int = eqx.field(static=True)
    noise_dim: int = eqx.field(static=True)  # l; one idle channel if nothing is random
    n_soft: int = eqx.field(static=True)  # rows of the soft constraints
    n_forced: int = eqx.field(static=True)  # channels of Q² and ψ; the bath's channels follow them

    def __init__(
        self,
        *,
        coordinates,
        params,
        angles=(),
        kinetic_energy=None,
        mass_matrix=None,
        potential=None,
        dissipation=None,
        force=None,
        noise_force=None,
        constraints=None,
        constraint_bias=None,
        holonomic=None,
        servo=None,
        soft=None,
        temperature=None,
        random_parameters=(),
        random_drift=None,
        random_diffusion=None,
    ):
        coordinates = tuple(coordinates)
        random_parameters = tuple(random_parameters)
        for label, names in (("coordinates", coordinates), ("random_parameters", random_parameters)):
            if not all(isinstance(c, str) and c for c in names) or len(set(names)) != len(names):
                raise ValueError(f"MechanicalSpec: {label}={names!r}; expected distinct non-empty names.")
        if not coordinates:
            raise ValueError("MechanicalSpec: coordinates=(); a system needs at least one coordinate.")
        angles = tuple(angles)
        if not set(angles) <= set(coordinates) or len(set(angles)) != len(angles):
            raise ValueError(f"MechanicalSpec: angles={angles!r}; expected distinct names among {coordinates}.")
        if not isinstance(params, AbstractParameters):
            raise TypeError(
                f"MechanicalSpec: params={type(params).__name__}; expected an AbstractParameters instance "
                "(physical constants as pytree leaves)."
            )
        if (kinetic_energy is None) == (mass_matrix is None):
            raise ValueError("MechanicalSpec: give exactly one of kinetic_energy=T(q, qdot, pi, t, p) or mass_matrix.")
        if servo is not None and not isinstance(servo, ServoConstraint):
            raise TypeError(f"MechanicalSpec: servo={type(servo).__name__}; expected a ServoConstraint.")
        if soft is not None and not isinstance(soft, SoftConstraint):
            raise TypeError(
                f"MechanicalSpec: soft={type(soft).__name__}; expected a SoftConstraint(matrix=A(q, pi, t, p), "
                "viscosity=gamma(p))."
            )
        functions = {
            "kinetic_energy": kinetic_energy,
            "mass_matrix": mass_matrix,
            "potential": potential,
            "dissipation": dissipation,
            "force": force,
            "noise_force": noise_force,
            "constraints": constraints,
            "constraint_bias": constraint_bias,
            "holonomic": holonomic,
            "random_drift": random_drift,
            "random_diffusion": random_diffusion,
            "temperature": temperature,
        }
        if servo is not None:
            functions.update(
                {"servo.matrix": servo.matrix, "servo.realisation": servo.realisation, "servo.bias": servo.bias}
            )
        if soft is not None:
            functions.update({"soft.matrix": soft.matrix, "soft.viscosity": soft.viscosity})
        for name, fn in functions.items():
            if fn is not None and not callable(fn):
                raise TypeError(f"MechanicalSpec: {name}={fn!r} is not callable.")
        if random_parameters and random_drift is None:
            raise ValueError("MechanicalSpec: random_parameters need random_drift=phi(pi, t, p) (S0 (1.2)).")
        if not random_parameters and (random_drift is not None or random_diffusion is not None):
            raise ValueError("MechanicalSpec: random_drift/random_diffusion given but random_parameters=().")
        if constraint_bias is not None and constraints is None:
            raise ValueError("MechanicalSpec: constraint_bias given without constraints.")
        self.coordinates = coordinates
        self.angles = angles
        self.params = params
        self.kinetic_energy = kinetic_energy
        self.mass_matrix = mass_matrix
        self.potential = potential
        self.dissipation = dissipation
        self.force = force
        self.noise_force = noise_force
        self.constraints = constraints
        self.constraint_bias = constraint_bias
        self.holonomic = holonomic
        self.servo = servo
        self.soft = soft
        self.temperature = temperature
        self.random_parameters = random_parameters
        self.random_drift = random_drift
        self.random_diffusion = random_diffusion
        self.n_ideal, self.n_servo, self.n_soft, self.n_forced, self.noise_dim = self._inspect()

    # ------------------------------------------------------------------ trace-time checks

    def _inspect(self):
        n, k = len(self.coordinates), len(self.random_parameters)
        q, v, pi = jnp.zeros(n), jnp.zeros(n), jnp.zeros(k)
        t, p = jnp.zeros(()), self.params
        pos, vel = (q, pi, t, p), (q, v, pi, t, p)
        if self.kinetic_energy is not None:
            _expect(
                "kinetic_energy", _VELOCITY, _traced_shape("kinetic_energy", _VELOCITY, self.kinetic_energy, vel), ()
            )
        else:
            _expect("mass_matrix", _POSITION, _traced_shape("mass_matrix", _POSITION, self.mass_matrix, pos), (n, n))
        for name, fn, args, sig in (
            ("potential", self.potential, pos, _POSITION),
            ("dissipation", self.dissipation, vel, _VELOCITY),
        ):
            if fn is not None:
                _expect(name, sig, _traced_shape(name, sig, fn, args), ())
        if self.force is not None:
            _expect("force", _VELOCITY, _traced_shape("force", _VELOCITY, self.force, vel), (n,))
        m = 0
        if self.constraints is not None:
            shape = _traced_shape("constraints", _POSITION, self.constraints, pos)
            if len(shape) != 2 or shape[1] != n:
                raise ValueError(
                    f"MechanicalSpec: constraints{_POSITION} returned shape {shape}; expected (m, {n}): "
                    f"one row a^κ of length n = {n} per constraint a^κ q̇ + a0^κ = 0."
                )
            m = shape[0]
            if self.constraint_bias is not None:
                _expect(
                    "constraint_bias",
                    _POSITION,
                    _traced_shape("constraint_bias", _POSITION, self.constraint_bias, pos),
                    (m,),
                )
        h = 0
        if self.holonomic is not None:
            shape = _traced_shape("holonomic", _POSITION, self.holonomic, pos)
            if len(shape) != 1:
                raise ValueError(f"MechanicalSpec: holonomic{_POSITION} returned shape {shape}; expected (h,).")
            h = shape[0]
        s = 0
        if self.servo is not None:
            shape = _traced_shape("servo.matrix", _POSITION, self.servo.matrix, pos)
            if len(shape) != 2 or shape[1] != n:
                raise ValueError(f"MechanicalSpec: servo.matrix{_POSITION} returned shape {shape}; expected (s, {n}).")
            s = shape[0]
            _expect(
                "servo.realisation",
                _POSITION,
                _traced_shape("servo.realisation", _POSITION, self.servo.realisation, pos),
                (s, n),
            )
            if self.servo.bias is not None:
                _expect("servo.bias", _POSITION, _traced_shape("servo.bias", _POSITION, self.servo.bias, pos), (s,))
        n_soft = 0
        if self.soft is not None:
            shape = _traced_shape("soft.matrix", _POSITION, self.soft.matrix, pos)
            if len(shape) != 2 or shape[1] != n:
                raise ValueError(f"MechanicalSpec: soft.matrix{_POSITION} returned shape {shape}; expected (s, {n}).")
            n_soft = shape[0]
            _expect("soft.viscosity", "(p)", _traced_shape("soft.viscosity", "(p)", self.soft.viscosity, (p,)), ())
        if self.temperature is not None:
            _expect("temperature", "(p)", _traced_shape("temperature", "(p)", self.temperature, (p,)), ())
        if m + h + s >= n:
            raise ValueError(
                f"MechanicalSpec: {m + h + s} constraints on {n} coordinates leave no motion; need fewer than n = {n}."
            )
        channels = None
        if self.noise_force is not None:
            shape = _traced_shape("noise_force", _VELOCITY, self.noise_force, vel)
            if len(shape) != 2 or shape[0] != n:
                raise ValueError(f"MechanicalSpec: noise_force{_VELOCITY} returned shape {shape}; expected ({n}, l).")
            channels = shape[1]
        if k:
            _expect(
                "random_drift",
                "(pi, t, p)",
                _traced_shape("random_drift", "(pi, t, p)", self.random_drift, (pi, t, p)),
                (k,),
            )
            if self.random_diffusion is not None:
                shape = _traced_shape("random_diffusion", "(pi, t, p)", self.random_diffusion, (pi, t, p))
                if len(shape) != 2 or shape[0] != k or (channels is not None and shape[1] != channels):
                    expected = f"({k}, {channels if channels is not None else 'l'})"
                    raise ValueError(
                        f"MechanicalSpec: random_diffusion(pi, t, p) returned shape {shape}; expected {expected} "
                        "(the same white noise V drives π and Q², S0 (1.2), (1.5))."
                    )
                channels = shape[1]
            kinematics = [
                ("kinetic_energy", self.kinetic_energy, vel),
                ("mass_matrix", self.mass_matrix, pos),
                ("constraints", self.constraints, pos),
                ("constraint_bias", self.constraint_bias, pos),
                ("holonomic", self.holonomic, pos),
            ]
            if self.soft is not None:
                kinematics.append(("soft.matrix", self.soft.matrix, pos))
            if self.servo is not None:
                kinematics += [
                    ("servo.matrix", self.servo.matrix, pos),
                    ("servo.bias", self.servo.bias, pos),
                    ("servo.realisation", self.servo.realisation, pos),
                ]
            for name, fn, args in kinematics:
                if fn is not None and depends_on(fn, args, len(args) - 3):
                    raise ValueError(
                        f"MechanicalSpec: {name} depends on the random parameters π. Then the Voronets "
                        "equations S0 (1.8) need the Itô correction Δσ = d(U1 U2) − U1 dU2 − U2 dU1 for "
                        "∂T/∂q̇ and B', which nhsde does not implement; let π enter only the potential, "
                        "dissipation and forces."
                    )
        forced = channels or 0
        bath = 0
        if self.temperature is not None:
            bath = (n if self.dissipation is not None else 0) + n_soft
        return m + h, s, n_soft, forced, (forced + bath) or 1

    # ------------------------------------------------------------------ evaluation

    @property
    def n(self) -> int:
        return len(self.coordinates)

    @property
    def k(self) -> int:
        return len(self.random_parameters)

    def kinetic(self, q, v, pi, t, p):
        """``T(q, q̇, π, t)``."""
        if self.kinetic_energy is not None:
            return self.kinetic_energy(q, v, pi, t, p)
        assert self.mass_matrix is not None  # exactly one of the two (checked when the spec is made)
        return 0.5 * v @ self.mass_matrix(q, pi, t, p) @ v

    def inertia(self, q, pi, t, p):
        """The mass matrix ``∂²T/∂q̇²``."""
        if self.mass_matrix is not None:
            return self.mass_matrix(q, pi, t, p)
        assert self.kinetic_energy is not None  # exactly one of the two (checked when the spec is made)
        return jax.hessian(self.kinetic_energy, argnums=1)(q, jnp.zeros_like(q), pi, t, p)

    def potential_energy(self, q, pi, t, p):
        return jnp.zeros((), q.dtype) if self.potential is None else self.potential(q, pi, t, p)

    def rayleigh(self, q, v, pi, t, p):
        """``R`` and, with soft constraints, the contacts' ``½ γ |A q̇|²``."""
        r = jnp.zeros((), q.dtype) if self.dissipation is None else self.dissipation(q, v, pi, t, p)
        if self.soft is None:
            return r
        slip = self.soft.matrix(q, pi, t, p) @ v
        return r + 0.5 * self.soft.viscosity(p) * (slip @ slip)

    def bath_force(self, q, pi, t, p):
        """The heat bath's random forces, ``(n, l_bath)``: ``√(2kT) L`` with ``L Lᵀ = ∂²R/∂q̇²`` (the dissipation
        ``R`` without the contacts), then ``√(2γkT) Aᵀ`` of the soft contacts; empty without a ``temperature``."""
        if self.temperature is None:
            return jnp.zeros((self.n, 0), q.dtype)
        root = sqrt_intensity(2 * self.temperature(p))
        columns = []
        if self.dissipation is not None:
            dissipation = self.dissipation
            friction = jax.hessian(lambda v: dissipation(q, v, pi, t, p))(jnp.zeros_like(q))
            columns.append(small.psd_factor(friction))
        if self.soft is not None:
            columns.append(jnp.sqrt(self.soft.viscosity(p)) * self.soft.matrix(q, pi, t, p).T)
        return root * jnp.concatenate(columns, axis=1).astype(q.dtype)

    def energy(self, q, v, pi, t, p):
        """Mechanical energy ``T + Π``."""
        return self.kinetic(q, v, pi, t, p) + self.potential_energy(q, pi, t, p)

    def disturbing_force(self, q, v, pi, t, p):
        """``Q¹``, shape ``(n,)``."""
        return jnp.zeros_like(q) if self.force is None else self.force(q, v, pi, t, p)

    def applied_force(self, q, v, pi, t, p):
        """``Q¹ − ∂Π/∂q − ∂R/∂q̇``: all deterministic generalised forces."""
        force = self.disturbing_force(q, v, pi, t, p)
        if self.potential is not None:  # without them the terms are zero: nothing to trace or differentiate
            force = force - jax.grad(self.potential_energy)(q, pi, t, p)
        if self.dissipation is not None or self.soft is not None:
            force = force - jax.grad(self.rayleigh, argnums=1)(q, v, pi, t, p)
        return force

    def random_force(self, q, v, pi, t, p):
        """``Q²``, shape ``(n, l)``, then the heat bath's channels (:meth:`bath_force`)."""
        if self.noise_force is None:
            forced = jnp.zeros((self.n, self.n_forced), q.dtype)
        else:
            forced = self.noise_force(q, v, pi, t, p)
        if self.temperature is None:
            return forced if self.n_forced else jnp.zeros((self.n, self.noise_dim), q.dtype)
        return jnp.concatenate([forced, self.bath_force(q, pi, t, p)], axis=1)

    def ideal_constraints(self, q, pi, t, p):
        """``(A, A0)``: the rows ``a, a0`` and the holonomic ones ``∂f/∂q, ∂f/∂t`` (S1 (1.4))."""
        rows, bias = [], []
        if self.constraints is not None:
            a = self.constraints(q, pi, t, p)
            rows.append(a)
            bias.append(
                jnp.zeros(a.shape[0], q.dtype) if self.constraint_bias is None else self.constraint_bias(q, pi, t, p)
            )
        if self.holonomic is not None:
            f_q, f_t = jax.jacfwd(self.holonomic, argnums=(0, 2))(q, pi, t, p)
            rows.append(f_q)
            bias.append(f_t)
        if not rows:
            return jnp.zeros((0, self.n), q.dtype), jnp.zeros(0, q.dtype)
        return jnp.concatenate(rows), jnp.concatenate(bias)

    def holonomic_residual(self, q, pi, t, p):
        """``f(q, t)`` for the holonomic rows of :meth:`ideal_constraints`, zero for the others."""
        f = jnp.zeros(0, q.dtype) if self.holonomic is None else self.holonomic(q, pi, t, p)
        return jnp.concatenate([jnp.zeros(self.n_ideal - f.shape[0], q.dtype), f])

    def servo_constraints(self, q, pi, t, p):
        """``(C, C0, D)`` of the servo-constraints (empty if none)."""
        if self.servo is None:
            empty = jnp.zeros((0, self.n), q.dtype)
            return empty, jnp.zeros(0, q.dtype), empty
        c = self.servo.matrix(q, pi, t, p)
        c0 = jnp.zeros(c.shape[0], q.dtype) if self.servo.bias is None else self.servo.bias(q, pi, t, p)
        return c, c0, self.servo.realisation(q, pi, t, p)

    def velocity_constraints(self, q, pi, t, p):
        """All rows the velocities obey, ideal then servo: ``(A; C) q̇ + (A0; C0) = 0``."""
        a, a0 = self.ideal_constraints(q, pi, t, p)
        c, c0, _ = self.servo_constraints(q, pi, t, p)
        return jnp.concatenate([a, c]), jnp.concatenate([a0, c0])

    def displacement_constraints(self, q, pi, t, p):
        """Rows the virtual displacements obey: ideal, then the servo realisation (S1 (3.2))."""
        a, _ = self.ideal_constraints(q, pi, t, p)
        _, _, d = self.servo_constraints(q, pi, t, p)
        return jnp.concatenate([a, d])

    def constraint_residual(self, q, v, pi, t, p):
        """``(A; C) q̇ + (A0; C0)``; zero on the real motion."""
        rows, bias = self.velocity_constraints(q, pi, t, p)
        return small.matmul(rows, v) + bias

    def pi_drift(self, pi, t, p):
        if self.random_drift is None:  # no random parameters (they need a drift): π is empty
            return jnp.zeros(self.k, pi.dtype)
        return self.random_drift(pi, t, p)

    def pi_diffusion(self, pi, t, p):
        if self.random_diffusion is None:
            return jnp.zeros((self.k, self.noise_dim), pi.dtype)
        psi = self.random_diffusion(pi, t, p)
        return jnp.pad(psi, ((0, 0), (0, self.noise_dim - psi.shape[1])))  # the bath does not drive π

    # ------------------------------------------------------------------ value checks

    def check(self, q, pi=None, t=0.0):
        """Check the spec's values at configuration ``q``; ``ValueError`` naming the problem.

        The mass matrix must be symmetric positive definite, ``T`` quadratic in
        ``q̇`` (a natural system), and the constraint rows (ideal, servo, and the
        servo realisation) independent.
        """
        q = jnp.asarray(q)
        if q.shape != (self.n,):
            raise ValueError(f"check: q has shape {q.shape}; expected ({self.n},) for coordinates {self.coordinates}.")
        pi = jnp.zeros(self.k, q.dtype) if pi is None else jnp.asarray(pi, q.dtype)
        t = jnp.asarray(t, q.dtype)
        p = self.params
        if not is_concrete(q, pi, t, p):  # built inside a transform: checked where its values are known
            return
        mass = np.asarray(self.inertia(q, pi, t, p))
        if not np.all(np.isfinite(mass)) or not np.allclose(mass, mass.T, rtol=1e-10, atol=1e-12 * np.abs(mass).max()):
            raise ValueError(f"mass matrix at q={np.asarray(q).tolist()} is not finite and symmetric:\n{mass}")
        eig = np.linalg.eigvalsh(mass)
        if eig[0] <= 1e-12 * max(abs(eig[-1]), 1e-300):
            raise ValueError(
                f"mass matrix at q={np.asarray(q).tolist()} is singular or indefinite (eigenvalues "
                f"{eig.tolist()}); every coordinate needs positive inertia."
            )
        if self.kinetic_energy is not None:
            v = jax.random.normal(jax.random.key(0), (self.n,), q.dtype)
            t0 = self.kinetic(q, jnp.zeros_like(v), pi, t, p)
            t1 = jax.grad(self.kinetic, argnums=1)(q, jnp.zeros_like(v), pi, t, p) @ v
            quadratic = t0 + t1 + 0.5 * v @ jnp.asarray(mass, q.dtype) @ v
            actual = self.kinetic(q, v, pi, t, p)
            if not np.isclose(float(actual), float(quadratic), rtol=1e-6, atol=1e-12):
                raise ValueError(
                    f"kinetic_energy is not quadratic in q̇ at q={np.asarray(q).tolist()} "
                    f"(T(v)={float(actual):g}, its quadratic part {float(quadratic):g}); S0 treats natural systems."
                )
        if self.temperature is not None or self.soft is not None:
            self._check_bath(q, pi, t, p)
        for label, rows in (
            ("constraint matrix (ideal and servo rows)", self.velocity_constraints(q, pi, t, p)[0]),
            ("virtual-displacement rows (ideal and servo realisation)", self.displacement_constraints(q, pi, t, p)),
        ):
            rows = np.asarray(rows)
            if rows.shape[0] == 0:
                continue
            sv = np.linalg.svd(rows, compute_uv=False)
            rank = int(np.sum(sv > 1e-10 * sv[0])) if sv[0] > 0 else 0
            if rank < rows.shape[0]:
                raise ValueError(
                    f"{label} at q={np.asarray(q).tolist()} has rank {rank} < {rows.shape[0]} rows: the constraints "
                    f"are not independent (singular values {sv.tolist()}); remove the redundant rows."
                )

    def _check_bath(self, q, pi, t, p):
        """``kT ≥ 0``, ``γ ≥ 0`` and, in a bath, ``R`` quadratic in ``q̇``: its noise is ``√(2kT) L``,
        ``L Lᵀ = ∂²R/∂q̇²``."""
        for name, fn in (("temperature", self.temperature), ("soft.viscosity", self.soft and self.soft.viscosity)):
            if fn is not None:
                value = float(fn(p))
                if not np.isfinite(value) or value < 0:
                    raise ValueError(f"MechanicalSpec: {name}(p) = {value}; must be finite and ≥ 0.")
        if self.temperature is None or self.dissipation is None:
            return
        dissipation = self.dissipation
        v = jax.random.normal(jax.random.key(1), (self.n,), q.dtype)
        friction = jax.hessian(lambda v: dissipation(q, v, pi, t, p))(jnp.zeros_like(v))
        actual, quadratic = float(dissipation(q, v, pi, t, p)), float(0.5 * v @ friction @ v)
        if not np.isclose(actual, quadratic, rtol=1e-6, atol=1e-12):
            raise ValueError(
                f"MechanicalSpec: dissipation is not quadratic in q̇ at q={np.asarray(q).tolist()} (R(v)={actual:g}, "
                f"½ vᵀ(∂²R/∂q̇²)v = {quadratic:g}); a temperature gives it the noise of covariance 2kT ∂²R/∂q̇², "
                "which needs R = ½ q̇ᵀ C(q) q̇."
            )
