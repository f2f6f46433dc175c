"""nhsde: stochastic nonholonomic mechanics in JAX.

Scenes build a :class:`StochasticSystem` (the Itô SDE of S0 (1.15)); :func:`simulate`
integrates vmapped ensembles on diffrax into an :class:`Ensemble`;
:mod:`nhsde.statistics` and :mod:`nhsde.analysis` turn them into drift statistics,
differentiable in every physical parameter; :mod:`nhsde.fit` estimates parameters
and :mod:`nhsde.runs` runs resumable files from the command line.
"""

import importlib
import importlib.metadata
from typing import TYPE_CHECKING

from . import (
    analysis as analysis,
    bodies as bodies,
    mechanics as mechanics,
    noise as noise,
    scenes as scenes,
    statistics as statistics,
)
from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._ensemble import (
    AbstractMoments as AbstractMoments,
    Ensemble as Ensemble,
    MomentSums as MomentSums,
    Save as Save,
    SimulationError as SimulationError,
    SimulationResult as SimulationResult,
    StationaryVarianceWarning as StationaryVarianceWarning,
)
from ._options import (
    AbstractSteps as AbstractSteps,
    AdaptiveSteps as AdaptiveSteps,
    Batching as Batching,
    FixedSteps as FixedSteps,
    RunOptions as RunOptions,
)
from ._params import (
    AbstractParameters as AbstractParameters,
    parameter as parameter,
    sqrt_intensity as sqrt_intensity,
    validated as validated,
)
from ._simulate import simulate as simulate
from ._solvers import SOLVERS as SOLVERS, ExponentialEuler as ExponentialEuler
from ._system import StateLayout as StateLayout, StochasticSystem as StochasticSystem
from ._weak import (
    GaussianWeakIncrement as GaussianWeakIncrement,
    PlatenWeak2 as PlatenWeak2,
    ThreePointIncrement as ThreePointIncrement,
    WeakIncrement as WeakIncrement,
)
from ._work_precision import (
    WorkPrecisionRow as WorkPrecisionRow,
    cheapest_setting as cheapest_setting,
    work_precision as work_precision,
)

__version__ = importlib.metadata.version("nhsde")

if TYPE_CHECKING:
    from . import fit as fit
    from ._sweep import sweep as sweep

_LAZY = {"fit": ("nhsde.fit", None), "sweep": ("nhsde._sweep", "sweep")}
"""Imported when first used (``nhsde.fit``, ``from nhsde import sweep``): optax and xarray with pandas take about
0.4 s each to import, which a process that only simulates need not spend."""


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'nhsde' has no attribute {name!r}")
    module, attribute = _LAZY[name]
    value = importlib.import_module(module)
    value = value if attribute is None else getattr(value, attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
