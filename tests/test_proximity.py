"""Distances between pairs of geoms (``neuroanimator.emulator.proximity`` through ``clearance.Clearance``): the
graph puts two spheres and capsules as far apart as MuJoCo measures them, wherever the joints put them
and whichever body (or the world) holds them; a bounding capsule stands in for other shapes; the pairs
are the ones that touch in the data, not the floor's; a limited string's slack is what MuJoCo's tendon
length leaves of its range; the features survive ONNX export and an artifact's save and load; the
gradient is finite where segments are parallel or a segment is a point."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.cli import main
from neuroanimator.core.model_spec import ModelSpec
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator import proximity
from neuroanimator.emulator.clearance import FRACTIONS, Clearance, limited_site_tendons
from neuroanimator.export.onnx import to_onnx
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainResult
from tests.helpers import METRICS

# a two-link arm (hinges with offset anchors) whose tip reaches a ball on two slides and a fixed post;
# a box, a cylinder and an ellipsoid on the ball's body for the bounding capsules
ARM_XML = """
<mujoco model="reach">
  <option gravity="0 0 0"/>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1" pos="0 0 -1"/>
    <geom name="post" type="capsule" fromto="0.5 -0.2 0 0.5 0.2 0.1" size="0.05"/>
    <body name="upper" pos="0 0 0">
      <joint name="shoulder" type="hinge" axis="0 1 0" pos="0 0 0.02"/>
      <geom name="upper" type="capsule" fromto="0 0 0 0.4 0 0" size="0.04"/>
      <body name="fore" pos="0.4 0 0" quat="0.96 0 0.28 0">
        <joint name="elbow" type="hinge" axis="0 1 0.2" ref="0.1"/>
        <geom name="tip" type="capsule" fromto="0 0 0 0.35 0 0" size="0.03"/>
        <site name="hand" pos="0.35 0 0"/>
      </body>
    </body>
    <body name="ball" pos="0.6 0 0.3">
      <joint name="ball_x" type="slide" axis="1 0 0"/>
      <joint name="ball_z" type="slide" axis="0 0 1"/>
      <geom name="ball" type="sphere" size="0.06"/>
      <site name="ball" pos="0 0.02 0.05"/>
      <geom name="crate" type="box" pos="0 0 0.3" size="0.04 0.03 0.12" quat="0.9 0.3 0 0.2"/>
      <geom name="can" type="cylinder" pos="0.3 0 0" size="0.05 0.1"/>
      <geom name="egg" type="ellipsoid" pos="-0.3 0 0" size="0.05 0.08 0.15"/>
    </body>
    <site name="hook" pos="0.2 0.1 0.6"/>
  </worldbody>
  <tendon>
    <spatial name="string" limited="true" range="0 1.1"><site site="hand"/><site site="hook"/><site site="ball"/></spatial>
    <spatial name="loose"><site site="hand"/><site site="ball"/></spatial>
  </tendon>
  <actuator>
    <motor joint="shoulder" ctrlrange="-1 1"/>
    <motor joint="elbow" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""
EXACT = [("tip", "ball"), ("upper", "ball"), ("tip", "post"), ("ball", "post"), ("upper", "tip")]
BOUNDED = [("tip", "crate"), ("tip", "can"), ("tip", "egg")]


@pytest.fixture(scope="module")
def arm() -> PhysicalModel:
    return PhysicalModel(ARM_XML, ModelSpec(name="reach"))


def _states(model: PhysicalModel, n: int, seed: int = 0) -> np.ndarray:
    """(n, S) states with the joints anywhere over their reach and the ball within a metre."""
    rng = np.random.default_rng(seed)
    m = model.mj_model
    full = model.to_physics(np.repeat(model.rest_state()[None], n, axis=0))
    full[:, 1 : 1 + m.nq] = rng.uniform(-np.pi, np.pi, (n, m.nq)) * np.array([1.0, 1.0, 0.3, 0.3])
    full[:, 1 + m.nq : 1 + m.nq + m.nv] = rng.normal(0.0, 1.0, (n, m.nv))
    return np.asarray(model.from_physics(full))


