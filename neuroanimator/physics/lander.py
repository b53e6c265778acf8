"""The lunar lander (thesis E.2): a free rigid body with a main jet and three attitude controls."""

from __future__ import annotations

from pathlib import Path

from neuroanimator.physics.model import PhysicalModel
from neuroanimator.physics.spec import InitialStates, ModelSpec

XML_PATH = Path(__file__).with_name("lander.xml")
HOVER_THRUST = 100 * 1.62 / 10.0  # main-jet control that balances lunar gravity

LAYOUT = [
    {
        "name": "position",
        "kind": "position",
        "size": 3,
        "source": "qpos",
        "address": 0,
        "labels": ["x", "y", "z"],
    },
    {
        "name": "orientation",
        "kind": "quaternion",
        "size": 4,
        "source": "qpos",
        "address": 3,
        "labels": ["w", "x", "y", "z"],
    },
    {
        "name": "velocity",
        "kind": "world_vector",
        "size": 3,
        "source": "qvel",
        "address": 0,
        "labels": ["x", "y", "z"],
    },
    {
        "name": "angular_velocity",
        "kind": "local_vector",
        "size": 3,
        "source": "qvel",
        "address": 3,
        "labels": ["x", "y", "z"],
    },
]


def lander() -> PhysicalModel:
    spec = ModelSpec(
        name="lander",
        description="lunar lander: free rigid body, main jet and attitude jets, lunar gravity (thesis E.2)",
        layout=LAYOUT,
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
