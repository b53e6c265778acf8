"""The lunar lander (thesis E.2): a free rigid body with a main jet and three attitude controls,
and its landing task (thesis 6.2)."""

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

XML_PATH = Path(__file__).with_name("lander.xml")
HOVER_THRUST = 100 * 1.62 / 10.0  # main-jet control that balances lunar gravity

LAYOUT = [
    StateGroup(name="position", kind="position", size=3, source="qpos", address=0, labels=("x", "y", "z")),
    StateGroup(
        name="orientation", kind="quaternion", size=4, source="qpos", address=3, labels=("w", "x", "y", "z")
    ),
    StateGroup(
        name="velocity", kind="world_vector", size=3, source="qvel", address=0, labels=("x", "y", "z")
    ),
    StateGroup(
        name="angular_velocity", kind="local_vector", size=3, source="qvel", address=3, labels=("x", "y", "z")
    ),
]


LABELS = tuple(StateLayout(tuple(LAYOUT)).labels())
# What the jets do (their units and gains come from the MJCF: 10 N and 0.25 N·m per unit of control).
CONTROL_INFO = {
    "main_jet": ControlInfo(
        label="main jet",
        sign="thrust along the lander's own +z axis (up when it is upright); 0 is off, it never pulls",
    ),
    **{
        axis: ControlInfo(
            label=f"{axis} jet",
            sign=f"positive turns the lander about its own +{letter} axis (right-hand rule)",
        )
        for axis, letter in (("roll", "x"), ("pitch", "y"), ("yaw", "z"))
    },
}


def lander() -> PhysicalModel:
    from neuroanimator.sim.model import PhysicalModel  # MuJoCo loads when a model is built

    spec = ModelSpec(
        name="lander",
        description="lunar lander: free rigid body, main jet and attitude jets, lunar gravity (thesis E.2)",
        layout=LAYOUT,
        control_info=CONTROL_INFO,
        # the useful range brackets hover thrust; attitude jets use their full range
        control_low=[0.0, -1.0, -1.0, -1.0],
        control_high=[2.0 * HOVER_THRUST, 1.0, 1.0, 1.0],
        control_spacing_s=1.0,
        initial=InitialStates(
            # around the body's start at (0, 0, 20): anywhere in a 40 m box, drifting and descending
            low=[-20, -20, -15, 0, 0, 0, 0, -2, -2, -3, -0.2, -0.2, -0.2],
            high=[20, 20, 20, 0, 0, 0, 0, 2, 2, 1, 0.2, 0.2, 0.2],
            random_yaw=True,
            max_tilt=0.5,
        ),
        episode_s=20.0,
        thesis_hidden=50,
    )
    return PhysicalModel(XML_PATH.read_text(), spec)


# Descend from 25 m up and 12 m off to the side, drifting, to a soft landing on the pad at the
# origin: upright, on the spot, barely moving down. The attitude jets are weak (0.05 rad/s² at
# most), so the lander must plan its tilt early to move sideways with the main jet.
LANDING = Task(
    name="lander-landing",
    model="lander",
    summary=(
        "Lunar lander: from 25 m above and 12 m beside the pad, drifting, land softly on the pad "
        "(the origin) in 20 s: upright, on the spot, with a small downward speed. Sideways motion "
        "needs tilting the main jet with weak attitude jets."
    ),
    labels=LABELS,
    initial_state=(-10.0, 6.0, 25.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.0, -1.0, 0.0, 0.0, 0.0),
    target_state=(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.5, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 1.0, 10.0, 10.0, 10.0, 10.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0),
    success=(
        SuccessCheck(check="distance", variables=["position.x", "position.y", "position.z"], max=1.0),
        SuccessCheck(
            check="orientation",
            variables=["orientation.w", "orientation.x", "orientation.y", "orientation.z"],
            max=math.radians(10.0),
        ),
        SuccessCheck(check="range", variables=["velocity.z"], min=-1.0, max=0.0),
        SuccessCheck(check="norm", variables=["velocity.x", "velocity.y"], max=0.5),
    ),
    initial_controls=(HOVER_THRUST, 0.0, 0.0, 0.0),  # hover, no attitude jets
    mu_u=1e-4,
    mu_s=1.0,
    optimizer={"learning_rate": 1.5, "momentum": 0.5, "max_iterations": 100, "tolerance": 1e-6},
)
TASKS = (LANDING,)


# A feedback policy's landing: from anywhere in a 30 m box up to 25 m high, drifting, tilted, land on
# a pad anywhere within 15 m of the origin (where MuJoCo's lander goes in its typical motion), checked
# as the landing task checks it, at the end of 20 s. Control every 0.25 s (the n = 25 emulator).
POLICY_LANDING = PolicyTask(
    name="lander-landing",
    model="lander",
    summary=(
        "Lunar lander: from anywhere up to 25 m high and 15 m to the side, drifting and tilted, land "
        "softly on a pad anywhere within 15 m of the origin in 20 s (upright, on the spot, a small "
        "downward speed)."
    ),
    labels=LABELS,
    substeps=25,
    episode_s=20.0,
    starts=StartBox(
        low=(-15, -15, 8, 1, 0, 0, 0, -1, -1, -2, -0.05, -0.05, -0.05),
        high=(15, 15, 25, 1, 0, 0, 0, 1, 1, 0.5, 0.05, 0.05, 0.05),
        random_yaw=True,
        max_tilt=0.2,
    ),
    goal=GoalSpec(variables=("position.x", "position.y"), low=(-15.0, -15.0), high=(15.0, 15.0)),
    target_state=(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.3, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 1.0, 10.0, 10.0, 10.0, 10.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0),
    success=LANDING.success,
    settle_s=10.0,
    timed=True,  # touch down (moving down, slowly) as the run ends, not hover above the pad
    train_seconds=900.0,
    # 32 wide lands as often as 64 (0.95 of 100 held-out runs each) at a third of the arithmetic:
    # it runs beside the emulator every served super-step
    hidden=(32, 32),
)
POLICY_TASKS = (POLICY_LANDING,)
