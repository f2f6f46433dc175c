"""Fitting physical parameters (``eps``, ``nu`` or any parameter leaf) to observed data.

Observed trajectories or measured drift statistics become
:class:`Observations`; :func:`estimate` minimises their Gaussian
quasi-likelihood distance to a model — :class:`Simulated` (through the
differentiable ``nhsde.simulate``), :class:`MomentEquations` (the
normal-approximation method) or :class:`ClosedForm` (closed forms) — with optax, and reports standard errors from
the Fisher
information of that likelihood.
"""

from ._estimate import (
    AbstractStatisticsModel as AbstractStatisticsModel,
    ClosedForm as ClosedForm,
    FitResult as FitResult,
    MomentEquations as MomentEquations,
    Simulated as Simulated,
    estimate as estimate,
)
from ._observations import (
    Observations as Observations,
    gaussian_statistic_covariance as gaussian_statistic_covariance,
    statistic_labels as statistic_labels,
    statistic_vector as statistic_vector,
)
