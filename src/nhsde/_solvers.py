"""Solvers: nhsde's own, the string aliases, and what any diffrax SDE solver needs, read from its type.

``simulate`` takes any diffrax SDE solver object (``diffrax.Euler()``,
``diffrax.ShARK()``, ``diffrax.SlowRK()``, …) or nhsde's own; its needs come from
diffrax's types: an ``AbstractItoSolver`` converges to the Itô solution, an
``AbstractStratonovichSolver`` to the Stratonovich one (the system is converted
first, S0 §2 Remark), a stochastic Runge–Kutta method whose tableau is for
additive noise needs additive noise (and then both calculi agree), and
``minimal_levy_area`` says which Lévy area the driver must draw.  The strings
of :data:`SOLVERS` are aliases for the CLI and run files.

:class:`ExponentialEuler` treats the stiff linear part ``A`` of the drift
``a(Z) = A Z + N(Z)`` (viscous friction, a soft contact) exactly, its noise included:

    Z_{n+1} = e^{Ah} Z_n + h φ₁(Ah) N(Z_n) + C ΔW_n,   C Cᵀ h = Σ_h = ∫₀ʰ e^{As} b bᵀ e^{Aᵀs} ds,   φ₁(x) = (e^x − 1)/x,

so a dissipative ``A`` stays stable for any ``λh`` (Euler–Maruyama needs ``λh < 2``), and a mode of any rate keeps
its stationary variance (``u̇ = −2εu + σV``: ``σ²/(4ε)`` at every ``εh``; Euler–Maruyama's noise ``φ₁(Ah) b ΔW``
gave ``σ²/(4ε)·tanh(εh)/(εh)``, a cold stiff contact).  ``C = φ₁(Ah) b + O(h²)``: strong order 1 for additive
noise (0.5 in general), Euler–Maruyama as ``A → 0``.  Exact in law for the linear flow wherever it keeps the noise
in the span of ``φ₁(Ah) b`` (``A`` acting on the noisy velocities: friction and contact damping); where ``A`` also
moves noiseless coordinates (the ball's ``ẋ = u``) ``C Cᵀ h`` is ``Σ_h`` projected on that span, an ``O(h³)``
error per step at small ``h``.  ``e^{Ah}``, ``hφ₁(Ah)`` and the map ``Q ↦ Σ_h`` depend on the parameters and the
step only: ``init`` computes them once per solve (in float64 where enabled), and ``C`` too for additive noise.

Every solver :func:`solver_needs` returns differentiates in forward and reverse mode alike (``jax.jacfwd``,
``jax.grad``, the estimators' ``wrt``): diffrax's explicit Runge–Kutta stages run as a scan of the stage count
(``scan_kind='bounded'``; ``'lax'`` is a while loop, forward mode only, and the default ``'checkpointed'`` reverse
mode only), a stochastic Runge–Kutta method's as a ``lax.scan`` (``'lax'``); and a step whose result is not
finite (or not successful), which ``simulate`` discards with its path, is linearised at the origin instead of at
its state, so that in reverse mode the discarded path's zero cotangent meets finite partial derivatives, not
overflowed ones (``0·∞ = nan``: ``dx = a x² dt`` from ``x = 10`` overflows ``∂x₁/∂a = h x²``).  The step's value,
and its derivative wherever it succeeds, are unchanged.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import ClassVar, Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ._system import StochasticSystem
from ._weak import WEAK_INCREMENTS, PlatenWeak2
from .mechanics._small import psd_factor

__all__ = ["SOLVERS", "ExponentialEuler", "SolverNeeds", "expm", "linear_flow", "solver_needs"]


class _LinearFlow(eqx.Module):
    """What :class:`ExponentialEuler` needs of the linear flow ``e^{As}`` over one step ``h``, once per solve.

    ``propagator = e^{Ah}``, ``h_phi = h φ₁(Ah)`` (one ``expm`` of ``[[A h, h I], [0, 0]]``), ``gram`` the linear map
    ``vec Q ↦ vec Σ_h = ∫₀ʰ (e^{As} ⊗ e^{As}) ds vec Q`` (the top right block of one ``expm`` of
    ``[[(A ⊕ A) h, h I], [0, 0]]``, ``A ⊕ A = A ⊗ I + I ⊗ A``: only the decaying ``e^{As}``, no ``e^{−Ah}``), and the
    noise factor ``noise`` when the noise is additive (else ``None``, computed per step).  Computed in float64 where
    JAX has it: in float32 ``b bᵀ`` of a stiff contact (``√γ`` in ``b``) loses the slow modes' part of ``Q``.
    """

    h: Array
    propagator: Array
    h_phi: Array
    gram: Array
    noise: Array | None


def _wide(dtype):
    """The precision of the once-per-solve matrices: float64 where enabled, else the state's."""
    return jnp.float64 if jax.config.read("jax_enable_x64") else dtype


