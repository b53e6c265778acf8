"""Models nobody here wrote, kept in tests/data with their licences (see each folder's NOTICE.md), load
through ``load_mjcf`` and behave as their authors built them:

- Gymnasium's inverted double pendulum (``inverted_double_pendulum``): its slider motor drives the cart
  into the rail's limit;
- reinmav-gym's quadrotor (``reinmav_quadrotor``), without a keyframe: where it operates is found from
  the physics, four equal thrusts that carry its weight and keep it still;
- MuJoCo Menagerie's UR5e (``universal_robots_ur5e``, visual meshes left out): its ``home`` keyframe
  is where it operates, and its servos hold it there against gravity."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from neuroanimator.sim import operating
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import PhysicalModel

DATA = Path(__file__).resolve().parents[1] / "data"
PENDULUM = DATA / "inverted_double_pendulum"
QUADROTOR = DATA / "reinmav_quadrotor"
UR5E = DATA / "universal_robots_ur5e"

QUADROTOR_WEIGHT = 0.3 * 9.81  # N: a 0.1 kg core, four 0.025 kg arms and four 0.025 kg rotor discs
UR5E_MASS = 4.0 + 3.7 + 8.393 + 2.275 + 1.219 + 1.219 + 0.1889  # kg: the seven links' <inertial> masses


def _load(folder: Path, entry: str) -> PhysicalModel:
    return load_mjcf(folder, entry=entry)


def _simulate(
    m: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray, seconds: float
) -> mujoco.MjData:
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:] = qpos, qvel, ctrl
    for _ in range(round(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
    return d


@pytest.mark.parametrize(
    ("folder", "entry", "name", "controls", "state_size"),
    [
        (PENDULUM, "inverted_double_pendulum.xml", "cartpole", ["slide"], 6),
        (
            QUADROTOR,
            "quadrotor_hovering.xml",
            "quadrotor0",
            ["actuator0", "actuator1", "actuator2", "actuator3"],
            13,
        ),
        (
            UR5E,
            "ur5e.xml",
            "ur5e",
            ["shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3"],
            12,
        ),
    ],
    ids=["inverted_double_pendulum", "reinmav_quadrotor", "universal_robots_ur5e"],
)
def test_each_loads_through_load_mjcf(
    folder: Path, entry: str, name: str, controls: list[str], state_size: int
) -> None:
    model = _load(folder, entry)
    assert model.name == name
    assert list(model.control_names) == controls
    assert model.state_size == state_size
    assert (folder / "LICENSE").is_file() and (folder / "NOTICE.md").is_file()


def test_the_double_pendulum_slider_reaches_its_rail_limit_under_full_control() -> None:
    m = _load(PENDULUM, "inverted_double_pendulum.xml").mj_model
    slider = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "slider")
    assert m.jnt_limited[slider] and tuple(m.jnt_range[slider]) == (-1.0, 1.0)
    assert m.nu == 1 and m.actuator_gear[0, 0] == 500.0
    end = float(m.jnt_range[slider, 1])
    address = int(m.jnt_qposadr[slider])
    d = mujoco.MjData(m)
    d.ctrl[:] = 1.0
    reached_at = None
    while d.time < 0.5 and reached_at is None:
        mujoco.mj_step(m, d)
        limit_engaged = np.any(
            (d.efc_type[: d.nefc] == mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT)
            & (d.efc_id[: d.nefc] == slider)
        )
        if d.qpos[address] >= end - 1e-3 or limit_engaged:
            reached_at = d.time
    assert reached_at is not None, f"the cart is at {d.qpos[address]:.3f} m after 0.5 s, short of {end} m"


def test_the_quadrotor_has_no_keyframe_and_is_held_by_four_equal_thrusts() -> None:
    m = _load(QUADROTOR, "quadrotor_hovering.xml").mj_model
    assert m.nkey == 0 and m.nu == 4
    found = operating.find(m)
    assert found.source == "hold", found.reason
    (point,) = found.points
    thrust = point.ctrl
    assert np.ptp(thrust) <= 0.01 * np.mean(thrust)
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    assert np.all(m.actuator_ctrllimited) and np.all((lo <= thrust) & (thrust <= hi))
    assert float(np.sum(thrust)) == pytest.approx(QUADROTOR_WEIGHT, rel=1e-3)
    d = _simulate(m, point.qpos, point.qvel, thrust, 1.0)
    assert np.linalg.norm(d.qpos[:3] - point.qpos[:3]) < 1e-3


def test_the_ur5e_is_held_at_its_home_keyframe() -> None:
    m = _load(UR5E, "ur5e.xml").mj_model
    assert float(m.body_subtreemass[0]) == pytest.approx(UR5E_MASS)
    assert not any(m.geom_type == mujoco.mjtGeom.mjGEOM_MESH)
    found = operating.find(m)
    assert found.source == "keyframe", found.reason
    assert [k.name for k in found.points] == ["home"]
    for point in found.points:
        d = _simulate(m, point.qpos, point.qvel, point.ctrl, 1.0)
        assert np.max(np.abs(d.qpos - point.qpos)) < 0.01
