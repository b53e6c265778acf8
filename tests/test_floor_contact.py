"""The floor decides the emulator (``clearance.floor_contact``, ``train.with_contact_features``): a model
whose sampled states touch its floor gets the contact-aware emulator (the floor's clearance as input)
without being asked, one whose states never touch it, or only slide along it, gets the plain one, and
each training says why; what the user chose stands."""

from __future__ import annotations

import numpy as np
import pytest

from neuroanimator.core.model_spec import ModelSpec
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.clearance import TOUCH_SHARE, floor_contact
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training import train as training

# a ball on a vertical slide (and a hinge to roll), resting on the floor: its motor hops it
DROP_XML = """
<mujoco model="drop">
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1"/>
    <body name="ball" pos="0 0 0.1">
      <joint name="height" type="slide" axis="0 0 1"/>
      <joint name="roll" type="hinge" axis="0 1 0"/>
      <geom name="ball" type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor joint="height" ctrlrange="-20 20"/></actuator>
</mujoco>
"""

# a pendulum hung 2 m above a floor: its bob never comes near it
HUNG_XML = """
<mujoco model="hung">
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1"/>
    <body name="arm" pos="0 0 2">
      <joint name="swing" type="hinge" axis="0 1 0"/>
      <geom name="bob" type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
    </body>
  </worldbody>
  <actuator><motor joint="swing" ctrlrange="-1 1"/></actuator>
</mujoco>
"""

# a puck sliding along the floor in x: always on it, never landing or lifting off (dm_control's
# reacher and point mass)
PUCK_XML = """
<mujoco model="puck">
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1"/>
    <body name="puck" pos="0 0 0.05">
      <joint name="x" type="slide" axis="1 0 0"/>
      <geom name="puck" type="cylinder" size="0.1 0.05"/>
    </body>
  </worldbody>
  <actuator><motor joint="x" ctrlrange="-1 1"/></actuator>
</mujoco>
"""

# a short training: what is asserted is what it decides before it fits, and what it writes
QUICK = dict(
    substeps=5, hidden=(8,), examples=1500, test_examples=200, max_seconds=2.0, rollout_steps=0,
    time_budget=None, progress=False, threads=1,
)  # fmt: skip


def _model(xml: str, name: str) -> PhysicalModel:
    return PhysicalModel(xml, ModelSpec(name=name))


def _states(model: PhysicalModel, column: str, values: np.ndarray) -> np.ndarray:
    states = np.zeros((len(values), model.layout.size), dtype=np.float32)
    states[:, model.layout.slice_of(column)] = values[:, None]
    return states


def test_the_share_of_states_that_touch_is_counted() -> None:
    drop = _model(DROP_XML, "drop")
    # the ball rests on the floor at an offset of 0; at 0.04 it is 4 cm clear (near, not touching), and
    # from 0.05 on 5 cm clear or more
    heights = np.array([0.0, 0.005, 0.04, 0.2, 0.3, 0.5, 1.0, 2.0])
    contact = floor_contact(drop, _states(drop, "height.pos", heights), 0.0)
    assert contact.floor and contact.geoms == ("ball",)
    assert contact.touching == pytest.approx(2 / 8)  # the ball within 1 cm of the floor in two of eight
    assert TOUCH_SHARE <= 2 / 8 and contact.touches
    aloft = floor_contact(drop, _states(drop, "height.pos", heights[3:]), 0.0)
    assert aloft.geoms == () and aloft.touching == 0.0 and not aloft.touches
    assert "no geom comes within 5 cm of the floor in 5 sampled states" in aloft.describe()


def test_sliding_along_the_floor_is_not_touching_it() -> None:
    puck = _model(PUCK_XML, "puck")
    contact = floor_contact(puck, _states(puck, "x.pos", np.linspace(-1.0, 1.0, 20)), 0.0)
    assert contact.geoms == ("puck",)  # it lies on the floor ...
    assert contact.touching == 0.0 and not contact.touches  # ... but never lands on it or lifts off


def test_a_model_without_a_floor_says_nothing() -> None:
    no_floor = _model(HUNG_XML.replace('<geom name="floor" type="plane" size="0 0 1"/>', ""), "nofloor")
    contact = floor_contact(no_floor, np.zeros((4, no_floor.layout.size), dtype=np.float32), 0.0)
    assert not contact.floor and not contact.touches and contact.describe() == "the model has no floor"
    result = training.train(no_floor, TrainConfig(**QUICK))  # type: ignore[arg-type]
    assert result.config.clearance is False and "clearance_reason" not in result.metrics


def test_a_model_whose_states_touch_the_floor_is_trained_contact_aware() -> None:
    result = training.train(_model(DROP_XML, "drop"), TrainConfig(**QUICK))  # type: ignore[arg-type]
    assert result.emulator.clearance is not None and tuple(result.emulator.clearance.geoms) == ("ball",)
    assert result.config.clearance is True  # the decision is what the manifest keeps
    assert result.metrics["clearance_reason"].startswith("contact-aware (the floor's clearance as input)")
    assert np.isfinite(result.metrics["one_step_rel_error"])


def test_a_model_that_never_touches_its_floor_gets_the_plain_emulator_and_says_so() -> None:
    result = training.train(_model(HUNG_XML, "hung"), TrainConfig(**QUICK))  # type: ignore[arg-type]
    assert result.emulator.clearance is None and result.config.clearance is False
    assert result.metrics["clearance_reason"].startswith("no clearance input: no geom comes within 5 cm")


def test_the_users_choice_stands() -> None:
    drop = _model(DROP_XML, "drop")
    off = training.train(drop, TrainConfig(**{**QUICK, "clearance": False}))  # type: ignore[arg-type]
    assert off.emulator.clearance is None and "clearance_reason" not in off.metrics
    on = training.train(_model(HUNG_XML, "hung"), TrainConfig(**{**QUICK, "clearance": True}))  # type: ignore[arg-type]
    assert on.config.clearance is True and "clearance_reason" not in on.metrics
