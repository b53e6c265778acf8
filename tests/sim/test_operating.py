"""Operating points read from the model: keyframes first, else the controls that hold it still, else
none; checked against the physics (the held model does not move) on models of the shapes users bring."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from neuroanimator.sim import operating
from neuroanimator.sim.errors import ModelError

# A quadrotor laid out as MuJoCo Menagerie's Skydio X2 (four thrusters on sites, 0-13 N each, yaw
# torque by a gear on the sixth axis), with its geometry reduced to boxes and ellipsoids.
QUAD = """<mujoco model="quad">
  <option timestep="0.01" density="1.225" viscosity="1.8e-5"/>
  <default><default class="q"><geom mass="0" type="box"/><motor ctrlrange="0 13"/></default></default>
  <worldbody>
    <body name="frame" pos="0 0 1" childclass="q">
      <freejoint/>
      <geom size=".06 .027 .02" pos=".04 0 .02" mass=".325"/>
      <geom name="r1" type="ellipsoid" size=".13 .13 .01" pos="-.14 -.18 .05" mass=".25"/>
      <geom name="r2" type="ellipsoid" size=".13 .13 .01" pos="-.14 .18 .05" mass=".25"/>
      <geom name="r3" type="ellipsoid" size=".13 .13 .01" pos=".14 .18 .08" mass=".25"/>
      <geom name="r4" type="ellipsoid" size=".13 .13 .01" pos=".14 -.18 .08" mass=".25"/>
      <site name="t1" pos="-.14 -.18 .05"/><site name="t2" pos="-.14 .18 .05"/>
      <site name="t3" pos=".14 .18 .08"/><site name="t4" pos=".14 -.18 .08"/>
    </body>
  </worldbody>
  <actuator>
    <motor class="q" name="t1" site="t1" gear="0 0 1 0 0 -.0201"/>
    <motor class="q" name="t2" site="t2" gear="0 0 1 0 0 .0201"/>
    <motor class="q" name="t3" site="t3" gear="0 0 1 0 0 .0201"/>
    <motor class="q" name="t4" site="t4" gear="0 0 1 0 0 -.0201"/>
  </actuator>
  KEYS
</mujoco>"""

ARM = """<mujoco model="arm">
  <worldbody>
    <body name="upper" pos="0 0 1">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.04" mass="1"/>
      <body name="fore" pos="0.4 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" ctrlrange="-1 1" gear="20"/>
    <general joint="elbow" ctrlrange="-1 1" gainprm="5" dyntype="filter" dynprm="0.05"/>
  </actuator>
</mujoco>"""

CARTPOLE = """<mujoco model="cartpole">
  <worldbody>
    <body name="cart">
      <joint name="slider" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.2 0.1 0.05" mass="1"/>
      <body name="pole"><joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.02" mass="0.1"/></body>
    </body>
  </worldbody>
  <actuator><motor joint="slider" ctrlrange="-1 1" gear="10"/></actuator>
</mujoco>"""

# a body thrown in the air with one hinge motor: its free root cannot be held by its actuator
FLUNG = """<mujoco model="flung">
  <worldbody>
    <body name="torso" pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="1"/>
      <body name="leg" pos="0 0 -0.1"><joint name="hip" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="0.2"/></body>
    </body>
  </worldbody>
  <actuator><motor joint="hip" ctrlrange="-1 1" gear="5"/></actuator>
</mujoco>"""

HOVER = '<keyframe><key name="hover" qpos="0 0 .3 1 0 0 0" ctrl="3.2495625 3.2495625 3.2495625 3.2495625"/></keyframe>'


def _model(xml: str) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(xml)


def _moves(m: mujoco.MjModel, point: operating.Keyframe, seconds: float = 1.0) -> float:
    """How far (the largest |Δqpos|) the model drifts in ``seconds`` from the point under its controls."""
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:] = point.qpos, point.qvel, point.ctrl
    has_act = m.actuator_actadr >= 0
    d.act[m.actuator_actadr[has_act]] = point.ctrl[has_act]
    for _ in range(round(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
    return float(np.max(np.abs(d.qpos - point.qpos)))


def test_a_drone_with_a_hover_keyframe_operates_there() -> None:
    found = operating.find(_model(QUAD.replace("KEYS", HOVER)))
    assert found.source == "keyframe" and [k.name for k in found.points] == ["hover"]
    assert found.points[0].qpos[2] == pytest.approx(0.3)
    np.testing.assert_allclose(found.points[0].ctrl, 3.2495625)
    assert "'hover'" in found.reason


def test_a_drone_without_keyframes_is_held_by_the_thrust_that_carries_its_weight() -> None:
    m = _model(QUAD.replace("KEYS", ""))
    found = operating.find(m)
    assert found.source == "hold", found.reason
    u = found.points[0].ctrl
    weight = float(m.body_subtreemass[1]) * -m.opt.gravity[2]
    assert float(u.sum()) == pytest.approx(weight, rel=1e-6)  # the thrusts carry its weight ...
    assert u[2] > u[0]  # ... more of it at the front, where its centre of mass lies
    assert _moves(m, found.points[0]) < 1e-6  # held still, by the physics
    assert "hold it still" in found.reason


def test_an_arm_is_held_against_gravity_also_through_an_actuator_with_dynamics() -> None:
    m = _model(ARM)
    found = operating.find(m)
    assert found.source == "hold", found.reason
    assert np.all(np.abs(found.points[0].ctrl) < 1) and np.all(found.points[0].ctrl != 0)
    assert _moves(m, found.points[0]) < 1e-6
    mujoco.mj_resetData(m, d := mujoco.MjData(m))
    for _ in range(100):  # without them the arm falls
        mujoco.mj_step(m, d)
    assert np.max(np.abs(d.qpos)) > 0.1


def test_a_hold_out_of_range_is_no_hold() -> None:
    weak = ARM.replace('gear="20"', 'gear="1"')  # 1 N·m cannot carry the arm
    found = operating.find(_model(weak))
    assert found.source == "none" and "unbalanced" in found.reason


@pytest.mark.parametrize(
    ("xml", "words"), [(CARTPOLE, "nothing to hold against"), (FLUNG, "no controls hold it")]
)
def test_models_with_nothing_to_hold_or_no_way_to_hold_it_keep_todays_controls(xml: str, words: str) -> None:
    found = operating.find(_model(xml))
    assert found.source == "none" and found.points == () and words in found.reason


def test_a_named_keyframe_is_chosen_and_an_unknown_one_is_refused_naming_those_there() -> None:
    two = HOVER.replace("</keyframe>", '<key name="landed" qpos="0 0 .05 1 0 0 0"/></keyframe>')
    m = _model(QUAD.replace("KEYS", two))
    assert [k.name for k in operating.find(m).points] == ["hover", "landed"]
    assert [k.name for k in operating.find(m, keyframe="landed").points] == ["landed"]
    with pytest.raises(ModelError, match=r"no keyframe 'hovr'; its keyframes are \['hover', 'landed'\]"):
        operating.find(m, keyframe="hovr")
