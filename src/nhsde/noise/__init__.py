"""Noise beyond the Wiener process: jump drivers and their laws (S0 (1.3)–(1.4)), shaping filters for coloured
noise (S0 (1.2))."""

from .._brownian import AbstractDriver as AbstractDriver, Wiener as Wiener
from ._filters import (
    AbstractShapingFilter as AbstractShapingFilter,
    FilteredParameters as FilteredParameters,
    OrnsteinUhlenbeck as OrnsteinUhlenbeck,
    ShapingFilter as ShapingFilter,
    with_shaping_filter as with_shaping_filter,
)
from ._levy import (
    AbstractJumpLaw as AbstractJumpLaw,
    CompoundPoisson as CompoundPoisson,
    Levy as Levy,
    NormalJumps as NormalJumps,
    ParetoJumps as ParetoJumps,
    driver_intensity as driver_intensity,
)
