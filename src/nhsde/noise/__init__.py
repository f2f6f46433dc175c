"""Noise: drivers of the stochastic systems and their counter-based increments."""

from ._brownian import BLOCK as BLOCK
from ._brownian import AbstractDriver as AbstractDriver
from ._brownian import StepIncrement as StepIncrement
from ._brownian import Wiener as Wiener
from ._brownian import block_keys as block_keys
from ._levy import JUMP_STREAM as JUMP_STREAM
from ._levy import TRUNCATION as TRUNCATION
from ._levy import AbstractJumpLaw as AbstractJumpLaw
from ._levy import CompoundPoisson as CompoundPoisson
from ._levy import Levy as Levy
from ._levy import NormalJumps as NormalJumps
from ._levy import ParetoJumps as ParetoJumps
from ._levy import driver_intensity as driver_intensity
from ._filters import AbstractShapingFilter as AbstractShapingFilter
from ._filters import FilteredParameters as FilteredParameters
from ._filters import OrnsteinUhlenbeck as OrnsteinUhlenbeck
from ._filters import ShapingFilter as ShapingFilter
from ._filters import with_shaping_filter as with_shaping_filter
