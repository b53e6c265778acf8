"""The three-link pendulum (thesis E.1) in three variants: passive, active (3 motor torques) and
with 3 applied forces (horizontal pushes on each link's centre of mass)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from neuroanimator.physics.model import PhysicalModel
from neuroanimator.physics.spec import ForceInput, InitialStates, ModelSpec

XML_PATH = Path(__file__).with_name("pendulum.xml")

LAYOUT = [
    {
        "name": "angles",
        "kind": "angle",
        "size": 3,
        "source": "qpos",
        "address": 0,
        "labels": ["j0", "j1", "j2"],
    },
    {
        "name": "rates",
        "kind": "scalar",
        "size": 3,
        "source": "qvel",
        "address": 0,
        "labels": ["j0", "j1", "j2"],
    },
]
# hanging at rest is angle 0; start anywhere within ±1.5 rad, slowly moving
INITIAL = InitialStates(low=[-1.5] * 3 + [-0.5] * 3, high=[1.5] * 3 + [0.5] * 3)


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
    return PhysicalModel(_xml(False, spec.name), spec)


def active() -> PhysicalModel:
    spec = ModelSpec(
        name="pendulum-active",
        description="three-link pendulum with a motor torque at each joint (thesis E.1)",
        layout=LAYOUT,
        initial=INITIAL,
        episode_s=30.0,
        thesis_hidden=20,
        control_spacing_s=1.0,
    )
    return PhysicalModel(_xml(True, spec.name), spec)


def force() -> PhysicalModel:
    spec = ModelSpec(
        name="pendulum-force",
        description="active three-link pendulum plus horizontal forces applied to each link (thesis 4.2)",
        layout=LAYOUT,
        initial=INITIAL,
        episode_s=30.0,
        thesis_hidden=20,
        forces=[
            ForceInput(name=f"push{i}", body=f"link{i}", component=0, low=-2.0, high=2.0) for i in range(3)
        ],
        force_spacing_s=1.0,
    )
    return PhysicalModel(_xml(True, spec.name), spec)