MAX_SQUARINGS = 64
"""Squarings :func:`expm` may take: its Taylor series is summed at ``‖m‖₁/2^s ≤ 1``, so up to ``‖m‖₁ = 2⁶⁴``."""

EXPM_DEGREE = 18
"""Degree of :func:`expm`'s Taylor polynomial: its remainder at norm ≤ 1 is below ``1/19! ≈ 8·10⁻¹⁸``."""


def expm(m: Array) -> Array:
    """``e^m`` of a small matrix by scaling and squaring: the Taylor polynomial of ``m/2^s`` (Horner's rule), squared
    ``s = ⌈log₂ ‖m‖₁⌉`` times.  Two short loops with static trip counts (the squarings beyond ``s`` skipped), so it
    compiles to two small kernels and differentiates in both modes; ``jax.scipy.linalg.expm``'s choice among five
    Padé degrees compiles every branch (3× this compile time, measured on its gradient)."""
    norm = jax.lax.stop_gradient(jnp.max(jnp.sum(jnp.abs(m), axis=0)))  # s sets the method, not the value
    s = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1.0))), 0, MAX_SQUARINGS).astype(jnp.int32)
    x = m / jnp.exp2(s.astype(m.dtype))
    eye = jnp.eye(m.shape[0], dtype=m.dtype)

    def horner(acc, k):  # acc ← I + x acc / k, for k = degree … 1
        return eye + (x @ acc) / k.astype(m.dtype), None

    e = jax.lax.scan(horner, eye, jnp.arange(EXPM_DEGREE, 0, -1))[0]
    square = lambda e, i: (jax.lax.cond(i < s, lambda e: e @ e, lambda e: e, e), None)  # noqa: E731
    return jax.lax.scan(square, e, jnp.arange(MAX_SQUARINGS, dtype=jnp.int32))[0]


def linear_flow(a: Array, h: Array, b: Array | None, dtype) -> _LinearFlow:
    wide = _wide(dtype)
    a, hw = a.astype(wide), jnp.asarray(h).astype(wide)
    d = a.shape[0]
    e = expm(jnp.block([[a * hw, hw * jnp.eye(d, dtype=wide)], [jnp.zeros((d, 2 * d), wide)]]))
    eye = jnp.eye(d, dtype=wide)
    ksum = jnp.kron(a, eye) + jnp.kron(eye, a)  # row-major vec: (A ⊕ A) vec X = vec(A X + X Aᵀ)
    dd = d * d
    big = expm(jnp.block([[ksum * hw, hw * jnp.eye(dd, dtype=wide)], [jnp.zeros((dd, 2 * dd), wide)]]))
    flow = _LinearFlow(hw, e[:d, :d], e[:d, d:], big[:dd, dd:], None)
    if b is not None:
        flow = dataclasses.replace(flow, noise=_noise_factor(flow, b))
    return flow


def _noise_factor(flow: _LinearFlow, b: Array) -> Array:
    """``C = P L`` with ``P = φ₁(Ah) b``, ``L Lᵀ = K = P⁺ (Σ_h/h) P⁺ᵀ`` (lower triangular, zero columns where ``K``
    is singular): ``C Cᵀ h = Σ_h`` wherever ``range Σ_h = range P`` (the linear flow keeps the noise in its span),
    else the projection of ``Σ_h`` on ``range P``.  ``K = I + O(h²)`` at small ``h``, so ``C = P + O(h²)``: the
    step keeps exponential Euler's strong order.  ``K`` does not depend on the scale of ``b``."""
    wide = flow.gram.dtype
    b = b.astype(wide)
    d, m = b.shape
    sigma = (flow.gram @ (b @ b.T).reshape(-1)).reshape(d, d) / flow.h
    p = flow.h_phi @ b / flow.h
    # P⁺ by SVD (zero singular values cut): a column without noise is a zero row of P⁺, and columns that depend on
    # others (more channels than P's rank, as a bath's contact whose noise enters several velocities) leave PᵀP
    # singular, where (PᵀP)⁻¹Pᵀ is not finite; its derivative is P⁺'s at constant rank
    left = jnp.linalg.pinv(p)
    k = left @ (0.5 * (sigma + sigma.T)) @ left.T
    return p @ psd_factor(0.5 * (k + k.T))


