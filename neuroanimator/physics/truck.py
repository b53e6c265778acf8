"""The truck (thesis E.3): a planar block steered by a side force ahead of its centre."""

from __future__ import annotations

from pathlib import Path

from neuroanimator.physics.model import PhysicalModel
from neuroanimator.physics.spec import InitialStates, ModelSpec

XML_PATH = Path(__file__).with_name("truck.xml")

LAYOUT = [
    {"name": "position", "kind": "position", "size": 2, "source": "qpos", "address": 0, "labels": ["x", "y"]},
    {"name": "heading", "kind": "heading", "size": 1, "source": "qpos", "address": 2},
    {
        "name": "velocity",
        "kind": "world_vector",
        "size": 2,
        "source": "qvel",
        "address": 0,
        "labels": ["x", "y"],
    },
    {"name": "yaw_rate", "kind": "scalar", "size": 1, "source": "qvel", "address": 2},
]


def truck() -> PhysicalModel:
    spec = ModelSpec(
        name="truck",
        description="truck: planar block with gas and steering, strong sideways friction (thesis E.3)",
        layout=LAYOUT,
        control_spacing_s=1.0,
        initial=InitialStates(
            low=[-30, -30, -3.1416, -3, -3, -0.1],
            high=[30, 30, 3.1416, 3, 3, 0.1],
        ),
        episode_s=30.0,
        thesis_hidden=40,
    )
    return PhysicalModel(XML_PATH.read_text(), spec)
