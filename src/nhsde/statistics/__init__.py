"""Statistics of ensembles: drift of the dependent coordinates, stationary moments."""

from ._drift import DriftStatistics as DriftStatistics
from ._drift import StationaryMoments as StationaryMoments
from ._drift import drift_statistics as drift_statistics
from ._drift import effective_diffusion as effective_diffusion
from ._drift import fluctuation_drift as fluctuation_drift
from ._drift import stationary_moments as stationary_moments
from ._drift import systematic_drift as systematic_drift
from ._moments import GreenKubo as GreenKubo
from ._moments import StationaryDrift as StationaryDrift
from ._moments import green_kubo as green_kubo
from ._moments import normal_approximation as normal_approximation
from ._moments import stationary_drift as stationary_drift
from ._stationary import StationaryDensity as StationaryDensity
from ._stationary import stationary_density as stationary_density
from ._fokker_planck import GridDensity as GridDensity
from ._fokker_planck import fokker_planck as fokker_planck
from ._fokker_planck import stationary_fokker_planck as stationary_fokker_planck
