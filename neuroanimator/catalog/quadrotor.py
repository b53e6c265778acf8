"""A quadrotor: a free flyer that tumbles, with rotor thrust, rotor reaction torques and air drag.

It is the catalog's test of the body frame: random rotor commands flip it over, so its data cover
every attitude, including upside down, where a heading is undefined.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

from neuroanimator.core.model_spec import ControlInfo, InitialStates, ModelSpec
from neuroanimator.goals.criteria import SuccessCheck
from neuroanimator.goals.policy_task import GoalSpec, PolicyTask, StartBox
from neuroanimator.goals.spec import Task

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

XML_PATH = Path(__file__).with_name("quadrotor.xml")
HOVER_THRUST = 1.0 * 9.81 / 4.0  # per rotor, newtons


TASKS: tuple[Task, ...] = ()  # no control task is set on it yet


# The rotors (units and gains from the MJCF: 1 N of thrust per unit, 0.016 N·m of reaction torque per N).
CONTROL_INFO = {
    f"rotor_{corner}": ControlInfo(
        label=f"{where} rotor",
        sign=f"thrust along the body's own +z axis (0 is off, it never pulls); the blades' reaction "
        f"torque turns the body about its {turn} axis (right-hand rule)",
    )
    for corner, where, turn in (
        ("fl", "front-left", "+z"),
        ("fr", "front-right", "−z"),
        ("bl", "back-left", "−z"),
        ("br", "back-right", "+z"),
    )
}


def quadrotor() -> PhysicalModel:
    from neuroanimator.sim.model import PhysicalModel  # MuJoCo loads when a model is built

    spec = ModelSpec(
        name="quadrotor",
        description="quadrotor: free rigid body, four rotors with reaction torques, air drag; flips over",
        control_info=CONTROL_INFO,
        # rotor commands within ±50% of hover, changing every 0.5 s: a differential of a newton or two
        # spins it at several turns per second, so it flips within a few seconds
        control_low=[0.5 * HOVER_THRUST] * 4,
        control_high=[1.5 * HOVER_THRUST] * 4,
        control_spacing_s=0.5,
        initial=InitialStates(
            # anywhere in a 20 m box around its start, any attitude, moving and spinning
            low=[-10, -10, -10, 0, 0, 0, 0, -2, -2, -2, -1, -1, -1],
            high=[10, 10, 10, 0, 0, 0, 0, 2, 2, 2, 1, 1, 1],
            random_yaw=True,
            max_tilt=math.pi,
        ),
        episode_s=10.0,
        substeps=25,
    )
    return PhysicalModel(XML_PATH.read_text(), spec)


_POS = ("root.pos.x", "root.pos.y", "root.pos.z")
# Follow a target that moves every 5 s to a point within 3 m of where it was (where MuJoCo's
# quadrotor goes in its typical motion, within 3 m of its start): within 0.3 m of it 2 s after each move. Control
# every 0.125 s (the n = 25 emulator).
POLICY_FOLLOW = PolicyTask(
    name="quadrotor-follow",
    model="quadrotor",
    summary=(
        "Quadrotor: follow a target that moves every 5 s to a point within 3 m: within 0.3 m of it 2 s "
        "after each move."
    ),
    labels=(
        *_POS,
        "root.quat.w",
        "root.quat.x",
        "root.quat.y",
        "root.quat.z",
        "root.vel.x",
        "root.vel.y",
        "root.vel.z",
        "root.angvel.x",
        "root.angvel.y",
        "root.angvel.z",
    ),
    substeps=25,
    episode_s=20.0,
    starts=StartBox(
        low=(-1.0, -1.0, 9.0, 1, 0, 0, 0, -0.3, -0.3, -0.3, -0.2, -0.2, -0.2),
        high=(1.0, 1.0, 11.0, 1, 0, 0, 0, 0.3, 0.3, 0.3, 0.2, 0.2, 0.2),
        random_yaw=True,
        max_tilt=0.15,
    ),
    goal=GoalSpec(variables=_POS, low=(-3.0, -3.0, 7.0), high=(3.0, 3.0, 13.0), max_move=3.0),
    target_state=(0.0, 0.0, 10.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.0, 0.2, 0.2, 0.2, 0.05, 0.05, 0.05),
    success=(SuccessCheck(check="distance", variables=list(_POS), max=0.3),),
    goal_period_s=5.0,
    check_after_s=2.0,
    settle_s=1.5,
    train_seconds=300.0,
)
POLICY_TASKS = (POLICY_FOLLOW,)
