"""What :func:`~nhsde.simulate` keeps and returns: ``Save``, ``Ensemble``, and the one moment reducer.

Paths are reduced block by block (``BLOCK`` paths each) to sums of the first
four powers of their saved values about a shift, and the blocks are added one
after another in path order, so every addition happens in the same order for
any chunk size, device count or piece of a run file: the statistics are bitwise
independent of all three.  Standard errors follow exactly from the same sums
(third- and fourth-order sums give the variance of the covariance estimate).
"""

# No ``from __future__ import annotations``: equinox reads AbstractVar annotations, which must not be strings.

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from equinox import AbstractVar
from jaxtyping import Array, Bool, Float, Int

from ._brownian import BLOCK
from ._misc import check_number, is_concrete

__all__ = [
    "AbstractMoments",
    "Ensemble",
    "MomentSums",
    "Save",
    "SimulationError",
    "SimulationResult",
    "StationaryVarianceWarning",
    "check_result",
]

MIN_PATHS = 4
"""Fewest paths a run may have: a covariance and the standard error of its estimate need four."""


FAILURE_CAUSES = "a non-finite state, a blow-up, an angle past its precision's resolution, or a solver error"
"""Why a path fails (``_simulate``: ``BLOW_UP``, ``ANGLE_RESOLUTION``), in every message that counts failed paths."""


class SimulationError(RuntimeError):
    """Paths failed (:data:`FAILURE_CAUSES`) and ``on_failure='raise'``."""


class StationaryVarianceWarning(UserWarning):
    """The solver's stationary variance on the declared linear friction is off by more than 10 % at this step."""


class SimulationResult(eqx.Enumeration):
    """How a run ended: the one failure channel of ``simulate`` and the estimators built on it.

    Computed inside the compiled run and checked once by :func:`check_result`: raised at
    once when the run is called plainly, attached to every output with ``eqx.error_if``
    under ``jit``, ``grad`` and ``vmap``, with the same cause and fix.
    """

    successful = ""
    unstable_step = (
        "the step is at or beyond the solver's stability limit on this system's linear friction (a damped mode "
        "is not damped by the solver: e.g. eps·dt ≥ 1 for Euler on the ball); take dt smaller, or use "
        "solver='exponential', which is stable at any step."
    )
    paths_failed = (
        f"some paths failed ({FAILURE_CAUSES}); try a smaller dt, a stiffer-stable solver, float64 states, or "
        "on_failure='exclude' to inspect them."
    )
    too_few_paths = (
        f"fewer than {MIN_PATHS} paths succeeded (the others failed on {FAILURE_CAUSES}); statistics and their "
        f"standard errors need ≥ {MIN_PATHS}: try a smaller dt, a stiffer-stable solver or float64 states."
    )
    moments_overflow = "the moment sums overflow (statistics not finite); use float64 states (jax_enable_x64)."


def failure_result(*, unstable, n_failed, n_used, raise_on_failure: bool, overflow) -> SimulationResult:
    """The run's :class:`SimulationResult` from its flags (traced or not), the cause first."""
    result = SimulationResult.where(overflow, SimulationResult.moments_overflow, SimulationResult.successful)
    if raise_on_failure:
        result = SimulationResult.where(n_failed > 0, SimulationResult.paths_failed, result)
    result = SimulationResult.where(n_used < MIN_PATHS, SimulationResult.too_few_paths, result)
    return SimulationResult.where(unstable, SimulationResult.unstable_step, result)


def scale_cause(params, y0) -> str:
    """Where paths failed: a note naming the largest concrete parameter or initial value when it is beyond
    ``max**(1/4)`` of ``y0``'s precision (fourth moments of such values overflow at any step), else ``""``."""
    dtype = jnp.asarray(y0).dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        return ""
    limit = float(jnp.finfo(dtype).max) ** 0.25
    largest, where = 0.0, ""
    leaves = [*jax.tree_util.tree_leaves_with_path(params), (("initial state",), y0)]
    for path, leaf in leaves:
        if not is_concrete(leaf) or not jnp.issubdtype(jnp.asarray(leaf).dtype, jnp.inexact):
            continue
        values = np.abs(np.asarray(leaf, np.float64))
        finite = values[np.isfinite(values)]
        if finite.size and finite.max() > largest:
            largest, where = float(finite.max()), "".join(str(getattr(k, "name", k)) for k in path).lstrip(".")
    if largest <= limit:
        return ""
    return (
        f"{where} = {largest:.3g} is beyond {limit:.3g}, where fourth moments overflow in {dtype.name}: the scale is "
        "the likely cause, not the step; rescale the units (or use float64 states)."
    )


