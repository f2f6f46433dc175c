"""Statistics of ensembles and of the moment equations: drift of the dependent coordinates, stationary laws.

- From the moments of an ensemble (:func:`~nhsde.simulate`, or the moment
  equations): :func:`drift_statistics` (S0 (6.7)), :func:`effective_diffusion` (and its
  standard error from the paths, :func:`effective_diffusion_se`),
  :func:`stationary_moments`; from its paths: :func:`green_kubo`.
- The normal approximation (S0 §6): :func:`normal_approximation` over time,
  :func:`stationary_drift` in the stationary regime.
- Exact stationary densities (S0 Statements 1–2): :func:`stationary_density`.
- Statistics at a requested accuracy for less work: :func:`extrapolate`
  (Richardson–Romberg / Talay–Tubaro), :func:`multilevel_monte_carlo` (Giles),
  :func:`antithetic` paths, :func:`control_variate` (the linearised system
  driven by the same increments), :func:`martingale_control_variate` (the discrete martingale Σ Z(Xₙ)·ΔWₙ fitted
  on a pilot), :func:`quasi_monte_carlo` (scrambled Sobol'
  points through a Brownian bridge), :func:`multilevel_quasi_monte_carlo`; :func:`to_accuracy` chooses among
  them from a pilot run for a requested RMSE, among estimator objects (:class:`PlainMonteCarlo`,
  :class:`Richardson`, :class:`Multilevel`, :class:`ControlVariate`, :class:`QuasiMonteCarlo`,
  :class:`MultilevelQuasiMonteCarlo`, :class:`MartingaleControlVariate`; ``estimators=``) that
  each predict their work from a pilot and run their plan.  Each returns an :class:`AbstractEstimate` (moments, standard
  errors, ``derivatives``, measured ``cost``); a statistic is named once, :class:`Mean` or :class:`Covariance`.
- Derivatives of simulated moments with their standard errors: :func:`moment_sensitivities`.
- The Fokker–Planck equation on a grid (1 and 2 components):
  :func:`stationary_fokker_planck`, :func:`fokker_planck`.
"""

from ._accuracy import AccuracyResult as AccuracyResult, to_accuracy as to_accuracy
from ._control_variate import (
    ControlVariateEstimate as ControlVariateEstimate,
    PerEntry as PerEntry,
    control_variate as control_variate,
    linearised_system as linearised_system,
)
from ._drift import (
    DriftStatistics as DriftStatistics,
    GreenKubo as GreenKubo,
    StationaryMoments as StationaryMoments,
    drift_statistics as drift_statistics,
    effective_diffusion as effective_diffusion,
    effective_diffusion_se as effective_diffusion_se,
    fluctuation_drift as fluctuation_drift,
    green_kubo as green_kubo,
    stationary_moments as stationary_moments,
    systematic_drift as systematic_drift,
)
from ._estimate import (
    AbstractEstimate as AbstractEstimate,
    AbstractStatistic as AbstractStatistic,
    Cost as Cost,
    Covariance as Covariance,
    Derivatives as Derivatives,
    Mean as Mean,
    MonteCarloEstimate as MonteCarloEstimate,
)
from ._estimators import (
    AbstractEstimator as AbstractEstimator,
    ControlVariate as ControlVariate,
    Multilevel as Multilevel,
    MultilevelQuasiMonteCarlo as MultilevelQuasiMonteCarlo,
    PlainMonteCarlo as PlainMonteCarlo,
    QuasiMonteCarlo as QuasiMonteCarlo,
    Richardson as Richardson,
)
from ._extrapolation import Extrapolation as Extrapolation, extrapolate as extrapolate
from ._fokker_planck import (
    GridDensity as GridDensity,
    fokker_planck as fokker_planck,
    stationary_fokker_planck as stationary_fokker_planck,
)
from ._martingale import martingale_control_variate as martingale_control_variate
from ._martingale_estimator import MartingaleControlVariate as MartingaleControlVariate
from ._multilevel import MultilevelEstimate as MultilevelEstimate, multilevel_monte_carlo as multilevel_monte_carlo
from ._multilevel_qmc import (
    multilevel_quasi_monte_carlo as multilevel_quasi_monte_carlo,
    quasi_monte_carlo as quasi_monte_carlo,
)
from ._normal_approximation import (
    NormalApproximation as NormalApproximation,
    normal_approximation as normal_approximation,
)
from ._qmc import QuasiMonteCarloEstimate as QuasiMonteCarloEstimate
from ._report import AccuracyAlternative as AccuracyAlternative
from ._sensitivities import Sensitivities as Sensitivities, moment_sensitivities as moment_sensitivities
from ._stationary import StationaryDensity as StationaryDensity, stationary_density as stationary_density
from ._stationary_drift import StationaryDrift as StationaryDrift, stationary_drift as stationary_drift
from ._variance_reduction import Antithetic as Antithetic, antithetic as antithetic
