"""The truck (thesis E.3): a planar block steered by a side force ahead of its centre, and its
parking task (thesis 6.2)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

from neuroanimator.core.model_spec import ControlInfo, InitialStates, ModelSpec
from neuroanimator.core.state import StateGroup, StateLayout
from neuroanimator.goals.criteria import SuccessCheck
from neuroanimator.goals.policy_task import GoalSpec, PolicyTask, StartBox
from neuroanimator.goals.spec import Task

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

XML_PATH = Path(__file__).with_name("truck.xml")

LAYOUT = [
    StateGroup(name="position", kind="position", size=2, source="qpos", address=0, labels=("x", "y")),
    StateGroup(name="heading", kind="heading", size=1, source="qpos", address=2),
    StateGroup(name="velocity", kind="world_vector", size=2, source="qvel", address=0, labels=("x", "y")),
    StateGroup(name="yaw_rate", kind="scalar", size=1, source="qvel", address=2),
]


LABELS = tuple(StateLayout(tuple(LAYOUT)).labels())
# Controls in MJCF order, [steer, gas] (units and gains from the MJCF: 2 N and 10 N per unit).
CONTROL_INFO = {
    "steer": ControlInfo(
        label="steering",
        sign="a sideways force 2 m ahead of the centre: positive pushes the front to the truck's left "
        "(its +y), so it turns left, counter-clockwise seen from above (heading increases)",
    ),
    "gas": ControlInfo(
        label="gas",
        sign="a force along the truck's own +x axis at its centre: positive drives forward, negative brakes "
        "and then reverses",
    ),
}


def truck() -> PhysicalModel:
    from neuroanimator.sim.model import PhysicalModel  # MuJoCo loads when a model is built

    spec = ModelSpec(
        name="truck",
        description="truck: planar block with gas and steering, strong sideways friction (thesis E.3)",
        layout=LAYOUT,
        control_info=CONTROL_INFO,
        control_spacing_s=1.0,
        initial=InitialStates(
            low=[-30, -30, -3.1416, -3, -3, -0.1],
            high=[30, 30, 3.1416, 3, 3, 0.1],
        ),
        episode_s=30.0,
        thesis_hidden=40,
    )
    return PhysicalModel(XML_PATH.read_text(), spec)


PARKING = Task(
    name="truck-parking",
    model="truck",
    summary=(
        "Truck: from rest at the origin facing +x, park 20 m ahead and 10 m to the left, facing +y, "
        "and stop there within 20 s."
    ),
    labels=LABELS,
    initial_state=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    target_state=(20.0, 10.0, math.pi / 2, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 10.0, 10.0, 10.0, 10.0),
    success=(
        SuccessCheck(check="distance", variables=["position.x", "position.y"], max=1.0),
        SuccessCheck(check="angle", variables=["heading"], max=math.radians(10.0)),
        SuccessCheck(check="norm", variables=["velocity.x", "velocity.y"], max=0.3),
    ),
    initial_controls=(0.0, 0.0),
    mu_u=1e-4,
    mu_s=1.0,
    optimizer={"learning_rate": 1.5, "momentum": 0.5, "max_iterations": 100, "tolerance": 1e-6},
)
TASKS = (PARKING,)


# A feedback policy's parking: from near the origin, any heading, rolling slowly, park anywhere MuJoCo's
# truck reaches within 20 m, facing any heading, and stop there; checked as the parking task checks it,
# at the end of 25 s. Control every 0.25 s (the n = 25 emulator).
POLICY_PARKING = PolicyTask(
    name="truck-parking",
    model="truck",
    summary=(
        "Truck: from near the origin, any heading, rolling slowly, park at a spot within 20 m facing a "
        "given heading and stop there within 25 s."
    ),
    labels=LABELS,
    substeps=25,
    episode_s=25.0,
    starts=StartBox(low=(-2.0, -2.0, -math.pi, -0.3, -0.3, -0.05), high=(2.0, 2.0, math.pi, 0.3, 0.3, 0.05)),
    goal=GoalSpec(
        variables=("position.x", "position.y", "heading"),
        low=(-20.0, -20.0, -math.pi),
        high=(20.0, 20.0, math.pi),
    ),
    target_state=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 10.0, 3.0, 3.0, 1.0),
    success=PARKING.success,
    settle_s=12.0,
)
POLICY_TASKS = (POLICY_PARKING,)