def check_result(outputs, result: SimulationResult, caller: str, details: str = "", scale: str = ""):
    """``outputs`` once ``result`` is checked: the one place a failed run is reported.

    Concrete (a plain call): raises :class:`SimulationError` naming ``caller``, the
    cause and the fix, with ``details`` (counts, the first failed path).  Traced
    (under ``jit``, ``grad``, ``vmap``): every leaf of ``outputs`` carries the same
    check, so no output of a failed run can be used, whichever is read.  ``scale``
    (:func:`scale_cause`) replaces the advice on the step where the scale is the cause.
    """
    if is_concrete(result):
        message = SimulationResult[result]  # read on the host: no program of its own
        failed = (SimulationResult.paths_failed, SimulationResult.too_few_paths)
        if scale and message in (SimulationResult[f] for f in failed):
            message = message.split(": try", 1)[0].split("; try", 1)[0] + "; " + scale
        if message:
            raise SimulationError(f"{caller}: {details}{message}")
        return outputs
    return _error_if_in_derivatives(outputs, result)


@jax.custom_jvp
def _error_if_in_derivatives(outputs, result: SimulationResult):
    """``outputs`` checked against ``result`` (``eqx.error_if``), in their derivatives too."""
    return result.error_if(outputs, result != SimulationResult.successful)


@_error_if_in_derivatives.defjvp
def _error_if_in_derivatives_jvp(primals, tangents):
    # the tangents read the checked outputs (times one): `jit(jacfwd(f))` or `jit(grad(f))` returning derivatives
    # alone keeps the check, which XLA removes where it rides on the primal outputs only
    outputs, result = primals
    checked = _error_if_in_derivatives(outputs, result)

    def carry(tangent, value):
        if tangent.dtype == jax.dtypes.float0:
            return tangent
        return tangent * (1 + 0 * value).astype(tangent.dtype)

    return checked, jax.tree.map(carry, tangents[0], checked)


def _tuple_of_names(names):
    return tuple(names) if isinstance(names, list) else names


class Save(eqx.Module):
    """What ``simulate`` keeps: which components, at how many times, per path or not.

    Arguments:
        names: state components or system observables (a tuple of names);
            ``None`` = the whole state.
        n: number of equally spaced save times from ``t0`` to ``t1`` inclusive;
            ``n − 1`` must divide the number of steps (``None``: the largest such ``n ≤ 11``).
        paths: also keep the per-path values, ``(n_paths, n, k)``.
        about: the point ``(n, k)`` the moment sums are taken about (default:
            the first path's values); pass an earlier piece's ``Ensemble.sums.shift``
            so that the sums of several pieces add exactly.

    Examples:
        >>> import nhsde
        >>> nhsde.Save(names=("x", "omega_x"), n=3)
        Save(names=('x', 'omega_x'), n=3)
        >>> nhsde.Save(n=1)
        Traceback (most recent call last):
        ...
        ValueError: Save(n=1); must be ≥ 2 (the start and the end at least).
    """

    names: tuple[str, ...] | None = eqx.field(default=None, converter=_tuple_of_names)
    n: int | None = None
    paths: bool = False
    about: Array | None = None

    def __check_init__(self):
        if self.names is not None:
            if not isinstance(self.names, tuple):
                raise TypeError(f"Save(names={self.names!r}); expected a tuple of names, e.g. ('x', 'y').")
            if not self.names:
                raise ValueError("Save(names=()); name at least one quantity, or None for the whole state.")
            if not all(isinstance(n, str) for n in self.names):
                raise TypeError(f"Save(names={self.names!r}); every name must be a string.")
        if self.n is not None and check_number("Save.n", self.n, integer=True) < 2:
            raise ValueError(f"Save(n={self.n}); must be ≥ 2 (the start and the end at least).")
        if not isinstance(self.paths, (bool, np.bool_)):
            raise TypeError(f"Save(paths={self.paths!r}); expected True or False.")


def _safe_sqrt(v):
    pos = v > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, v, 1.0)), 0.0)


