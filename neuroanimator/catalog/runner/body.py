"""The runner (thesis 4.4, Fig. 4.8, 6.1): a 70 kg human figure of 35 degrees of freedom on a floor.

The MJCF (``runner.xml``) says where its masses and sizes come from. Its 29 controls are the targets
of position servos at the hinges, in radians (the actuators' order: waist, neck, left arm, right arm,
left leg, right leg; ``JOINTS``). Servos rather than torque motors because the controller that drives
the figure (``runner_control``) sets a pose a few times per control period and the servo's spring and
damper run inside every physical step: stable at any control period, and the emulator's controls stay
joint targets, held over a super-step like any model's controls. The torque a servo applies is capped
by its ``forcerange``, so a target far away is a bounded torque, not an impulse.

The running data come from the closed loop (``runner_control.run``), whose targets reach across the
actuators' whole ``ctrlrange`` (a swing knee folds to 1.8 rad): so the range of the controls, which the
emulator service clips inputs to, is the ``ctrlrange`` and not a band around the standing pose. The
spec's driver (``DRIVER``) lets the emulator service run that controller for a session.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from neuroanimator.core.model_spec import (
    Branch,
    DriverParam,
    DriverSpec,
    ForceInput,
    InitialStates,
    ModelSpec,
)

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

XML_PATH = Path(__file__).with_name("runner.xml")

SIDES = ("left", "right")
LEG = ("hip_x", "hip_z", "hip_y", "knee", "ankle_y", "ankle_x", "toe")
ARM = ("shoulder_x", "shoulder_y", "shoulder_z", "elbow", "wrist")
JOINTS: tuple[str, ...] = (
    "waist_x",
    "waist_y",
    "waist_z",
    "neck_y",
    "neck_z",
    *(f"{side}_{j}" for side in SIDES for j in ARM),
    *(f"{side}_{j}" for side in SIDES for j in LEG),
)
"""The actuated hinges, in the order of the controls (each actuator is named after its joint)."""

# A relaxed standing pose (radians): slightly bent knees, arms a little away from the body.
STAND: dict[str, float] = {
    **{f"{side}_shoulder_x": 0.15 for side in SIDES},
    **{f"{side}_elbow": 0.3 for side in SIDES},
}


PUSH_N = 300.0  # the range of the push force inputs (newtons on the torso, each horizontal axis)
SUBSTEPS = 6  # the super-step: the running controller's period (runner_control's gait is tuned for it)


def branches() -> list[Branch]:
    """The thesis' hierarchy (Fig. 4.8): a network per arm and per leg, each writing its joints' angles
    and rates and reading its own servo targets; the trunk network writes the root (the pelvis) and the
    waist and neck."""
    out = []
    for side in SIDES:
        for limb, joints in (("arm", ARM), ("leg", LEG)):
            names = [f"{side}_{j}" for j in joints]
            out.append(
                Branch(
                    name=f"{side}_{limb}",
                    groups=[f"{n}.angle" for n in names] + [f"{n}.rate" for n in names],
                    controls=names,
                )
            )
    return out


# The running controller sets the joint targets; a client sets its target speed. The range is the
# speeds the emulator's training runs were at (runner_data.TRAIN_SPEEDS); 2.0 m/s lies between them.
DRIVER = DriverSpec(
    name="run",
    description="the running controller (runner_control): joint targets from the emulated state each "
    "super-step; the client sets the target speed and may push the torso",
    factory="neuroanimator.catalog.runner.gait:driver",
    params=[DriverParam(name="speed", label="target speed", unit="m/s", low=1.6, high=2.4, default=2.0)],
)


def stand_targets() -> list[float]:
    """(29,) the servo targets of the standing pose, in the order of ``JOINTS``."""
    return [STAND.get(name, 0.0) for name in JOINTS]


def runner() -> PhysicalModel:
    import numpy as np

    from neuroanimator.sim.model import PhysicalModel  # MuJoCo loads when a model is built

    xml = XML_PATH.read_text()
    probe = PhysicalModel(xml, ModelSpec(name="runner"))
    size = probe.state_size
    height = probe.layout.slice_of("root.pos").start + 2
    jitter_low, jitter_high = np.zeros(size), np.zeros(size)
    jitter_low[height], jitter_high[height] = -0.02, 0.0  # settle from at most 2 cm lower
    vel = probe.layout.slice_of("root.vel")
    jitter_low[vel], jitter_high[vel] = -0.2, 0.2
    spec = ModelSpec(
        name="runner",
        substeps=SUBSTEPS,
        branches=branches(),
        data_source="neuroanimator.catalog.runner.data",
        driver=DRIVER,
        forces=[
            ForceInput(name=f"push_{axis}", body="torso", component=i, low=-PUSH_N, high=PUSH_N)
            for i, axis in enumerate("xy")
        ],
        train_at_start=False,  # 71 state variables and 29 controls: its emulator is trained on purpose
        description=(
            "running human figure: 70 kg, 35 degrees of freedom (free root, 29 servoed hinges), "
            "ground contact with friction; controls are joint targets (thesis 4.4, Hodgins' runner)"
        ),
        control_spacing_s=0.5,
        initial=InitialStates(
            low=jitter_low.tolist(), high=jitter_high.tolist(), random_yaw=True, max_tilt=0.05
        ),
        episode_s=10.0,
        thesis_hidden=30,
    )
    return PhysicalModel(xml, spec)


TASKS: tuple[()] = ()  # the runner's motion comes from its running controller (runner_control), not a task