class ExponentialEuler(dfx.AbstractItoSolver):
    """Exponential Euler–Maruyama with the exact noise of the linear flow, for ``dZ = (A Z + N(Z)) dt + b(Z) dW``
    (Itô):

        Z_{n+1} = e^{Ah} Z_n + h φ₁(Ah) N(Z_n) + C ΔW_n,   C Cᵀ h = Σ_h = ∫₀ʰ e^{As} b bᵀ e^{Aᵀs} ds,

    ``b = b(Z_n)``, ``φ₁(x) = (eˣ − 1)/x``, ``C = φ₁(Ah) b + O(h²)`` (THEORY.md §8: a mode of any rate ``λh`` keeps
    its stationary variance).  ``linear(params) -> A`` gives the linear part of the drift; the drift term's vector
    field is the full drift ``A Z + N(Z)``.  Left ``None``, ``simulate`` takes the system's declared
    ``linear_drift``.  ``additive``: ``b`` does not depend on the state, so ``C`` is computed once per solve.
    """

    linear: Callable | None = None
    additive: bool = eqx.field(default=False, static=True)
    term_structure: ClassVar = dfx.MultiTerm[tuple[dfx.AbstractTerm, dfx.AbstractTerm]]
    interpolation_cls: ClassVar = dfx.LocalLinearInterpolation

    def order(self, terms):
        return 1

    def strong_order(self, terms):
        return 0.5

    def _linear(self, args, dtype):
        if self.linear is None:
            raise ValueError("ExponentialEuler needs linear(params) -> A; simulate fills it from the system.")
        return self.linear(args).astype(dtype)

    def _flow(self, terms, t0, h, y0, args) -> _LinearFlow:
        b = terms.terms[1].vf(t0, y0, args) if self.additive else None
        return linear_flow(self._linear(args, y0.dtype), h, b, y0.dtype)

    def init(self, terms, t0, t1, y0, args):
        """The matrices of the linear flow over the step ``t1 − t0`` (:class:`_LinearFlow`), once per solve."""
        return self._flow(terms, t0, t1 - t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        drift, diffusion = terms.terms
        h = t1 - t0
        a = self._linear(args, y0.dtype)
        if solver_state is None:
            flow = self._flow(terms, t0, h, y0, args)
        else:  # a step of another length (adaptive steps, a last short step): the matrices afresh
            flow = jax.lax.cond(
                jnp.asarray(h).astype(solver_state.h.dtype) == solver_state.h,
                lambda: solver_state,
                lambda: self._flow(terms, t0, h, y0, args),
            )
        noise = flow.noise if flow.noise is not None else _noise_factor(flow, diffusion.vf(t0, y0, args))
        propagator, h_phi, noise = (x.astype(y0.dtype) for x in (flow.propagator, flow.h_phi, noise))
        nonlinear = drift.vf(t0, y0, args) - a @ y0
        y1 = propagator @ y0 + h_phi @ nonlinear + diffusion.prod(noise, diffusion.contr(t0, t1))
        return y1, None, dict(y0=y0, y1=y1), solver_state, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class _Milstein(dfx.ItoMilstein):
    """diffrax's Itô Milstein method, ``Z₁ = Z₀ + a h + b ΔW + ½ Σ b_k ∂_k b (ΔWΔWᵀ − h I)``, stepping in the
    state's precision.

    diffrax 0.7 builds the ``h I`` of the double integral in JAX's default precision: with float64 enabled a
    float32 state became float64 (a dtype error under strict promotion, a changed carry otherwise).  The step
    runs as diffrax's and returns its results in the state's dtype.
    """

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        with jax.numpy_dtype_promotion("standard"):
            y1, error, dense, state, result = super().step(terms, t0, t1, y0, args, solver_state, made_jump)
        return jax.tree.map(lambda a, b: a.astype(b.dtype), y1, y0), error, _like(dense, y0), state, result


def _like(dense: dict, y0):
    return {k: jax.tree.map(lambda a, b: a.astype(b.dtype), v, y0) for k, v in dense.items()}


SOLVERS: dict[str, Callable[[], dfx.AbstractSolver]] = {
    "euler": dfx.Euler,
    "milstein": _Milstein,
    "heun": dfx.EulerHeun,
    "heun2": lambda: dfx.Heun(scan_kind="bounded"),
    "sra1": lambda: dfx.SRA1(scan_kind="lax"),
    "exponential": ExponentialEuler,
    "weak2": PlatenWeak2,
}
"""String aliases (CLI, run files) → solver objects: Euler–Maruyama and Milstein (Itô); Euler–Heun
(Stratonovich, Euler in the drift); Heun (Stratonovich, second order in the drift); SRA1 (additive
noise, strong order 1.5); exponential Euler–Maruyama (exact in the linear friction); Platen's explicit weak
order-2.0 scheme for any noise, with three-point increments (``PlatenWeak2``)."""


def _both_modes(solver: dfx.AbstractSolver) -> dfx.AbstractSolver:
    """``solver`` with its stage loop a scan of static length, which ``jax.jvp`` and ``jax.vjp`` both differentiate
    (module): explicit Runge–Kutta stages ``scan_kind='bounded'``, stochastic Runge–Kutta stages ``'lax'``."""
    if isinstance(solver, dfx.AbstractSRK) and solver.scan_kind != "lax":
        return dataclasses.replace(solver, scan_kind="lax")
    if isinstance(solver, dfx.AbstractRungeKutta) and solver.scan_kind != "bounded":
        return dataclasses.replace(solver, scan_kind="bounded")
    return solver


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _finite_step(step: Callable, inputs):
    """``step(*inputs)``: a solver step's ``(y1, error, dense, state, result)`` from ``inputs = ((y0, args),
    hoisted)`` (their arrays), differentiated where it succeeds (:func:`_finite_step_jvp`)."""
    return step(*inputs)


def _is_zero(t) -> bool:
    return isinstance(t, jax.custom_derivatives.SymbolicZero)


def _finite_step_jvp(step: Callable, primals, tangents):
    """The step, and its tangent at ``y0`` where its ``y1`` is finite and its result successful, else at the origin
    ``y0 = 0``: such a step's value is discarded (a failed path keeps its last state), and so its tangent, but in
    reverse mode its zero cotangent still meets the partial derivatives at the linearisation point, where at ``y0``
    they overflow (``0·∞ = nan``), and the origin's are finite for a drift and diffusion finite there.  Evaluated twice
    (the step, then ``jax.jvp`` at its state or the origin): ``jax.linearize`` once, masking the tangent instead, cost
    1.3–2× in ``jacfwd`` and ``value_and_grad`` (its residuals are materialised; benchmarks/RESULTS.md)."""
    (inputs,), (dots,) = primals, tangents
    out = step(*inputs)
    y1, result = out[0], out[4]
    ok = jnp.all(jnp.array([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(y1)])) & (
        result == dfx.RESULTS.successful
    )
    dynamic, hoisted = inputs
    y0 = jax.tree.map(lambda v: jnp.where(ok, v, jnp.zeros_like(v)), dynamic[3])  # the double where's first
    leaves, tree = jax.tree.flatten(((*dynamic[:3], y0, *dynamic[4:]), hoisted))
    dots = jax.tree.leaves(dots, is_leaf=_is_zero)
    live = [i for i, t in enumerate(dots) if not _is_zero(t) and t.dtype != jax.dtypes.float0]

    def at(*values):
        full = list(leaves)
        for i, v in zip(live, values, strict=True):
            full[i] = v
        return step(*jax.tree.unflatten(tree, full))

    if not live:
        return out, jax.tree.map(_zero_tangent, out)
    _, out_dot = jax.jvp(at, tuple(leaves[i] for i in live), tuple(dots[i] for i in live))
    return out, out_dot


_finite_step.defjvp(_finite_step_jvp, symbolic_zeros=True)


def _zero_tangent(x):
    x = jnp.asarray(x)
    return jnp.zeros_like(x) if jnp.issubdtype(x.dtype, jnp.inexact) else np.zeros(x.shape, jax.dtypes.float0)


@functools.cache
def _finite_class(cls: type) -> type:
    """``cls`` with its ``step`` differentiated only where it succeeds (:func:`_finite_step`): a subclass, so the
    solver keeps its type, name and fields."""

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # every array argument is an input of the rule (an adaptive step's times, its bool `made_jump`, a Brownian
        # tree's key are traced: closed over, a non-float tracer would be a constant of the rule's program, which
        # cannot be lowered)
        dynamic, static = eqx.partition((terms, t0, t1, y0, args, solver_state, made_jump), eqx.is_array)

        def plain(inputs):
            terms_, t0_, t1_, y, a, state, jump = eqx.combine(inputs, static)
            return cls.step(self, terms_, t0_, t1_, y, a, state, jump)

        # values the step closes over (the increments, a closure's parameters) become explicit inputs too, so that
        # the rule sees every value it is differentiated in
        converted, hoisted = jax.closure_convert(plain, dynamic)
        return _finite_step(lambda inputs, extra: converted(inputs, *extra), (dynamic, hoisted))

    names = {"__module__": cls.__module__, "__qualname__": cls.__qualname__, "__doc__": cls.__doc__}
    return type(cls.__name__, (cls,), {"step": step, "_finite_tangents": True, **names})


def _finite_tangents(solver: dfx.AbstractSolver) -> dfx.AbstractSolver:
    """``solver`` (same fields) as an instance of :func:`_finite_class` of its type."""
    if getattr(type(solver), "_finite_tangents", False):
        return solver
    guarded = object.__new__(_finite_class(type(solver)))
    for field in dataclasses.fields(solver):
        object.__setattr__(guarded, field.name, getattr(solver, field.name))
    return guarded


class SolverNeeds(eqx.Module):
    """What a solver needs of a system and its driver, read from the solver's type."""

    solver: dfx.AbstractSolver
    name: str = eqx.field(static=True)
    interpretation: Literal["ito", "stratonovich", "any"] = eqx.field(static=True)
    additive_only: bool = eqx.field(static=True)
    levy_area: type = eqx.field(static=True)
    embedded_error: bool = eqx.field(static=True)


def _levy_area(solver) -> type:
    need = getattr(solver, "minimal_levy_area", dfx.AbstractBrownianIncrement)
    for offered in (dfx.BrownianIncrement, dfx.SpaceTimeLevyArea, *WEAK_INCREMENTS):
        if issubclass(offered, need):
            return offered
    raise ValueError(
        f"solver={type(solver).__name__}() needs {need.__name__}, which nhsde's counter-based driver does not "
        "draw (it offers Brownian increments, space-time Lévy area and PlatenWeak2's increments); "
        "choose another solver."
    )


def solver_needs(solver: str | dfx.AbstractSolver, system: StochasticSystem) -> SolverNeeds:
    """The solver object for ``solver`` (an alias of :data:`SOLVERS` or a diffrax solver) and its needs.

    Raises naming ``solver`` when it cannot solve ``system``: not an SDE solver,
    additive-noise-only on a state-dependent diffusion, not Euler–Maruyama on a
    driver with jumps (S0 §2, Remark), or the exponential solver on a system
    without a declared linear drift.
    """
    if isinstance(solver, str):
        if solver not in SOLVERS:
            raise ValueError(f"solver={solver!r}; allowed: {', '.join(SOLVERS)}, or a diffrax SDE solver object.")
        name, solver = solver, SOLVERS[solver]()
    elif isinstance(solver, dfx.AbstractSolver):
        name = type(solver).__name__
        if type(solver) is dfx.ItoMilstein:
            solver = _Milstein()  # diffrax's own, in the state's precision
    else:
        raise TypeError(f"solver={solver!r}; expected one of {', '.join(SOLVERS)} or a diffrax solver object.")
    if isinstance(solver, dfx.AbstractFosterLangevinSRK):
        raise ValueError(
            f"solver={name!r}: a Langevin solver needs diffrax's underdamped-Langevin terms, not a general SDE; "
            f"use one of {', '.join(SOLVERS)}, or e.g. diffrax.ShARK()."
        )
    srk = isinstance(solver, dfx.AbstractSRK)
    additive_only = srk and solver.tableau.is_additive_noise()
    if additive_only:
        interpretation = "any"
    elif isinstance(solver, dfx.AbstractItoSolver):
        interpretation = "ito"
    elif isinstance(solver, dfx.AbstractStratonovichSolver):
        interpretation = "stratonovich"
    else:
        raise ValueError(
            f"solver={name!r}: not an SDE solver (diffrax marks SDE solvers as Itô or Stratonovich); "
            f"use one of {', '.join(SOLVERS)}, or e.g. diffrax.ShARK()."
        )
    if additive_only and not system.additive_noise:
        raise ValueError(
            f"solver={name!r} needs additive noise, but this system's diffusion depends on the state; "
            "use 'euler', 'milstein', 'heun' or 'heun2'."
        )
    if not system.noise.continuous and not isinstance(solver, dfx.Euler):
        raise ValueError(f"solver={name!r} does not apply to a system driven by jumps; use 'euler' (S0 §2, Remark).")
    if isinstance(solver, ExponentialEuler) and solver.linear is None:
        if system.linear_drift is None:
            raise ValueError(
                f"solver={name!r} needs the system's linear drift part (StochasticSystem.linear_drift); "
                "this system does not declare one."
            )
        solver = ExponentialEuler(system.linear_drift, additive=system.additive_noise)
    embedded = isinstance(solver, dfx.AbstractSRK) and solver.tableau.b_error is not None
    solver = _finite_tangents(_both_modes(solver))
    return SolverNeeds(solver, name, interpretation, additive_only, _levy_area(solver), embedded)
