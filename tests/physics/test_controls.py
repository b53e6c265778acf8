"""What each control means (label, unit, gain, sign): the catalog's words, the MJCF's numbers, written
into every manifest; manifests written before these fields still read."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import pytest

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.core.manifest import parse_manifest
from neuroanimator.core.model_spec import ControlInfo, ModelSpec
from neuroanimator.sim.controls import describe_actuator
from neuroanimator.sim.model import ModelError, PhysicalModel
from tests.helpers import ARM_XML, Trained

ROOT = Path(__file__).resolve().parents[2]
COMMITTED = sorted(p.parent for p in (ROOT / "artifacts").glob("*/*/manifest.json"))


@pytest.mark.parametrize("name", sorted(catalog.CATALOG))
def test_every_catalog_control_says_what_it_means(name: str) -> None:
    model = catalog.get(name)
    assert len(model.control_info) == model.num_controls
    for control, info in zip(model.control_names, model.control_info, strict=True):
        assert info.label and info.unit and info.sign and info.gain, (control, info)
        assert info.unit in ("N", "N·m", "rad", "m", "rad/s", "m/s"), (control, info)


@pytest.mark.parametrize("path", COMMITTED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_committed_manifests_carry_the_catalog_meaning(path: Path) -> None:
    manifest = registry.read_manifest(path)
    infos = dict(
        zip(catalog.get(manifest.model).control_names, catalog.get(manifest.model).control_info, strict=True)
    )
    for c in manifest.controls:
        got = ControlInfo(label=c.label, unit=c.unit, gain=c.gain, sign=c.sign)
        assert got == infos[c.name], c.name


def test_truck_controls_are_steer_then_gas() -> None:
    truck = catalog.get("truck")
    assert truck.control_names == ["steer", "gas"]
    steer, gas = truck.control_info
    assert (steer.unit, steer.gain, gas.unit, gas.gain) == ("N", 2.0, "N", 10.0)
    assert "left" in (steer.sign or "") and "forward" in (gas.sign or "")


def test_a_manifest_written_before_the_fields_still_reads() -> None:
    data = json.loads((COMMITTED[0] / registry.MANIFEST_FILE).read_text())
    for c in data["controls"]:
        for key in ("label", "unit", "gain", "sign"):
            c.pop(key, None)
    data["spec"].pop("control_info", None)
    manifest = parse_manifest(data)
    assert all(c.unit is None and c.sign is None for c in manifest.controls)


def test_a_trained_artifact_records_them(trained_pendulum: Trained) -> None:
    manifest = registry.read_manifest(trained_pendulum.path)
    assert [c.unit for c in manifest.controls] == ["N·m"] * 3
    assert all(c.label and c.sign for c in manifest.controls)


ACTUATORS = """<mujoco>
  <worldbody>
    <body name="a">
      <joint name="hinge" type="hinge" axis="0 0 1"/>
      <geom type="sphere" size="0.1" mass="1"/>
      <site name="tip" pos="0.1 0 0"/>
      <body name="b" pos="0.3 0 0">
        <joint name="slide" type="slide" axis="1 0 0"/>
        <geom type="sphere" size="0.1" mass="1"/>
        <site name="s2" pos="0 0 0"/>
      </body>
    </body>
  </worldbody>
  <tendon><spatial name="rope"><site site="tip"/><site site="s2"/></spatial></tendon>
  <actuator>
    <motor name="twist" joint="hinge" gear="2" ctrlrange="-1 1"/>
    <motor name="backwards" joint="hinge" gear="-3" ctrlrange="-1 1"/>
    <position name="aim" joint="hinge" kp="10" ctrlrange="-1 1"/>
    <velocity name="spin" joint="hinge" kv="5" ctrlrange="-1 1"/>
    <motor name="push" joint="slide" ctrlrange="-1 1"/>
    <general name="pull" tendon="rope" gainprm="-4" ctrlrange="0 1"/>
    <general name="thrust" site="tip" gear="0 0 5 0 0 0.1" ctrlrange="0 1"/>
  </actuator>
</mujoco>"""


def test_units_and_signs_from_the_mjcf() -> None:
    m = mujoco.MjModel.from_xml_string(ACTUATORS)
    got = {
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i): describe_actuator(m, i) for i in range(m.nu)
    }
    assert (got["twist"].unit, got["twist"].gain) == ("N·m", 2.0)
    assert "about +z" in (got["twist"].sign or "")
    assert (got["backwards"].gain, "about −z" in (got["backwards"].sign or "")) == (3.0, True)
    assert (got["aim"].unit, got["spin"].unit) == ("rad", "rad/s")
    assert (got["push"].unit, got["push"].gain) == ("N", 1.0)
    assert "along +x" in (got["push"].sign or "")
    assert (got["pull"].unit, got["pull"].gain) == ("N", 4.0)
    assert "contracts tendon rope" in (got["pull"].sign or "")
    assert (got["thrust"].unit, got["thrust"].gain) == ("N", 5.0)
    assert "+z" in (got["thrust"].sign or "") and "0.1 N·m" in (got["thrust"].sign or "")


def test_the_spec_overrides_field_by_field() -> None:
    spec = ModelSpec(name="myarm", control_info={"elbow_motor": ControlInfo(label="elbow")})
    arm = PhysicalModel(ARM_XML, spec)
    shoulder, elbow = arm.control_info
    assert shoulder.label == "torque on shoulder"
    assert (elbow.label, elbow.unit, elbow.gain) == ("elbow", "N·m", 1.0)


def test_control_info_for_an_unknown_control_is_refused() -> None:
    spec = ModelSpec(name="myarm", control_info={"wrist": ControlInfo(label="wrist")})
    with pytest.raises(ModelError, match="wrist"):
        PhysicalModel(ARM_XML, spec)