def _central_product_moment(a, m2, m3, m4):
    """``E[(z_i − a_i)² (z_j − a_j)²]`` from moments about the shift.

    ``a = E z``, ``m2_ij = E z_i z_j``, ``m3_ij = E z_i z_j²``, ``m4_ij = E z_i² z_j²``;
    the variance of the product of the centred components is this minus ``cov²``.
    """
    ai, aj = a[:, :, None], a[:, None, :]
    d = jnp.diagonal(m2, axis1=1, axis2=2)
    return (
        m4
        - 2 * ai * m3
        - 2 * aj * jnp.swapaxes(m3, 1, 2)
        + aj**2 * d[:, :, None]
        + ai**2 * d[:, None, :]
        + 4 * ai * aj * m2
        - 3 * ai**2 * aj**2
    )


class MomentSums(eqx.Module):
    """Sums over valid paths of ``z``, ``z zᵀ``, ``z_i z_j²``, ``z_i² z_j²`` with ``z = x − shift``, and their count.

    The one reducer of path values to statistics, used by ``simulate`` (one chunk,
    one device or many) and by run files (piece by piece).
    """

    shift: Float[Array, "n k"]
    s1: Float[Array, "n k"]
    s2: Float[Array, "n k k"]
    s3: Float[Array, "n k k"]
    s4: Float[Array, "n k k"]
    count: Int[Array, ""]

    @classmethod
    def zeros(cls, shift) -> "MomentSums":
        n, k = shift.shape
        z2 = jnp.zeros((n, k, k), shift.dtype)
        return cls(shift, jnp.zeros((n, k), shift.dtype), z2, z2, z2, jnp.zeros((), jnp.int32))

    def add(self, other: "MomentSums") -> "MomentSums":
        """The sums of both sets of paths (same shift)."""
        return dataclasses.replace(
            self,
            s1=self.s1 + other.s1,
            s2=self.s2 + other.s2,
            s3=self.s3 + other.s3,
            s4=self.s4 + other.s4,
            count=self.count + other.count,
        )

    def block_sums(self, obs: Float[Array, "p n k"], valid: Bool[Array, " p"]):
        """The sums of each block of ``BLOCK`` paths of ``obs`` (stacked); invalid paths add nothing.

        Every block is reduced by the same fixed-shape loop body, so a block's sums
        do not depend on which chunk or device it ran in.
        """

        def one(_, block):
            obs_b, valid_b = block
            z = jnp.where(valid_b[:, None, None], obs_b - self.shift, 0.0)
            zz = jnp.einsum("cni,cnj->cnij", z, z)
            z_zz = jnp.einsum("cni,cnj->cnij", z, z * z)
            sums = (jnp.sum(z, 0), jnp.sum(zz, 0), jnp.sum(z_zz, 0), jnp.sum(zz * zz, 0))
            return None, (*sums, jnp.sum(valid_b, dtype=jnp.int32))

        blocks = (obs.reshape(-1, BLOCK, *obs.shape[1:]), valid.reshape(-1, BLOCK))
        return jax.lax.scan(one, None, blocks)[1]

    def add_blocks(self, block_sums) -> "MomentSums":
        """Add stacked block sums one after another, in path order."""

        def add(acc, block):
            s1, s2, s3, s4, count = block
            return acc.add(dataclasses.replace(acc, s1=s1, s2=s2, s3=s3, s4=s4, count=count)), None

        return jax.lax.scan(add, self, block_sums)[0]

    def add_paths(self, obs: Float[Array, "p n k"], valid: Bool[Array, " p"]) -> "MomentSums":
        """Add paths ``obs`` (a multiple of ``BLOCK``) block by block, in path order."""
        return self.add_blocks(self.block_sums(obs, valid))

    def statistics(self):
        """``(mean, cov, mean_se, cov_se)``: sample mean, unbiased covariance and their Monte-Carlo errors.

        One compiled program for every caller (``simulate`` on one device or many, run files piece by piece),
        so the statistics of the same sums round the same wherever they are taken (on one local device: sums
        spread over devices would compile another program, which may round differently).
        """
        sums = jax.device_put(self, jax.local_devices()[0]) if is_concrete(self) else self
        return _statistics(sums)


@eqx.filter_jit
def _statistics(sums: MomentSums):
    """:meth:`MomentSums.statistics`, compiled."""
    nf = sums.count.astype(sums.s1.dtype)
    mean = sums.shift + sums.s1 / nf
    cov = (sums.s2 - jnp.einsum("ni,nj->nij", sums.s1, sums.s1) / nf) / jnp.maximum(nf - 1, 1)
    mean_se = _safe_sqrt(jnp.diagonal(cov, axis1=1, axis2=2) / nf)
    fourth = _central_product_moment(sums.s1 / nf, sums.s2 / nf, sums.s3 / nf, sums.s4 / nf)
    return mean, cov, mean_se, _safe_sqrt(covariance_variance(cov, fourth, nf))


