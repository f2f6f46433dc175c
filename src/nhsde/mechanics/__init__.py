"""Mechanics: from a mechanical specification to the stochastic system, automatically.

Write a nonholonomic system as JAX functions — kinetic energy, potential,
Rayleigh function, linear constraints, forces, random parameters — in a
:class:`MechanicalSpec`, and get its Itô SDE (S0 (1.15)) by one of four routes:
the reduced Voronets equations, their Hamiltonian form, Lagrange's equations
with multipliers, or Gauss's principle of least compulsion
(:func:`formulate`, :func:`build`).  :func:`state_space` gives Ding's
state-space equations (S3) and reports their singularity.
"""

from ._elimination import Elimination as Elimination
from ._elimination import choose_dependent as choose_dependent
from ._forms import ROUTES as ROUTES
from ._forms import AbstractForm as AbstractForm
from ._forms import GaussForm as GaussForm
from ._forms import HamiltonianForm as HamiltonianForm
from ._forms import MultiplierForm as MultiplierForm
from ._forms import ReducedForm as ReducedForm
from ._forms import build as build
from ._forms import formulate as formulate
from ._forms import project_velocity as project_velocity
from ._spec import MechanicalSpec as MechanicalSpec
from ._spec import ServoConstraint as ServoConstraint
from ._state_space import SingularStateSpaceError as SingularStateSpaceError
from ._state_space import StateSpace as StateSpace
from ._state_space import StateSpaceReport as StateSpaceReport
from ._state_space import state_space as state_space