def _mujoco_gaps(model: PhysicalModel, states: np.ndarray, pairs: list[tuple[str, str]]) -> np.ndarray:
    """(n, P) MuJoCo's signed distance between the geoms of each pair (``mj_geomDistance``)."""
    m = model.mj_model
    d = mujoco.MjData(m)
    ids = [tuple(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in p) for p in pairs]
    out = np.zeros((len(states), len(ids)))
    for i, full in enumerate(model.to_physics(states)):
        mujoco.mj_setState(m, d, full, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_kinematics(m, d)
        for j, (a, b) in enumerate(ids):
            out[i, j] = mujoco.mj_geomDistance(m, d, a, b, 10.0, None)
    return out


def _gaps(clr: Clearance, states: np.ndarray) -> np.ndarray:
    """(n, P, K) the graph's distances."""
    out = clr(torch.from_numpy(states).float()).detach().numpy()
    return out.reshape(len(states), -1, len(FRACTIONS))[:, len(clr.geoms) :]


def test_spheres_and_capsules_are_as_far_apart_as_mujoco_measures(arm: PhysicalModel) -> None:
    states = _states(arm, 300)
    got = _gaps(Clearance(arm, [], 0.05, EXACT), states)[:, :, 0]
    want = _mujoco_gaps(arm, states, EXACT)
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert (want < 0).any(axis=0).sum() >= 3  # overlapping pairs are measured too (negative)


def test_other_shapes_are_their_bounding_capsules(arm: PhysicalModel) -> None:
    states = _states(arm, 300, seed=1)
    got = _gaps(Clearance(arm, [], 0.05, BOUNDED), states)[:, :, 0]
    want = _mujoco_gaps(arm, states, BOUNDED)
    # a capsule along the longest axis, as wide as the widest cross-section: within a half-size
    assert np.abs(got - want).max() < 0.06
    assert np.corrcoef(got.ravel(), want.ravel())[0, 1] > 0.99


def test_the_gaps_follow_the_extrapolated_state(arm: PhysicalModel) -> None:
    m = arm.mj_model
    states = _states(arm, 20, seed=3)
    h = 0.05
    got = _gaps(Clearance(arm, [], h, EXACT), states)
    d = mujoco.MjData(m)
    for i, full in enumerate(arm.to_physics(states)):
        mujoco.mj_setState(m, d, full, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        q0 = d.qpos.copy()
        for k, a in enumerate(FRACTIONS):
            d.qpos[:] = q0
            mujoco.mj_integratePos(m, d.qpos, d.qvel, a * h)
            mujoco.mj_kinematics(m, d)
            for p, names in enumerate(EXACT):
                ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in names]
                want = mujoco.mj_geomDistance(m, d, ids[0], ids[1], 10.0, None)
                assert got[i, p, k] == pytest.approx(want, abs=2e-5)


def test_the_pairs_are_those_that_touch_and_not_the_floor(arm: PhysicalModel) -> None:
    m = arm.mj_model
    full = arm.to_physics(_states(arm, 400, seed=4))
    floors = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")}
    pairs = proximity.touching_pairs(m, full[:, 1 : 1 + m.nq], floors)
    names = {tuple(sorted(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in p)) for p in pairs}
    assert ("ball", "tip") in names
    assert not any("floor" in p for p in names)
    assert ("tip", "upper") not in names  # a parent and its child do not collide
    assert len(pairs) <= proximity.MAX_PAIRS


def test_a_strings_slack_is_what_its_length_leaves_of_its_range(arm: PhysicalModel) -> None:
    m = arm.mj_model
    assert limited_site_tendons(m) == ["string"]  # "loose" has no limit
    states = _states(arm, 200, seed=6)
    clr = Clearance(arm, [], 0.05, (), ["string"])
    got = clr(torch.from_numpy(states).float()).detach().numpy().reshape(200, 1, len(FRACTIONS))[:, 0, 0]
    d = mujoco.MjData(m)
    want = np.zeros(200)
    for i, full in enumerate(arm.to_physics(states)):
        mujoco.mj_setState(m, d, full, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_forward(m, d)
        want[i] = 1.1 - d.ten_length[0]
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert want.min() < 0.0 < want.max()  # some of these states pull it taut past its limit
    with pytest.raises(ValueError, match="no limited tendon through sites named 'loose'"):
        Clearance(arm, [], 0.05, (), ["loose"])


def test_the_gradient_is_finite_for_points_and_parallel_segments() -> None:
    total = proximity.sum_matrix(3)
    c1 = torch.tensor([[0.0, 0, 0, 0, 0, 0, 0, 0, 0]], requires_grad=True)
    d1 = torch.tensor([[0.0, 0, 0, 1, 0, 0, 1, 0, 0]])  # a point; a segment; a segment
    c2 = torch.tensor([[1.0, 0, 0, 0, 1, 0, 0, 0, 0.0]])
    d2 = torch.tensor([[0.0, 0, 1, 1, 0, 0, 1, 0, 0]])  # a segment; parallel; the same segment
    gap = proximity.segment_gap(c1, d1, c2, d2, torch.zeros(3), total)
    np.testing.assert_allclose(gap.detach().numpy(), [[1.0, 1.0, 0.0]], atol=1e-5)
    gap.sum().backward()
    assert c1.grad is not None and torch.isfinite(c1.grad).all()


def test_pairs_survive_export_and_an_artifact_round_trip(arm: PhysicalModel, tmp_path: Path) -> None:
    cfg = TrainConfig(substeps=5, hidden=(16,), clearance=True, proximity=True, progress=False)
    states = _states(arm, 400, seed=5)
    emu = training.build_emulator(arm, cfg, states)
    assert emu.clearance is not None and ("ball", "tip") in {tuple(sorted(p)) for p in emu.clearance.pairs}
    assert emu.clearance.tendons == ("string",)
    torch.manual_seed(0)
    with torch.no_grad():
        emu.x_std.uniform_(0.5, 2.0)
        emu.y_std.uniform_(0.005, 0.02)
        for p in emu.core.parameters():
            p.normal_(0.0, 0.3)
    emu.eval()
    x = torch.from_numpy(states[:32]).float()
    u, f = torch.zeros(32, arm.num_controls), torch.zeros(32, 0)
    with torch.no_grad():
        want = emu(x, u, f)
    onnx = OnnxEmulator(to_onnx(emu)).step(x.numpy(), u.numpy(), f.numpy())
    np.testing.assert_allclose(onnx, want.numpy(), atol=2e-5, rtol=0)
    path = artifacts.save(tmp_path, arm, TrainResult(emu, cfg, METRICS, np.zeros((1, 1)), "0" * 64))
    (net,) = registry.read_manifest(path).emulator.networks
    assert net.clearance is not None and [tuple(p) for p in net.clearance.pairs] == list(emu.clearance.pairs)
    assert net.clearance.tendons == ["string"]
    with torch.no_grad():
        torch.testing.assert_close(artifacts.load_torch(path)(x, u, f), want, rtol=0, atol=0)


@pytest.mark.parametrize("flag", ["on", None])
def test_neuro_train_reads_the_pairs_only_when_asked(flag: str | None, tmp_path: Path) -> None:
    path = tmp_path / "reach.xml"
    path.write_text(ARM_XML)
    out = tmp_path / "out"
    argv = ["train", "--mjcf", str(path), "--substeps", "10", "--examples", "400", "--epochs", "1"]
    argv += ["--hidden", "8", "--rollout-steps", "0", "--force", "--out", str(out), "--quiet"]
    assert main(argv + (["--proximity", flag] if flag else [])) == 0
    (net,) = registry.read_manifest(registry.resolve(out, "reach")).emulator.networks
    assert net.clearance is not None and net.clearance.tendons == ["string"]  # a limit: always read
    assert bool(net.clearance.pairs) == (flag == "on")
