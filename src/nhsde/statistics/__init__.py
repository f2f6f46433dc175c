"""Statistics of ensembles: drift of the dependent coordinates, stationary moments."""

from ._drift import DriftStatistics as DriftStatistics
from ._drift import StationaryMoments as StationaryMoments
from ._drift import drift_statistics as drift_statistics
from ._drift import effective_diffusion as effective_diffusion
from ._drift import fluctuation_drift as fluctuation_drift
from ._drift import stationary_moments as stationary_moments
from ._drift import systematic_drift as systematic_drift
