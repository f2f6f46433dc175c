"""Statistics of ensembles: drift of the dependent coordinates, stationary moments."""

from ._drift import (
    DriftStatistics as DriftStatistics,
    StationaryMoments as StationaryMoments,
    drift_statistics as drift_statistics,
    effective_diffusion as effective_diffusion,
    fluctuation_drift as fluctuation_drift,
    stationary_moments as stationary_moments,
    systematic_drift as systematic_drift,
)
from ._fokker_planck import (
    GridDensity as GridDensity,
    fokker_planck as fokker_planck,
    stationary_fokker_planck as stationary_fokker_planck,
)
from ._moments import (
    GreenKubo as GreenKubo,
    StationaryDrift as StationaryDrift,
    green_kubo as green_kubo,
    normal_approximation as normal_approximation,
    stationary_drift as stationary_drift,
)
from ._stationary import StationaryDensity as StationaryDensity, stationary_density as stationary_density
