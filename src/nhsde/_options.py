"""Option objects of :func:`~nhsde.simulate`, each checking itself (diffrax's ``SaveAt``/``StepTo`` manner).

- :class:`FixedSteps` / :class:`AdaptiveSteps`: how time is stepped;
- :class:`Batching`: how paths are grouped into chunks, spread over devices and
  differentiated (reverse-mode checkpointing);
- :class:`RunOptions`: all of a run's options together, checked once (built by :func:`run_options`).
"""

# No ``from __future__ import annotations``: equinox reads AbstractVar annotations, which must not be strings.

import dataclasses
from collections.abc import Sequence

import diffrax as dfx
import equinox as eqx
import jax
import numpy as np

from ._brownian import BLOCK
from ._ensemble import Save
from ._misc import check_number, check_span, check_steps

__all__ = ["AbstractSteps", "AdaptiveSteps", "Batching", "FixedSteps", "RunOptions", "run_options"]


class AbstractSteps(eqx.Module):
    """How ``simulate`` steps in time: :class:`FixedSteps` or :class:`AdaptiveSteps`."""

    dt: eqx.AbstractVar[float]
    max_steps: eqx.AbstractVar[int]


class FixedSteps(AbstractSteps):
    """Steps of ``dt`` on the counter-based Brownian path (``dt`` must divide ``t1 − t0``).

    Arguments:
        dt: the step, ``> 0``.
        brownian_dt: base step of the Brownian path (divides ``dt``); solves with
            different ``dt`` and the same ``brownian_dt`` and key share one path (strong errors).
        max_steps: the step budget per path; a longer run is refused naming the
            count (raise it to run longer).

    Examples:
        >>> import nhsde
        >>> nhsde.FixedSteps(0.01, brownian_dt=0.001)
        FixedSteps(dt=0.01, brownian_dt=0.001)
        >>> nhsde.FixedSteps(-0.1)
        Traceback (most recent call last):
        ...
        ValueError: dt=-0.1; must be > 0.
    """

    dt: float
    brownian_dt: float | None = None
    max_steps: int = 10_000_000

    def __check_init__(self):
        check_number("dt", self.dt, positive=True)
        if self.brownian_dt is not None:
            check_number("brownian_dt", self.brownian_dt, positive=True)
        if check_number("max_steps", self.max_steps, integer=True) < 1:
            raise ValueError(f"max_steps={self.max_steps}; must be ≥ 1.")


class AdaptiveSteps(AbstractSteps):
    """Adaptive steps: ``diffeqsolve`` with a PID controller on a ``VirtualBrownianTree`` per path.

    The error estimate is the solver's own where a stochastic Runge–Kutta
    tableau embeds one, else step doubling (``diffrax.HalfSolver``).  Wiener-driven systems only.

    Arguments:
        dt: the first step.
        rtol, atol: the controller's relative and absolute tolerances.
        max_steps: at most this many steps per path (a path that needs more counts as failed).

    Examples:
        >>> import nhsde
        >>> nhsde.AdaptiveSteps(dt=0.01, rtol=1e-4, atol=1e-4)
        AdaptiveSteps(dt=0.01, rtol=0.0001, atol=0.0001)
    """

    dt: float
    rtol: float = 1e-3
    atol: float = 1e-3
    max_steps: int = 100_000

    def __check_init__(self):
        for name in ("dt", "rtol", "atol"):
            check_number(name, getattr(self, name), positive=True)
        if check_number("max_steps", self.max_steps, integer=True) < 1:
            raise ValueError(f"max_steps={self.max_steps}; must be ≥ 1.")


def _devices(devices):
    return tuple(devices) if isinstance(devices, (list, tuple)) else devices


