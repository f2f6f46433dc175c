"""Noise: drivers of the stochastic systems and their counter-based increments."""

from ._brownian import (
    BLOCK as BLOCK,
    AbstractDriver as AbstractDriver,
    StepIncrement as StepIncrement,
    Wiener as Wiener,
    block_keys as block_keys,
)
from ._filters import (
    AbstractShapingFilter as AbstractShapingFilter,
    FilteredParameters as FilteredParameters,
    OrnsteinUhlenbeck as OrnsteinUhlenbeck,
    ShapingFilter as ShapingFilter,
    with_shaping_filter as with_shaping_filter,
)
from ._levy import (
    JUMP_STREAM as JUMP_STREAM,
    TRUNCATION as TRUNCATION,
    AbstractJumpLaw as AbstractJumpLaw,
    CompoundPoisson as CompoundPoisson,
    Levy as Levy,
    NormalJumps as NormalJumps,
    ParetoJumps as ParetoJumps,
    driver_intensity as driver_intensity,
)
