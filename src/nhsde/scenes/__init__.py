"""Ready scenes: declarative descriptions that build a :class:`~nhsde.StochasticSystem`.

Every scene keeps one contract, :class:`AbstractScene` (parameters as pytree
leaves, keyword construction with flags naming what to observe, ``build()``,
``initial_state()``, ``observable_names()``, a CLI ``name``); a scene given by
its energies and constraints subclasses :class:`AbstractSpecScene`.  ``SCENES``
is derived from the concrete scenes defined here.  The deterministic rolling
bodies (:class:`RollingBody`, :class:`FlatBaseOnSphere`, :class:`Rattleback`)
are another kind, :class:`AbstractRollingBodyScene`: ODEs, not in ``SCENES``.
"""

from pathlib import Path

from ._ball import (
    BallOnVibratingPlane as BallOnVibratingPlane,
    BallParameters as BallParameters,
    ball_covariances as ball_covariances,
    ball_two_time_covariances as ball_two_time_covariances,
)
from ._base import (
    AbstractRollingBodyScene as AbstractRollingBodyScene,
    AbstractScene as AbstractScene,
    scene_registry,
)
from ._beghin import BeghinParameters as BeghinParameters, BeghinPlate as BeghinPlate
from ._body_on_vibrating_plane import (
    BodyOnVibratingPlane as BodyOnVibratingPlane,
    VibratingPlaneParameters as VibratingPlaneParameters,
    revolution_measure_s0 as revolution_measure_s0,
    sample_stationary as sample_stationary,
    stationary_nutation_density as stationary_nutation_density,
)
from ._chaplygin_ball import (
    ChaplyginBall as ChaplyginBall,
    ChaplyginBallParameters as ChaplyginBallParameters,
    chaplygin_ball_measure as chaplygin_ball_measure,
    chaplygin_ball_omega as chaplygin_ball_omega,
)
from ._contact_oscillator import (
    ContactOscillator as ContactOscillator,
    ContactOscillatorParameters as ContactOscillatorParameters,
)
from ._disk import DiskParameters as DiskParameters, VerticalRollingDisk as VerticalRollingDisk
from ._lookup import (
    ENTRY_POINT_GROUP as ENTRY_POINT_GROUP,
    find_scene,
    installed_scenes as _installed,
    scene_source_hash as scene_source_hash,
)
from ._rattleback import Rattleback as Rattleback
from ._rolling import FlatBaseOnSphere as FlatBaseOnSphere, RollingBody as RollingBody
from ._rolling_ball import BallFromLagrangian as BallFromLagrangian, RollingBallParameters as RollingBallParameters
from ._rolling_disk import (
    RollingDisk as RollingDisk,
    RollingDiskParameters as RollingDiskParameters,
    rolling_disk_kinematics as rolling_disk_kinematics,
)
from ._rotating_rod import BeadOnRotatingRod as BeadOnRotatingRod, RodParameters as RodParameters
from ._sleigh import ChaplyginSleigh as ChaplyginSleigh, SleighParameters as SleighParameters
from ._spec_scene import AbstractSpecScene as AbstractSpecScene
from ._spec_sleigh import ChaplyginSleighFromSpec as ChaplyginSleighFromSpec
from ._thermal_disk import (
    BathDiskParameters as BathDiskParameters,
    VerticalRollingDiskInBath as VerticalRollingDiskInBath,
)
from ._thermal_sleigh import (
    BathSleighParameters as BathSleighParameters,
    ChaplyginSleighInBath as ChaplyginSleighInBath,
)

SCENES = scene_registry(__name__)
"""Scene names (as the CLI spells them) → scene classes: every concrete :class:`AbstractScene` defined in
``nhsde.scenes`` (read-only, derived from the classes' ``name``)."""


def installed_scenes() -> dict[str, str]:
    """The scenes installed packages add: ``name → "MODULE:CLASS"`` of the entry points in the group
    ``nhsde.scenes`` (:data:`ENTRY_POINT_GROUP`), but those whose name is a shipped scene's.

    A package adds one in its ``pyproject.toml``::

        [project.entry-points."nhsde.scenes"]
        knife-edge = "my_scenes:KnifeEdge"
    """
    return _installed(SCENES)


def get_scene(name: str, *, folder: str | Path | None = None) -> type[AbstractScene]:
    """The scene class called ``name``: a shipped scene, an installed one, or ``MODULE:CLASS``.

    Arguments:
        name: a scene's CLI name (a key of ``SCENES`` or of :func:`installed_scenes`), or ``"MODULE:CLASS"``:
            the class ``CLASS`` of the module ``MODULE``, imported from the Python path (which runs the module's
            code, as ``import`` does).
        folder: a folder to look for ``MODULE`` in first (that module only); the ``nhsde`` command passes the
            current directory for a ``MODULE:CLASS`` named on its command line, and nothing else looks there.

    Returns:
        the scene class (construct it with keyword arguments).

    Raises:
        ValueError: naming ``name`` and what is wrong: an unknown name (the known ones are listed), a module
            not found, a missing attribute, or an object that is not a concrete scene class.

    Examples:
        >>> from nhsde import scenes
        >>> scenes.get_scene("ball-on-vibrating-plane")
        <class 'nhsde.scenes._ball.BallOnVibratingPlane'>
        >>> scenes.get_scene("nhsde.scenes:ChaplyginSleigh")
        <class 'nhsde.scenes._sleigh.ChaplyginSleigh'>
        >>> scenes.get_scene("ball")
        Traceback (most recent call last):
        ...
        ValueError: scene 'ball': unknown scene; known scenes: ball-on-vibrating-plane, ...
        >>> scenes.get_scene("nhsde.scenes:AbstractSpecScene")
        Traceback (most recent call last):
        ...
        ValueError: scene 'nhsde.scenes:AbstractSpecScene': AbstractSpecScene is an abstract scene; ...
    """
    try:
        return find_scene(name, SCENES, folder=None if folder is None else Path(folder))
    except ValueError as e:
        raise ValueError(f"scene {name!r}: {e}") from None
