"""A ball on a floor: the catalog's model with ground contact.

A free sphere dropped onto a plane lands, then rolls and slides under two horizontal pushes fixed
in the world's axes. Its data hold every kind of contact state: in the air, landing, sliding and
rolling; contacts engage in most of its states, which is what the trainer's constrained-model
defaults are for (``super_step.constrained_defaults``) and why it is emulated at a short super-step
(n = 10, 0.02 s).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

from neuroanimator.core.model_spec import ControlInfo, InitialStates, ModelSpec
from neuroanimator.goals.spec import Task

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

XML_PATH = Path(__file__).with_name("ball.xml")
RADIUS = 0.15  # metres: the ball's centre is this high when it rests on the floor

TASKS: tuple[Task, ...] = ()  # no control task is set on it yet

CONTROL_INFO = {
    f"push_{axis}": ControlInfo(
        label=f"push along {axis}",
        sign=f"a force in newtons through the ball's centre along the world's +{axis} axis, whichever "
        "way the ball has turned",
    )
    for axis in ("x", "y")
}


def ball() -> PhysicalModel:
    from neuroanimator.sim.model import PhysicalModel  # MuJoCo loads when a model is built

    spec = ModelSpec(
        name="ball",
        description="ball on a floor: dropped, it lands, rolls and slides under two horizontal pushes",
        control_info=CONTROL_INFO,
        control_spacing_s=0.5,
        initial=InitialStates(
            # anywhere in a 10 m square, from resting on the floor (z = 0.15) to dropped from 1 m,
            # moving and spinning, in any orientation; the MJCF's start is z = 0.5. (Starts at up to
            # 3 m/s and 10 rad/s, the speeds a few seconds of pushes reach, halved the drift of a
            # 5 s rollout but raised the one-step error from 0.0089 to 0.0124: BENCHMARKS.md)
            low=[-5, -5, -0.35, 0, 0, 0, 0, -1, -1, -1, -3, -3, -3],
            high=[5, 5, 0.5, 0, 0, 0, 0, 1, 1, 0.5, 3, 3, 3],
            random_yaw=True,
            max_tilt=math.pi,
        ),
        # a run restarts every 2.5 s: a fresh drop, landing and roll each time, so that landings (the
        # contact's hardest moments, a few percent of the states) are not rare in the data
        episode_s=2.5,
        substeps=10,
    )
    return PhysicalModel(XML_PATH.read_text(), spec)
