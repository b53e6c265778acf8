"""Ground clearance features (``neuroanimator.emulator.clearance``): the forward kinematics inside the graph puts
every geom's lowest point where MuJoCo's own distance to the floor does, for every joint and geom kind;
the state is extrapolated as MuJoCo integrates positions; the runner's legs read their own feet; the
features survive ONNX export and an artifact's save and load."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.catalog.runner import gait as runner_control
from neuroanimator.core.model_spec import ModelSpec
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.articulated import articulated_core, branch_geoms
from neuroanimator.emulator.clearance import FRACTIONS, Clearance, ground_geoms, near_geoms
from neuroanimator.export.onnx import to_onnx
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainResult
from tests.helpers import METRICS

# every joint kind (free root, ball, hinge with an offset anchor, slide) and every geom kind
KINDS_XML = """
<mujoco model="kinds">
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1" pos="0 0 -0.3"/>
    <body name="root" pos="0 0 1">
      <freejoint/>
      <geom name="core" type="ellipsoid" size="0.2 0.1 0.15"/>
      <body name="arm" pos="0.2 0 0" quat="0.92 0 0.38 0">
        <joint name="shoulder" type="ball"/>
        <geom name="upper" type="capsule" fromto="0 0 0 0.3 0 0" size="0.04"/>
        <body name="fore" pos="0.3 0 0">
          <joint name="elbow" type="hinge" axis="0 1 1" pos="0.02 0 0.01" ref="0.2"/>
          <geom name="block" type="box" pos="0.15 0 0" size="0.12 0.03 0.05" quat="0.9 0.3 0.1 0"/>
          <body name="slider" pos="0.3 0 0">
            <joint name="extend" type="slide" axis="1 0.5 0" ref="0.05"/>
            <geom name="can" type="cylinder" size="0.05 0.08"/>
            <geom name="knob" type="sphere" pos="0 0 0.1" size="0.03"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="elbow" ctrlrange="-1 1"/></actuator>
