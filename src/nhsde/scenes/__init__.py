"""Ready scenes: declarative descriptions that build a :class:`~nhsde.StochasticSystem`.

Each scene takes its physical parameters as keyword arguments (pytree leaves)
and flags naming what the user wants to observe; ``build()`` returns a system
whose state holds only what those need.
"""

from ._ball import (
    BallOnVibratingPlane as BallOnVibratingPlane,
    BallParameters as BallParameters,
    ball_covariances as ball_covariances,
)
from ._beghin import BeghinParameters as BeghinParameters, BeghinPlate as BeghinPlate
from ._contact_oscillator import (
    ContactOscillator as ContactOscillator,
    ContactOscillatorParameters as ContactOscillatorParameters,
)
from ._disk import DiskParameters as DiskParameters, VerticalRollingDisk as VerticalRollingDisk
from ._rolling_ball import BallFromLagrangian as BallFromLagrangian, RollingBallParameters as RollingBallParameters
from ._rolling_disk import RollingDisk as RollingDisk, RollingDiskParameters as RollingDiskParameters
from ._rotating_rod import BeadOnRotatingRod as BeadOnRotatingRod, RodParameters as RodParameters
from ._sleigh import ChaplyginSleigh as ChaplyginSleigh, SleighParameters as SleighParameters
from ._spec_scene import AbstractSpecScene as AbstractSpecScene
from ._spec_sleigh import ChaplyginSleighFromSpec as ChaplyginSleighFromSpec

SCENES = {
    "ball-on-vibrating-plane": BallOnVibratingPlane,
    "chaplygin-sleigh": ChaplyginSleigh,
    "chaplygin-sleigh-from-spec": ChaplyginSleighFromSpec,
    "vertical-rolling-disk": VerticalRollingDisk,
    "rolling-disk": RollingDisk,
    "contact-oscillator": ContactOscillator,
    "beghin-plate": BeghinPlate,
    "ball-from-lagrangian": BallFromLagrangian,
    "bead-on-rotating-rod": BeadOnRotatingRod,
}
"""Scene names (as the CLI spells them) → scene classes."""


def get_scene(name: str):
    """The scene class called ``name``; a clear error lists the known names."""
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}.") from None


from ._body_on_vibrating_plane import (
    BodyOnVibratingPlane as BodyOnVibratingPlane,
    VibratingPlaneParameters as VibratingPlaneParameters,
    revolution_measure_s0 as revolution_measure_s0,
    stationary_nutation_density as stationary_nutation_density,
)
from ._chaplygin_ball import (
    ChaplyginBall as ChaplyginBall,
    ChaplyginBallParameters as ChaplyginBallParameters,
    chaplygin_ball_measure as chaplygin_ball_measure,
    chaplygin_ball_omega as chaplygin_ball_omega,
)
from ._rattleback import Rattleback as Rattleback
from ._rolling import FlatBaseOnSphere as FlatBaseOnSphere, RollingBody as RollingBody

SCENES["body-on-vibrating-plane"] = BodyOnVibratingPlane
SCENES["chaplygin-ball"] = ChaplyginBall
from ._body_on_vibrating_plane import sample_stationary as sample_stationary
