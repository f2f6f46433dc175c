"""Noise: Brownian paths and drivers."""

from ._brownian import BLOCK as BLOCK
from ._brownian import CounterBrownianPath as CounterBrownianPath
from ._brownian import block_keys as block_keys
from ._brownian import AbstractDriver as AbstractDriver
from ._brownian import Wiener as Wiener
