"""Physical parameters as pytree leaves, with their allowed ranges.

Every physical constant of a scene — friction ``eps``, noise intensity ``nu``,
masses, radii — is a leaf of an :class:`AbstractParameters` module, never a
static field and never closed over, so ``jax.grad``/``jax.jacfwd`` reach it.
Each leaf declares its range with :func:`parameter`; concrete values are checked
when the module is built (``ValueError`` naming the argument, the value and the
range), traced values are checked at run time with ``eqx.error_if`` by
:func:`validated`, which walks any pytree of parameters (the one parameters
interface: a system's ``params`` is any pytree, and its
:class:`AbstractParameters` nodes carry the ranges).
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._misc import is_concrete

__all__ = ["AbstractParameters", "check_ranges", "parameter", "sqrt_intensity", "validated"]


def _host_checked_state():
    """A JAX config state in every jit and transformation cache key (JAX's private ``config.State``), or ``None``
    where this JAX offers none: then every program keeps its parameters' checks (correct, and not cached on disk)."""
    try:
        from jax._src import config as jax_config

        return jax_config.State(
            "nhsde_parameters_checked_on_host",
            False,
            "nhsde internal: the parameters of the programs traced now were checked on the host (ranges, and no "
            "differentiated parameter is 0), so their run-time checks (host callbacks) are left out of the programs.",
            include_in_jit_key=True,
            include_in_trace_context=True,  # a program traced without the checks is never reused by a trace that
            # needs them
        )
    except (ImportError, AttributeError, TypeError):
        return None


_CHECKED_ON_HOST = _host_checked_state()
"""JAX's persistent compilation cache writes no entry for a program with a host callback (``eqx.error_if``); a
program traced in :func:`checked_on_host` has none of the parameters' checks."""


def _as_leaf(value):
    """``value`` as an array leaf; what cannot be one is kept as given, for the check to name it."""
    if isinstance(value, (bool, np.bool_, str, bytes)) or value is None:
        return value
    try:
        leaf = jnp.asarray(value)
    except (TypeError, ValueError):
        return value
    # physical constants are reals: a whole number given (eps=0) becomes the default float
    return leaf.astype(jnp.result_type(float)) if jnp.issubdtype(leaf.dtype, jnp.integer) else leaf


def parameter(*, default, lower: float | None = None, strict: bool = False, doc: str = "", per_channel: bool = False):
    """A parameter leaf that must be a finite real ``≥ lower`` (``> lower`` if ``strict``).

    A parameter with a scalar default must be a scalar, unless ``per_channel``
    (one value per noise channel is allowed): a vector given for a scalar is
    refused rather than broadcast.

    Arguments:
        default: the value when none is given.
        lower: the smallest allowed value (``None``: any finite real).
        strict: exclude ``lower`` itself.
        doc: one line with the symbol and its unit, shown by :meth:`AbstractParameters.describe`.
        per_channel: allow one value per noise channel.

    Returns:
        an ``equinox`` field declaration for a subclass of :class:`AbstractParameters`.

    Examples:
        >>> import jax
        >>> import jax.numpy as jnp
        >>> import nhsde
        >>> class Friction(nhsde.AbstractParameters):
        ...     eps: jnp.ndarray = nhsde.parameter(default=1.0, lower=0.0, doc="friction ε, 1/s")
        >>> Friction(eps=0.5).eps
        Array(0.5, dtype=float64, weak_type=True)
        >>> Friction.describe()
        [('eps', 1.0, 'finite and ≥ 0', 'friction ε, 1/s')]
        >>> Friction(eps=-1.0)
        Traceback (most recent call last):
        ...
        ValueError: Friction: parameter eps=-1.0 is not allowed; eps must be finite and ≥ 0.
        >>> float(jax.grad(lambda p: p.eps**2)(Friction(eps=3.0)).eps)  # a leaf: gradients reach it
        6.0
    """
    return eqx.field(
        default=default,
        converter=_as_leaf,
        metadata={"lower": lower, "strict": strict, "doc": doc, "per_channel": per_channel},
    )


def _range_text(lower, strict) -> str:
    if lower is None:
        return "finite"
    return f"finite and {'>' if strict else '≥'} {lower:g}"


def _declared(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if "lower" in f.metadata]


class AbstractParameters(eqx.Module):
    """Base class of a scene's parameters; subclasses declare leaves with :func:`parameter`."""

    @classmethod
    def describe(cls) -> list[tuple[str, object, str, str]]:
        """``(name, default, allowed range, doc)`` for each declared parameter."""
        return [
            (f.name, f.default, _range_text(f.metadata["lower"], f.metadata["strict"]), f.metadata["doc"])
            for f in _declared(cls)
        ]

    def __check_init__(self):
        check_ranges(self)

    def replace(self, **changes):
        """A copy with some parameters changed (and re-checked)."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            allowed = ", ".join(name for name, *_ in self.describe())
            raise TypeError(f"{type(self).__name__} has no parameter {unknown[0]!r}; parameters: {allowed}.")
        return dataclasses.replace(self, **changes)


def _check_leaf(owner: str, f: dataclasses.Field, value) -> None:
    kind = getattr(value, "dtype", None)
    if kind is None or not (jnp.issubdtype(kind, jnp.floating) or jnp.issubdtype(kind, jnp.integer)):
        raise TypeError(f"{owner}: parameter {f.name}={value!r}; expected a real number.")
    if not f.metadata["per_channel"] and np.ndim(cast(Any, f.default)) == 0 and np.ndim(value) != 0:
        raise ValueError(f"{owner}: parameter {f.name} has shape {np.shape(value)}; {f.name} is one number.")
    if not is_concrete(value):
        return  # traced: checked by `validated` at run time
    value = np.asarray(value)
    lower, strict = f.metadata["lower"], f.metadata["strict"]
    ok = np.all(np.isfinite(value))
    if ok and lower is not None:
        ok = np.all(value > lower) if strict else np.all(value >= lower)
    if not ok:
        raise ValueError(
            f"{owner}: parameter {f.name}={value.tolist()!r} is not allowed; "
            f"{f.name} must be {_range_text(lower, strict)}."
        )


def check_ranges(params) -> None:
    """Check every concrete declared leaf of the parameters in ``params`` (any pytree) against its range.

    Run when parameters are built, and again by ``simulate`` after casting them to
    the state's precision (a radius of 1e-50 is 0 in float32).
    """
    for node in jax.tree_util.tree_leaves(params, is_leaf=_is_parameters):
        if _is_parameters(node):
            for f in _declared(node):
                _check_leaf(type(node).__name__, f, getattr(node, f.name))


def _is_parameters(node) -> bool:
    return isinstance(node, AbstractParameters)


def _holds_parameters(tree) -> bool:
    return any(_is_parameters(n) for n in jax.tree_util.tree_leaves(tree, is_leaf=_is_parameters))


def _with_run_time_checks(node: AbstractParameters) -> AbstractParameters:
    out = node
    for f in dataclasses.fields(node):
        value = getattr(node, f.name)
        if "lower" not in f.metadata:
            if f.metadata.get("static") or not _holds_parameters(value):
                continue
            checked = validated(value)  # nested parameters (a filtered system's, a body's surface)
        elif is_concrete(value):
            continue
        else:
            lower, strict = f.metadata["lower"], f.metadata["strict"]
            bad = ~jnp.isfinite(value)
            if lower is not None:
                bad = bad | ((value <= lower) if strict else (value < lower))
            checked = eqx.error_if(
                value,
                jnp.any(bad),
                f"{type(node).__name__}: parameter {f.name} must be {_range_text(lower, strict)}.",
            )
        out = eqx.tree_at(lambda p, n=f.name: getattr(p, n), out, checked, is_leaf=lambda x: x is None)
    return out


def validated(params):
    """``params`` (any pytree) with run-time range checks attached to the traced leaves of its parameters.

    Concrete values were checked when each :class:`AbstractParameters` was built;
    traced ones (under ``jit``/``grad``) get an ``eqx.error_if`` naming the
    parameter and its range, unless their caller checked them on the host
    (:func:`checked_on_host`).
    """
    if parameters_checked_on_host():
        return params  # the caller checked them on the host (`checked_on_host`)
    return jax.tree_util.tree_map(
        lambda node: _with_run_time_checks(node) if _is_parameters(node) else node, params, is_leaf=_is_parameters
    )


def parameters_checked_on_host() -> bool:
    """Whether the programs traced now take parameters that their caller checked on the host
    (:func:`checked_on_host`)."""
    return _CHECKED_ON_HOST is not None and bool(_CHECKED_ON_HOST.value)


@contextlib.contextmanager
def checked_on_host():
    """Within: the parameters of the programs traced here (traced leaves included) were checked on the host by the
    caller: their ranges in the state's precision (:func:`check_ranges`), and no parameter leaf that carries a
    tangent is 0 (:func:`differentiated_nonzero`), so that ``√ν``'s derivative is finite.  The programs then leave
    out those run-time checks, host callbacks with which JAX's persistent compilation cache writes no entry.

    The setting is part of JAX's trace context and jit key, so it is in every jit and transformation cache key: a
    program traced here is never reused outside, where traced parameters need their checks.  As with the
    estimators' forward mode, ``simulate`` then leaves the stationary-variance warning of traced parameters to the
    caller (``stable_step`` and the warning are the host's, on the concrete values).

    ``simulate`` called here (by ``moment_sensitivities``, whose jit traces it with concrete parameters) also leaves
    out the checks of its run's outcome: the caller checked the step's stability on the host before the run
    (``_simulate._check_linear_stability``) and checks too few paths and overflow on the host after it, so
    ``simulate`` returns its traced outputs unchecked.
    """
    if _CHECKED_ON_HOST is None:  # this JAX cannot key programs on it: the checks stay in them
        yield
        return
    with _CHECKED_ON_HOST(True):
        yield


def concrete_primal(tree):
    """``tree`` with its primal values where they are known on the host (concrete leaves, or tracers of
    ``jax.jvp`` / ``jax.jacfwd`` over concrete values, their tangents dropped); ``None`` under ``jit`` or ``vmap``."""
    # stop_gradient of a forward-mode tracer over a concrete value is that value
    primal = jax.tree_util.tree_map(lambda x: x if is_concrete(x) else jax.lax.stop_gradient(x), tree)
    return primal if is_concrete(primal) else None


def differentiated_nonzero(params) -> bool:
    """Whether the primal values of ``params`` are known on the host (:func:`concrete_primal`) and every leaf that
    carries a tangent is nonzero everywhere: then no :func:`sqrt_intensity` of a parameter is differentiated at 0,
    the one case its run-time check catches."""
    primal = concrete_primal(params)
    if primal is None:
        return False  # under jit or vmap: the values are not known here
    pairs = zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(primal))
    return all(bool(np.all(np.asarray(p) != 0)) for x, p in pairs if not is_concrete(x))


_SINGULAR = (
    "the derivative with respect to a noise intensity nu at nu = 0 is singular (paths scale like √nu); "
    "differentiate at nu > 0 or with respect to √nu."
)


@jax.custom_jvp
def sqrt_intensity(nu):
    """``√ν``: the amplitude of white noise of intensity ``ν`` (S0: ``E[VVᵀ] = ν δ``).

    Every path scales like ``√ν``, so ``∂/∂ν`` of a path at ``ν = 0`` is infinite
    and only statistics such as covariances (``∝ ν``) have a finite derivative
    there, which a pathwise gradient cannot see.  Instead of a silent NaN, a
    derivative with respect to ``ν`` taken at ``ν = 0`` raises; take it at
    ``ν > 0`` (covariances are linear in ``ν``) or differentiate in ``√ν``.

    Examples:
        >>> import jax
        >>> import nhsde
        >>> float(nhsde.sqrt_intensity(4.0)), float(jax.grad(nhsde.sqrt_intensity)(4.0))
        (2.0, 0.25)
    """
    return jnp.sqrt(nu)


@sqrt_intensity.defjvp
def _sqrt_intensity_jvp(primals, tangents):
    (nu,), (dnu,) = primals, tangents
    zero = nu == 0
    if parameters_checked_on_host():
        # no differentiated parameter is 0 (checked on the host, no host callback in the program); a ν computed
        # from them that is 0 anyway (the leaf check cannot see it) gives a nan derivative, never a silent one
        root = jnp.sqrt(nu)
        return root, dnu * jnp.where(zero, jnp.nan, 1 / (2 * jnp.where(zero, 1.0, root)))
    root = eqx.error_if(jnp.sqrt(nu), jnp.any(zero), _SINGULAR)
    return root, jnp.where(zero, 0.0, dnu / (2 * jnp.where(zero, 1.0, root)))
