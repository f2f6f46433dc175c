"""Fitting physical parameters (``eps``, ``nu`` or any parameter leaf) to observed data.

Observed trajectories or measured drift statistics become
:class:`Observations`; :func:`estimate` minimises their Gaussian
quasi-likelihood distance to a model — :class:`Simulated` (through the
differentiable ``nhsde.simulate``), :class:`MomentEquations` (the
normal-approximation method) or :class:`ClosedForm` (closed forms) — with optax, and reports standard errors from the Fisher
information of that likelihood.
"""

from ._estimate import AbstractStatisticsModel as AbstractStatisticsModel
from ._estimate import ClosedForm as ClosedForm
from ._estimate import FitResult as FitResult
from ._estimate import MomentEquations as MomentEquations
from ._estimate import Simulated as Simulated
from ._estimate import estimate as estimate
from ._observations import Observations as Observations
from ._observations import statistic_labels as statistic_labels
from ._observations import statistic_vector as statistic_vector