class Batching(eqx.Module):
    """How the paths are grouped, spread and differentiated.

    Statistics are bitwise the same for every choice: only memory and speed change.

    Arguments:
        chunk_size: paths per chunk (a multiple of 64; default: each device's share
            of the paths, up to 8192 on a CPU and 2²⁰ on a GPU or TPU); memory
            scales with it, not with ``n_paths``.
        devices: the devices to shard chunks over (default: all of
            ``jax.devices()``); one chunk per device at a time, statistics bitwise the
            same as on one device.
        checkpoint: in reverse mode, ``True`` recomputes each save interval
            instead of storing every step (memory ∝ steps per save interval, about one
            extra forward pass); ``False`` stores every step (faster, memory ∝ steps ×
            chunk); ``None`` stores while the estimated residuals (≈ 10 × steps per
            interval × chunk × state size × bytes) stay under 1 GiB.

    Examples:
        >>> import nhsde
        >>> nhsde.Batching(chunk_size=256, checkpoint=True)
        Batching(chunk_size=256, checkpoint=True)
        >>> nhsde.Batching(chunk_size=100)
        Traceback (most recent call last):
        ...
        ValueError: chunk_size=100; must be a positive multiple of 64.
    """

    chunk_size: int | None = None
    devices: Sequence[jax.Device] | None = eqx.field(default=None, converter=_devices)  # pyright: ignore[reportInvalidTypeForm]  # jax.Device is a bare alias
    checkpoint: bool | None = None

    def __check_init__(self):
        if self.chunk_size is not None:
            chunk = check_number("chunk_size", self.chunk_size, integer=True)
            if chunk < BLOCK or chunk % BLOCK:
                raise ValueError(f"chunk_size={self.chunk_size}; must be a positive multiple of {BLOCK}.")
        if self.devices is not None:
            if not isinstance(self.devices, tuple):
                raise TypeError(f"devices={self.devices!r}; expected a list of JAX devices, e.g. jax.devices()[:2].")
            if not self.devices:
                raise ValueError("devices is empty; pass None for all devices or a list of JAX devices.")
            if not all(isinstance(d, jax.Device) for d in self.devices):
                raise TypeError(f"devices={self.devices!r}; every entry must be a JAX device.")
            if len(set(self.devices)) != len(self.devices):
                raise ValueError(f"devices={self.devices!r} lists a device twice; each device takes one chunk.")
        if self.checkpoint is not None and not isinstance(self.checkpoint, (bool, np.bool_)):
            raise TypeError(f"checkpoint={self.checkpoint!r}; expected True, False or None.")


def _span_end(name: str):
    return lambda value: check_number(name, value)


class RunOptions(eqx.Module):
    """A run's options, checked once: the span ``(t0, t1)``, the steps, the solver, what is saved and how paths are
    batched.  Pass it whole as ``run=`` to :func:`~nhsde.simulate`, :func:`~nhsde.sweep`,
    :func:`~nhsde.statistics.moment_sensitivities` and every estimator; their flat keywords (``t1=``, ``dt=``,
    ``solver=``, …) are sugar that builds it.  The estimators' levels, pilots and coupled solves are the same options
    at other steps (:meth:`at`) or solvers.

    Arguments:
        t1: the final time.
        steps: :class:`FixedSteps` or :class:`AdaptiveSteps` (estimators: fixed steps only).
        t0: the initial time (default 0).
        solver: a diffrax SDE solver or an alias of ``nhsde.SOLVERS`` (default ``'euler'``).
        save: what is kept (:class:`~nhsde.Save`; default: every state component at ≤ 11 times for ``simulate``,
            the statistic's components for an estimator).
        batching: :class:`Batching` (default: its defaults).

    Examples:
        >>> import nhsde
        >>> run = nhsde.RunOptions(t1=1.0, steps=nhsde.FixedSteps(0.25))
        >>> run.n_steps, run.at(0.125).n_steps, run.solver
        (4, 8, 'euler')
        >>> nhsde.RunOptions(t1=1.0, steps=nhsde.FixedSteps(0.3))
        Traceback (most recent call last):
        ...
        ValueError: dt=0.3 must divide t1 − t0 = 1.0 into a whole number of steps.
    """

    t1: float = eqx.field(converter=_span_end("t1"))
    steps: AbstractSteps
    t0: float = eqx.field(default=0.0, converter=_span_end("t0"))
    solver: str | dfx.AbstractSolver = "euler"
    save: Save | None = None
    batching: Batching = eqx.field(default=None, converter=lambda b: Batching() if b is None else b)

    def __check_init__(self):
        check_span(self.t0, self.t1)
        if not isinstance(self.steps, AbstractSteps):
            raise TypeError(f"steps={self.steps!r}; expected nhsde.FixedSteps(...) or nhsde.AdaptiveSteps(...).")
        if self.save is not None and not isinstance(self.save, Save):
            raise TypeError(f"save={self.save!r}; expected nhsde.Save(...).")
        if not isinstance(self.batching, Batching):
            raise TypeError(f"batching={self.batching!r}; expected nhsde.Batching(...).")
        step, span = float(self.steps.dt), self.t1 - self.t0
        if step > span:
            raise ValueError(f"dt={step} is larger than t1 − t0 = {span}.")
        n_steps = self.n_steps
        if n_steps > self.steps.max_steps:
            raise ValueError(
                f"dt={step} makes {n_steps} steps of (t0, t1) = ({self.t0}, {self.t1}), beyond the budget "
                f"max_steps={self.steps.max_steps}; raise it with steps=FixedSteps(dt, max_steps=…) to run this long."
            )
        self.substeps  # noqa: B018  (raises where brownian_dt does not divide the step)

    @property
    def n_steps(self) -> int:
        """Steps of ``(t0, t1)``."""
        return check_steps("dt", self.t1 - self.t0, float(self.steps.dt))

    @property
    def dt(self) -> float:
        """The step taken, ``(t1 − t0)/n_steps``."""
        return (self.t1 - self.t0) / self.n_steps

    @property
    def substeps(self) -> int:
        """Base steps of the Brownian path per step (1 where ``brownian_dt`` is not set)."""
        base = getattr(self.steps, "brownian_dt", None)
        return 1 if base is None else check_steps("brownian_dt", self.dt, float(base))

    def at(self, dt: float, brownian_dt: float | None = None) -> "RunOptions":
        """The same options at fixed steps ``dt`` on a Brownian path of base step ``brownian_dt`` (a level, a pilot,
        one of a coupled pair), the step budget kept."""
        steps = FixedSteps(dt, brownian_dt=brownian_dt, max_steps=self.steps.max_steps)
        return dataclasses.replace(self, steps=steps)


