"""nhsde: stochastic nonholonomic mechanics in JAX.

Scenes build a :class:`StochasticSystem` (the Itô SDE of S0 (1.15)); :func:`simulate`
integrates vmapped ensembles on diffrax; :mod:`nhsde.statistics` turns them into
drift statistics, differentiable in every physical parameter.
"""

import importlib.metadata

from . import (
    analysis as analysis,
    bodies as bodies,
    fit as fit,
    mechanics as mechanics,
    noise as noise,
    scenes as scenes,
    statistics as statistics,
)
from ._params import AbstractParameters as AbstractParameters, parameter as parameter, sqrt_intensity as sqrt_intensity
from ._simulate import (
    SOLVERS as SOLVERS,
    Ensemble as Ensemble,
    Save as Save,
    SimulationError as SimulationError,
    simulate as simulate,
)
from ._system import StateLayout as StateLayout, StochasticSystem as StochasticSystem
from ._work_precision import (
    WorkPrecisionRow as WorkPrecisionRow,
    cheapest_setting as cheapest_setting,
    work_precision as work_precision,
)

__version__ = importlib.metadata.version("nhsde")
