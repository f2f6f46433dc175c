"""nhsde: stochastic nonholonomic mechanics in JAX.

Scenes build a :class:`StochasticSystem` (the Itô SDE of S0 (1.15)); :func:`simulate`
integrates vmapped ensembles on diffrax; :mod:`nhsde.statistics` turns them into
drift statistics, differentiable in every physical parameter.
"""

from . import noise as noise
from . import mechanics as mechanics
from . import scenes as scenes
from . import statistics as statistics
from . import fit as fit
from . import bodies as bodies
from . import analysis as analysis
from ._params import AbstractParameters as AbstractParameters
from ._params import parameter as parameter
from ._params import sqrt_intensity as sqrt_intensity
from ._simulate import SOLVERS as SOLVERS
from ._simulate import Ensemble as Ensemble
from ._simulate import Save as Save
from ._simulate import SimulationError as SimulationError
from ._simulate import simulate as simulate
from ._system import StateLayout as StateLayout
from ._system import StochasticSystem as StochasticSystem
from ._work_precision import WorkPrecisionRow as WorkPrecisionRow
from ._work_precision import cheapest_setting as cheapest_setting
from ._work_precision import work_precision as work_precision

__version__ = "0.1.0"