_FLAT = ("t0", "t1", "dt", "steps", "solver", "save", "batching")


def run_options(
    who: str,
    run: "RunOptions | None" = None,
    *,
    t0=None,
    t1=None,
    dt=None,
    steps=None,
    solver=None,
    save=None,
    batching=None,
    adaptive: bool = False,
    brownian_dt: bool = False,
) -> RunOptions:
    """The :class:`RunOptions` of a call of ``who`` (:func:`~nhsde.simulate` or an estimator): ``run`` as given, or
    built from the flat keywords (plain sugar: ``t0 = 0``, ``solver = 'euler'``, and the one rule for the step:
    ``dt=h`` or ``steps=…``, not both), never both.  Estimators (``adaptive=False``) take fixed steps only (they
    compare and couple solves on fixed grids), and a ``brownian_dt`` only where ``who`` does not set its own."""
    flat = dict(t0=t0, t1=t1, dt=dt, steps=steps, solver=solver, save=save, batching=batching)
    if run is not None:
        if not isinstance(run, RunOptions):
            raise TypeError(f"run={run!r}; expected nhsde.RunOptions(t0=…, t1=…, steps=…, solver=…).")
        given = [name for name in _FLAT if flat[name] is not None]
        if given:
            raise TypeError(
                f"{who}: run= and {', '.join(f'{n}=' for n in given)} both given; give the run's options once, "
                f"in run= (e.g. dataclasses.replace(run, {given[0]}=…)) or as keywords."
            )
        steps = run.steps
    else:
        if t1 is None:
            raise TypeError(f"{who} needs t1 (or run=nhsde.RunOptions(...)).")
        if steps is None:
            if dt is None:
                allowed = "steps=nhsde.FixedSteps(h)" + (" / nhsde.AdaptiveSteps(h)" if adaptive else "")
                raise TypeError(f"{who} needs a step: dt=h or {allowed}.")
            if isinstance(dt, AbstractSteps):
                raise TypeError(f"dt={dt!r}; give a number, dt=h, or the steps as steps=nhsde.FixedSteps(h).")
            steps = FixedSteps(check_number("dt", dt, positive=True))
        elif dt is not None:
            raise TypeError(f"dt={dt} and steps={steps!r}: give the step once.")
        elif not isinstance(steps, AbstractSteps):
            raise TypeError(f"steps={steps!r}; expected nhsde.FixedSteps(h), or the step as a number, dt=h.")
        solver = "euler" if solver is None else solver
        run = RunOptions(t0=0.0 if t0 is None else t0, t1=t1, steps=steps, solver=solver, save=save, batching=batching)
    if not adaptive:
        if not isinstance(steps, FixedSteps):
            raise ValueError(
                f"steps={steps!r}: {who} compares solves on fixed step grids; use dt=h or steps=nhsde.FixedSteps(h)."
            )
        if steps.brownian_dt is not None and not brownian_dt:
            raise ValueError(f"steps={steps!r}: {who} sets the Brownian path's step itself; leave brownian_dt None.")
    return run
