"""Typical starts that do not begin inside the floor or inside each other (``catalog.separation``): a
start in the floor is lifted by its root and keeps its joint angles and velocities; two bodies drawn
into each other with no root to lift are drawn nearer the rest pose; starts that touch nothing are
exactly as drawn."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.sim import mjcf, separation
from neuroanimator.sim.model import PhysicalModel

HOPPER = """
<mujoco model="stilt">
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="torso" pos="0 0 0.5">
      <joint name="rootz" type="slide" axis="0 0 1"/>
      <joint name="rootx" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1" mass="2"/>
      <body name="leg" pos="0 0 -0.1">
        <joint name="hip" type="hinge" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="hip" ctrlrange="-1 1"/></actuator>
</mujoco>
"""

# two rods hanging side by side from the world: swung towards each other by the typical ±0.3 rad they
# cross, and neither has a root that could rise
RODS = """
<mujoco model="rods">
  <worldbody>
    <body name="a" pos="-0.08 0 1">
      <joint name="a" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03" mass="1"/>
    </body>
    <body name="b" pos="0.08 0 1">
      <joint name="b" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor joint="a" ctrlrange="-1 1"/><motor joint="b" ctrlrange="-1 1"/></actuator>
</mujoco>
"""


def load(tmp_path: Path, xml: str) -> PhysicalModel:
    path = tmp_path / "model.xml"
    path.write_text(xml)
    return mjcf.load_mjcf(path, stabilise=False)


def drawn_as_before(model: PhysicalModel, seed: int, batch: int) -> np.ndarray:
    """The starts the generator gives without the separation (as typical starts were drawn before)."""
    sep = model._separator
    model.__dict__["_separator"] = None
    try:
        return model.initial_states(np.random.default_rng(seed), batch)
    finally:
        model.__dict__["_separator"] = sep


def deepest(model: PhysicalModel, states: np.ndarray) -> np.ndarray:
    sep = model._separator
    assert sep is not None
    qpos = model.to_physics(states)[:, model._qpos_at : model._qpos_at + model.mj_model.nq]
    return np.array([sep.depths(q).deepest for q in qpos])


def test_starts_in_the_floor_are_lifted_keeping_their_joints_and_velocities(tmp_path: Path) -> None:
    model = load(tmp_path, HOPPER)
    before = drawn_as_before(model, 3, 400)
    after = model.initial_states(np.random.default_rng(3), 400)
    inside = deepest(model, before) > separation.TOLERANCE
    assert 0.2 < inside.mean() < 0.9  # rootz drawn down by up to 0.3 m puts the foot in the floor
    assert deepest(model, after).max() <= separation.TOLERANCE
    z = model.layout.slice_of("rootz.pos")
    assert np.array_equal(after[~inside], before[~inside])  # what touched nothing is as drawn
    assert np.all(after[inside, z] > before[inside, z])  # lifted...
    others = np.ones(model.state_size, dtype=bool)
    others[z] = False
    assert np.array_equal(after[inside][:, others], before[inside][:, others])  # ...and nothing else
    # lifted to just above the floor, not thrown up: lowered by a millimetre past the clearance, it touches
    lowered = after[inside] - (separation.CLEARANCE + 0.001) * np.eye(model.state_size)[z.start]
    assert np.all(deepest(model, lowered) > 0.0)


def test_bodies_drawn_into_each_other_start_nearer_rest(tmp_path: Path) -> None:
    model = load(tmp_path, RODS)
    before = drawn_as_before(model, 4, 300)
    after = model.initial_states(np.random.default_rng(4), 300)
    inside = deepest(model, before) > separation.TOLERANCE
    assert inside.any() and not inside.all()
    assert deepest(model, after).max() <= separation.TOLERANCE
    angles = np.r_[model.layout.slice_of("a.angle"), model.layout.slice_of("b.angle")]
    rest = model.rest_state()[angles]
    shrink = np.abs(after[inside][:, angles] - rest) / np.abs(before[inside][:, angles] - rest)
    assert np.all(shrink < 1.0) and np.all(shrink >= 0.0)
    rates = np.r_[model.layout.slice_of("a.rate"), model.layout.slice_of("b.rate")]
    assert np.array_equal(after[:, rates], before[:, rates])
    assert np.array_equal(after[~inside], before[~inside])


@pytest.mark.parametrize("name", ["ball", "quadrotor"])
def test_catalog_starts_that_touch_nothing_are_as_drawn(name: str) -> None:
    model = catalog.get(name)
    assert np.array_equal(model.initial_states(np.random.default_rng(9), 128), drawn_as_before(model, 9, 128))