def covariance_variance(cov, fourth, n):
    """The squared standard error of the unbiased sample covariance ``cov`` of ``n`` paths.

    Exactly ``Var s_ij = (μ₂₂ − σ_ij²)/n + (σ_ii σ_jj + σ_ij²)/(n(n − 1))``, with
    ``μ₂₂ = E[(z_i − a_i)²(z_j − a_j)²]`` (``fourth``, the sample's own, divided by ``n``);
    estimated with the sample's central moments ``m = cov·(n − 1)/n``: the first term
    ``m₂₂ − m_ij² ≥ 0`` (Cauchy–Schwarz) and the second ``> 0`` for a non-degenerate
    sample, so no standard error is zero unless the sample is.
    """
    m = cov * (n - 1) / n
    var = jnp.diagonal(m, axis1=-2, axis2=-1)
    pair = var[..., :, None] * var[..., None, :] + m**2
    return jnp.maximum(fourth - m**2, 0.0) / n + pair / (n * jnp.maximum(n - 1, 1))


class AbstractMoments(eqx.Module):
    """Means and covariances of named quantities at times ``ts``: what the statistics consume.

    Monte Carlo (:class:`Ensemble`) carries standard errors; approximations
    (the moment equations) carry none (``standard_errors`` returns ``None``).
    """

    ts: AbstractVar[Float[Array, " n"]]
    mean: AbstractVar[Float[Array, "n k"]]
    cov: AbstractVar[Float[Array, "n k k"]]
    names: AbstractVar[tuple[str, ...]]
    roles: AbstractVar[tuple[str, ...]]

    def standard_errors(self) -> tuple[Array | np.ndarray, Array | np.ndarray] | None:
        """``(mean_se, cov_se)``, or ``None`` where the moments carry no Monte-Carlo error."""
        return None

    def select(self, names: tuple[str, ...]):
        """``(mean, cov, mean_se, cov_se)`` restricted to ``names`` (the errors ``None`` when there are none)."""
        for n in names:
            if n not in self.names:
                raise ValueError(f"{n!r} was not saved; saved: {self.names}.")
        mean, cov, errors = _select(self.mean, self.cov, self.standard_errors(), tuple(map(self.names.index, names)))
        return (mean, cov, *((None, None) if errors is None else errors))


@functools.partial(jax.jit, static_argnums=3)
def _select(mean, cov, errors, idx: tuple[int, ...]):
    """Means and covariances (with their errors, where there are) of the components ``idx`` (one program)."""
    i = jnp.asarray(idx)

    def cut(m, c):
        return m[:, i], c[:, i[:, None], i[None, :]]

    return *cut(mean, cov), None if errors is None else cut(*errors)


class Ensemble(AbstractMoments):
    """Result of :func:`~nhsde.simulate`: moments of the saved quantities over the paths.

    ``mean[i]``, ``cov[i]`` are the sample mean and (unbiased) covariance over the
    paths that did not fail, at ``ts[i]``; ``mean_se``, ``cov_se`` their
    Monte-Carlo standard errors; ``sums`` the moment sums they come from.
    ``n_failed`` paths failed (:data:`FAILURE_CAUSES`, or saved
    values whose fourth power overflows the precision); failed paths never enter
    a statistic.  With ``Save(paths=True)``, ``paths`` holds the per-path values
    and ``failed[p]`` marks path ``p`` (a failed path keeps its last finite
    state); otherwise both are ``None`` and memory does not grow with the paths.
    """

    ts: Float[Array, " n"]
    mean: Float[Array, "n k"]
    cov: Float[Array, "n k k"]
    mean_se: Float[Array, "n k"]
    cov_se: Float[Array, "n k k"]
    n_used: Int[Array, ""]
    n_failed: Int[Array, ""]
    failed: Bool[Array, " paths"] | None
    paths: Float[Array, "paths n k"] | None
    sums: MomentSums
    names: tuple[str, ...] = eqx.field(static=True)
    roles: tuple[str, ...] = eqx.field(static=True)
    solver: str = eqx.field(static=True)
    dt: float = eqx.field(static=True)

    def standard_errors(self):
        return self.mean_se, self.cov_se
