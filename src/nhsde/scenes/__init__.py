"""Ready scenes: declarative descriptions that build a :class:`~nhsde.StochasticSystem`.

Each scene takes its physical parameters as keyword arguments (pytree leaves)
and flags naming what the user wants to observe; ``build()`` returns a system
whose state holds only what those need.
"""

from ._ball import BallOnVibratingPlane as BallOnVibratingPlane
from ._ball import BallParameters as BallParameters
from ._ball import ball_covariances as ball_covariances
from ._sleigh import ChaplyginSleigh as ChaplyginSleigh
from ._sleigh import SleighParameters as SleighParameters

SCENES = {
    "ball-on-vibrating-plane": BallOnVibratingPlane,
    "chaplygin-sleigh": ChaplyginSleigh,
}
"""Scene names (as the CLI spells them) → scene classes."""


def get_scene(name: str):
    """The scene class called ``name``; a clear error lists the known names."""
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}.") from None
