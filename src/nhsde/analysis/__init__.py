"""Checks users call on a vector field: invariant measures (Liouville), first integrals, Poincaré sections.

- :func:`check_invariant_measure`: ``div(ρ v)`` by autodiff at given states;
  :func:`measure_obstruction`: S2's criterion (2.5)/(2.21) that no analytic
  measure exists.
- :func:`integral_rates`: ``dF/dt`` by autodiff; :func:`solve_flow` and
  :func:`integral_drift`: conservation along long, accurate, vmapped integrations.
- :func:`poincare_section`: the map of S2 (1.18) on ``E = h``, ``g = g₀``.

A vector field is any ``f(t, y, params)``, e.g. :class:`nhsde.bodies.RollingField`
or a :class:`~nhsde.StochasticSystem`'s ``drift_fn``.
"""

from ._integrals import Flow as Flow
from ._integrals import integral_drift as integral_drift
from ._integrals import integral_rates as integral_rates
from ._integrals import solve_flow as solve_flow
from ._liouville import LiouvilleCheck as LiouvilleCheck
from ._liouville import MeasureObstruction as MeasureObstruction
from ._liouville import check_invariant_measure as check_invariant_measure
from ._liouville import divergence as divergence
from ._liouville import measure_obstruction as measure_obstruction
from ._poincare import PoincareSection as PoincareSection
from ._poincare import andoyer as andoyer
from ._poincare import from_andoyer as from_andoyer
from ._poincare import poincare_section as poincare_section