</mujoco>
"""


@pytest.fixture(scope="module")
def kinds() -> PhysicalModel:
    return PhysicalModel(KINDS_XML, ModelSpec(name="kinds"))


@pytest.fixture(scope="module")
def runner() -> PhysicalModel:
    return catalog.get("runner")


def _random_states(model: PhysicalModel, n: int, seed: int = 0) -> np.ndarray:
    """(n, S) states at any attitude, joints and velocities far from rest."""
    rng = np.random.default_rng(seed)
    m = model.mj_model
    full = model.to_physics(np.repeat(model.rest_state()[None], n, axis=0))
    quat = rng.normal(size=(n, 4))
    full[:, 4:8] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    full[:, 3] = rng.uniform(0.1, 1.3, n)  # the root's height: some bodies reach through the floor
    full[:, 8 : 1 + m.nq] += rng.normal(0.0, 0.5, (n, m.nq - 7))
    for j in range(m.njnt):  # a ball joint's quaternion stays a unit quaternion
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            a = 1 + int(m.jnt_qposadr[j])
            full[:, a : a + 4] /= np.linalg.norm(full[:, a : a + 4], axis=1, keepdims=True)
    full[:, 1 + m.nq : 1 + m.nq + m.nv] = rng.normal(0.0, 1.0, (n, m.nv))
    return np.asarray(model.from_physics(full))


def _mujoco_clearance(model: PhysicalModel, states: np.ndarray, geoms: list[str], floor: str) -> np.ndarray:
    """(n, G) MuJoCo's signed distance from each geom to the floor geom (``mj_geomDistance``)."""
    m = model.mj_model
    d = mujoco.MjData(m)
    fid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, floor)
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in geoms]
    out = np.zeros((len(states), len(ids)))
    for i, full in enumerate(model.to_physics(states)):
        mujoco.mj_setState(m, d, full, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_kinematics(m, d)
        for j, g in enumerate(ids):
            out[i, j] = mujoco.mj_geomDistance(m, d, g, fid, 10.0, None)
    return out


@pytest.mark.parametrize("name", ["kinds", "runner"])
def test_the_lowest_points_are_where_mujoco_measures_them(
    name: str, kinds: PhysicalModel, runner: PhysicalModel
) -> None:
    model = kinds if name == "kinds" else runner
    geoms = ground_geoms(model.mj_model)
    assert len(geoms) == (5 if name == "kinds" else 18)  # every moving geom; not the floor
    states = _random_states(model, 40)
    clr = Clearance(model, geoms, horizon=0.02)
    got = clr(torch.from_numpy(states).float()).numpy().reshape(40, len(geoms), len(FRACTIONS))[:, :, 0]
    want = _mujoco_clearance(model, states, geoms, "floor")
    # above the floor MuJoCo's distance is exact for these shapes; below it, it is the penetration depth
    # along the contact normal, which for the plane is the same height
    np.testing.assert_allclose(got, want, atol=2e-4)
    assert got.min() < 0.0 < got.max()  # some of these states go through the floor


def test_the_state_is_extrapolated_as_mujoco_integrates_positions(kinds: PhysicalModel) -> None:
    m = kinds.mj_model
    geoms = ground_geoms(m)
    states = _random_states(kinds, 16, seed=2)
    h = 0.01
    got = Clearance(kinds, geoms, h)(torch.from_numpy(states).float()).numpy()
    got = got.reshape(16, len(geoms), len(FRACTIONS))
    d = mujoco.MjData(m)
    fid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in geoms]
    for i, full in enumerate(kinds.to_physics(states)):
        mujoco.mj_setState(m, d, full, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        q0 = d.qpos.copy()
        for k, a in enumerate(FRACTIONS):
            d.qpos[:] = q0
            mujoco.mj_integratePos(m, d.qpos, d.qvel, a * h)
            mujoco.mj_kinematics(m, d)
            want = [mujoco.mj_geomDistance(m, d, g, fid, 10.0, None) for g in ids]
            # first order in the quaternions' turn: a few 1e-5 m over 10 ms at these rates
            np.testing.assert_allclose(got[i, :, k], want, atol=1e-3 if k else 2e-4)


def test_only_geoms_that_come_near_the_floor_are_probed(runner: PhysicalModel) -> None:
    start = runner_control.running_start(runner.mj_model, 2.0)
    states = runner.from_physics(start[None])
    near = near_geoms(runner, states, 0.0162)
    assert "left_foot" in near and "head" not in near and "right_hand" not in near


def test_probing_and_transforming_in_chunks_equals_all_at_once(
    kinds: PhysicalModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Large data sets are probed and transformed a chunk at a time (the runner's 1.6 million examples
    would hold 26 GB at once); the chunks' seams change nothing."""
    states = _random_states(kinds, 50, seed=3)
    nxt = _random_states(kinds, 50, seed=4)
    whole = near_geoms(kinds, states, 0.05)
    emu = training.build_emulator(
        kinds, TrainConfig(substeps=10, hidden=(8,), limits=False, clearance=True), states
    )
    s, n = torch.from_numpy(states).float(), torch.from_numpy(nxt).float()
    u = torch.linspace(-1.0, 1.0, 50)[:, None]
    with torch.no_grad():
        x_all, y_all = emu.local_inputs(s, u, None), emu.delta_to_local(s, n - s)
        monkeypatch.setattr("neuroanimator.emulator.clearance.PROBE_CHUNK", 7)
        monkeypatch.setattr(training, "LOCAL_CHUNK", 7)
        x, y = training.local_examples(emu, s, u, None, n)
    assert near_geoms(kinds, states, 0.05) == whole and whole  # some geoms come near the floor
    assert emu.clearance is not None and x.shape == x_all.shape
    assert torch.allclose(x, x_all, atol=1e-6) and torch.allclose(y, y_all, atol=1e-6)


def _emulator(model: PhysicalModel, seed: int = 0) -> training.StructuredEmulator:
    torch.manual_seed(seed)
    emu = training.build_emulator(model, TrainConfig(substeps=6, hidden=(16,), limits=False, clearance=True))
    with torch.no_grad():
        emu.x_std.uniform_(0.5, 2.0)
        emu.y_std.uniform_(0.005, 0.02)
        for p in emu.core.parameters():
            p.normal_(0.0, 0.3)
    return emu.eval()


def test_a_leg_reads_its_own_feet_and_not_the_other_legs(runner: PhysicalModel) -> None:
    emu = _emulator(runner)
    core = articulated_core(emu)
    assert core is not None and emu.clearance is not None
    left = next(b for b in core.branches if b.name == "left_leg")
    assert branch_geoms(emu, left) == ["left_thigh", "left_shank", "left_foot", "left_toes"]
    k = [b.name for b in core.branches].index("left_leg")
    states = torch.from_numpy(_random_states(runner, 4)).float()
    u, f = torch.zeros(4, runner.num_controls), torch.zeros(4, runner.num_forces)
    moved, own = states.clone(), states.clone()
    moved[:, runner.layout.slice_of("right_knee.angle").start] += 0.4
    own[:, runner.layout.slice_of("left_ankle_y.angle").start] += 0.4
    with torch.no_grad():
        x, x_moved, x_own = (emu.network_inputs(s, u, f) @ core.selection(k) for s in (states, moved, own))
    assert torch.equal(x, x_moved)  # the right foot's height is not among its inputs
    assert not torch.equal(x, x_own)


def test_clearance_survives_export_and_an_artifact_round_trip(runner: PhysicalModel, tmp_path: Path) -> None:
    emu = _emulator(runner)
    states = torch.from_numpy(_random_states(runner, 32)).float()
    u, f = torch.zeros(32, runner.num_controls), torch.zeros(32, runner.num_forces)
    with torch.no_grad():
        want = emu(states, u, f)
    onnx = OnnxEmulator(to_onnx(emu)).step(states.numpy(), u.numpy(), f.numpy())
    np.testing.assert_allclose(onnx, want.numpy(), atol=2e-5, rtol=0)
    cfg = TrainConfig(substeps=6, hidden=(16,), limits=False, clearance=True, progress=False)
    path = artifacts.save(tmp_path, runner, TrainResult(emu, cfg, METRICS, np.zeros((1, 1)), "0" * 64))
    nets = {n.name: n for n in registry.read_manifest(path).emulator.networks}
    assert nets["trunk"].clearance is not None and len(nets["trunk"].clearance.geoms) == 18
    assert nets["left_leg"].clearance is not None and nets["left_arm"].clearance is not None
    with torch.no_grad():
        torch.testing.assert_close(artifacts.load_torch(path)(states, u, f), want, rtol=0, atol=0)
