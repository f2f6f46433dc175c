"""Checks users call on a vector field: invariant measures (Liouville), first integrals, Poincaré sections.

- :func:`check_invariant_measure`: ``div(ρ v)`` by autodiff at given states;
  :func:`measure_obstruction`: S2's criterion (2.5)/(2.21) that no analytic
  measure exists.
- :func:`integral_rates`: ``dF/dt`` by autodiff; :func:`solve_flow` and
  :func:`integral_drift`: conservation along long, accurate, vmapped integrations.
- :func:`poincare_section`: the map of S2 (1.18) on ``E = h``, ``g = g₀``.
- :func:`linear_stability` (:func:`jacobian`, :class:`Stability`): eigenvalues of the
  linearisation about a steady state in a family of steady states (S4 Theorem 4.1).
- :func:`chaplygin_system`, :func:`steady_motions`, :func:`steady_stability`,
  :func:`stability_boundary`: steady motions of Chaplygin systems (S4 (4.9)), the
  Routh-reduced characteristic equation (4.19) (:func:`routh_pencil`,
  :func:`delta_matrix`) and Andronov–Hopf points (Remark 4.6).
- :func:`stationary_spread`, :func:`linear_residence_time`, :func:`residence_time`:
  with friction and noise, the linearised (Ornstein–Uhlenbeck) spread about a
  stable steady motion and the mean residence time near it, linearised and by
  Monte Carlo.

A vector field is any ``f(t, y, params)``, e.g. :class:`nhsde.bodies.RollingField`
or a :class:`~nhsde.StochasticSystem`'s ``drift_fn``.
"""

from ._chaplygin import ChaplyginSystem as ChaplyginSystem, chaplygin_system as chaplygin_system
from ._flow import Flow as Flow, solve_flow as solve_flow
from ._integrals import integral_drift as integral_drift, integral_rates as integral_rates
from ._linearised import (
    LinearResidence as LinearResidence,
    Spread as Spread,
    linear_residence_time as linear_residence_time,
    stationary_spread as stationary_spread,
)
from ._liouville import (
    LiouvilleCheck as LiouvilleCheck,
    MeasureObstruction as MeasureObstruction,
    check_invariant_measure as check_invariant_measure,
    divergence as divergence,
    measure_obstruction as measure_obstruction,
)
from ._poincare import (
    PoincareSection as PoincareSection,
    andoyer as andoyer,
    from_andoyer as from_andoyer,
    poincare_section as poincare_section,
)
from ._residence import Residence as Residence, residence_time as residence_time
from ._routh import delta_matrix as delta_matrix, routh_pencil as routh_pencil
from ._stability import Stability as Stability, jacobian as jacobian, linear_stability as linear_stability
from ._steady import SteadyMotions as SteadyMotions, steady_motions as steady_motions
from ._steady_stability import (
    StabilityBoundary as StabilityBoundary,
    SteadyStability as SteadyStability,
    stability_boundary as stability_boundary,
    steady_stability as steady_stability,
)
