"""The three-link pendulum (thesis E.1) in three variants: passive, active (3 motor torques) and
with 3 applied forces (horizontal pushes on each link's centre of mass); and the active one's
swing task (thesis 6.2)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

from neuroanimator.core.model_spec import ControlInfo, ForceInput, InitialStates, ModelSpec
from neuroanimator.core.state import StateGroup, StateLayout
from neuroanimator.goals.criteria import SuccessCheck
from neuroanimator.goals.policy_task import GoalSpec, PolicyTask, StartBox
from neuroanimator.goals.spec import Task

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

XML_PATH = Path(__file__).with_name("pendulum.xml")

LAYOUT = [
    StateGroup(name="angles", kind="angle", size=3, source="qpos", address=0, labels=("j0", "j1", "j2")),
    StateGroup(name="rates", kind="scalar", size=3, source="qvel", address=0, labels=("j0", "j1", "j2")),
]
LABELS = tuple(StateLayout(tuple(LAYOUT)).labels())
# hanging at rest is angle 0; start anywhere within ±1.5 rad, slowly moving
INITIAL = InitialStates(low=[-1.5] * 3 + [-0.5] * 3, high=[1.5] * 3 + [0.5] * 3)


def _model(xml: str, spec: ModelSpec) -> PhysicalModel:
    from neuroanimator.sim.model import PhysicalModel  # MuJoCo loads when a model is built

    return PhysicalModel(xml, spec)


def _xml(with_motors: bool, name: str) -> str:
    root = ET.fromstring(XML_PATH.read_text())
    root.set("model", name)
    if not with_motors:
        for act in root.findall("actuator"):
            root.remove(act)
    return ET.tostring(root, encoding="unicode")


def passive() -> PhysicalModel:
    spec = ModelSpec(
        name="pendulum-passive",
        description="three-link pendulum swinging under gravity and joint friction (thesis E.1)",
        layout=LAYOUT,
        initial=INITIAL,
        episode_s=30.0,
        thesis_hidden=20,
    )
    return _model(_xml(False, spec.name), spec)


# The motors' meaning (their unit and gain come from the MJCF: 1 N·m per unit of control).
CONTROL_INFO = {
    f"torque{i}": ControlInfo(
        label=f"motor at joint {i}" + (" (the pivot)" if i == 0 else f" (between links {i - 1} and {i})"),
        sign=f"positive turns link {i} (relative to what it hangs from) about the world's +y axis, "
        "right-hand rule: a hanging link swings towards −x",
    )
    for i in range(3)
}


def _active_spec() -> ModelSpec:
    return ModelSpec(
        name="pendulum-active",
        description="three-link pendulum with a motor torque at each joint (thesis E.1)",
        control_info=CONTROL_INFO,
        layout=LAYOUT,
        initial=INITIAL,
        episode_s=30.0,
        thesis_hidden=20,
        control_spacing_s=1.0,
    )


def active() -> PhysicalModel:
    spec = _active_spec()
    return _model(_xml(True, spec.name), spec)


def force() -> PhysicalModel:
    """The active pendulum with a horizontal push on each link."""
    spec = _active_spec().model_copy(
        update={
            "name": "pendulum-force",
            "description": "active three-link pendulum plus horizontal forces applied to each link (thesis 4.2)",
            "forces": [
                ForceInput(name=f"push{i}", body=f"link{i}", component=0, low=-2.0, high=2.0)
                for i in range(3)
            ],
            "force_spacing_s": 1.0,
        }
    )
    return _model(_xml(True, spec.name), spec)


# From hanging at rest, end 20 s later at a pose well to the side, at zero velocity. Holding the
# pose would need a torque of about 9.8·(0.25 + 0.75 + 1.25)·sin(θ) ≈ 18 N·m at the base; the
# motors give at most 2, so the pendulum must pump energy by swinging back and forth and arrive at
# the top of a swing (the thesis' Fig. 6.8 problem).
SWING = Task(
    name="pendulum-swing",
    model="pendulum-active",
    summary=(
        "Three-link pendulum (pendulum-active, torque limit 2 N·m per joint): from hanging at rest, "
        "end at the target pose with zero velocity after 20 s. The torque is far too low to lift the "
        "links there directly, so the controller must swing back and forth to gain momentum."
    ),
    labels=LABELS,
    initial_state=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    target_state=(1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 1.0, 1.0, 1.0, 1.0),
    success=(
        SuccessCheck(check="angle", variables=["angles.j0", "angles.j1", "angles.j2"], max=0.1),
        SuccessCheck(check="abs", variables=["rates.j0", "rates.j1", "rates.j2"], max=0.1),
    ),
    initial_controls=(0.0, 0.0, 0.0),
    mu_u=1e-4,
    mu_s=1.0,
    optimizer={"learning_rate": 2.0, "momentum": 0.5, "max_iterations": 100, "tolerance": 1e-6},
)
TASKS = (SWING,)


# A feedback policy's pose: from near hanging, go to a pose the pendulum reaches at rest in its own
# motion and that its motors can hold still (every rate below 0.3 rad/s there, the torques to hold it
# within 2 N·m), and be there, still, 20 s later; checked as the swing task checks it. Control every
# 0.25 s. (Poses it passes through at rest but cannot hold, the top of a swing, asked it to arrive at
# the exact moment: a policy met the 0.1 rad bound in about 70 % of runs, at 0.25 s or at 0.1 s.)
POLICY_SWING = PolicyTask(
    name="pendulum-swing",
    model="pendulum-active",
    summary=(
        "Three-link pendulum (pendulum-active): from near hanging, go to a pose it reaches at rest and "
        "can hold, and be there, still, after 20 s."
    ),
    labels=LABELS,
    substeps=25,
    episode_s=20.0,
    starts=StartBox(low=(-0.2, -0.2, -0.2, -0.2, -0.2, -0.2), high=(0.2, 0.2, 0.2, 0.2, 0.2, 0.2)),
    goal=GoalSpec(
        variables=("angles.j0", "angles.j1", "angles.j2"),
        low=(-1.5, -1.5, -1.5),
        high=(1.5, 1.5, 1.5),
        at_rest=True,
        holdable=True,
    ),
    target_state=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 1.0, 1.0, 1.0, 1.0),
    success=SWING.success,
    settle_s=8.0,
    train_seconds=300.0,
)
POLICY_TASKS = (POLICY_SWING,)
