"""Mechanics: from a mechanical specification to the stochastic system, automatically.

Write a nonholonomic system as JAX functions — kinetic energy, potential,
Rayleigh function, linear constraints, forces, random parameters — in a
:class:`MechanicalSpec`, and get its Itô SDE (S0 (1.15)) by one of four routes:
the reduced Voronets equations, their Hamiltonian form, Lagrange's equations
with multipliers, or Gauss's principle of least compulsion
(:func:`formulate`, :func:`build`).  :func:`state_space` gives Ding's
state-space equations (S3) and reports their singularity.
"""

from ._elimination import Elimination as Elimination, choose_dependent as choose_dependent
from ._forms import (
    ROUTES as ROUTES,
    AbstractForm as AbstractForm,
    GaussForm as GaussForm,
    HamiltonianForm as HamiltonianForm,
    MultiplierForm as MultiplierForm,
    ReducedForm as ReducedForm,
    build as build,
    formulate as formulate,
    project_velocity as project_velocity,
)
from ._spec import (
    MechanicalSpec as MechanicalSpec,
    ServoConstraint as ServoConstraint,
    SoftConstraint as SoftConstraint,
)
from ._state_space import (
    SingularStateSpaceError as SingularStateSpaceError,
    StateSpace as StateSpace,
    StateSpaceReport as StateSpaceReport,
    state_space as state_space,
)
