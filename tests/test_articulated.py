"""Articulated hierarchies (thesis 4.4, Fig. 4.8): a trunk network and one network per limb composed into
one step; the composition, what each network reads, its ONNX graph, its artifact, its training."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.core.model_spec import Branch
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.articulated import TRUNK, ArticulatedCore, articulated_core, check_branches
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.export.onnx import to_onnx
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainResult
from tests.helpers import METRICS, ROOT


@pytest.fixture(scope="module")
def runner() -> PhysicalModel:
    return catalog.get("runner")


def _random(model: PhysicalModel, seed: int = 0) -> StructuredEmulator:
    """The model's articulated emulator with random weights and normalisation (nothing cancels)."""
    torch.manual_seed(seed)
    emu = training.build_emulator(model, TrainConfig(substeps=6, hidden=(16,)))
    with torch.no_grad():
        emu.x_mean.normal_(0.0, 0.1)
        emu.x_std.uniform_(0.5, 2.0)
        emu.y_mean.normal_(0.0, 0.01)
        emu.y_std.uniform_(0.005, 0.02)
        for p in emu.core.parameters():
            p.normal_(0.0, 0.3)
    return emu.eval()


def _inputs(model: PhysicalModel, batch: int, seed: int = 1) -> tuple[torch.Tensor, ...]:
    rng = np.random.default_rng(seed)
    s = model.initial_states(rng, batch)
    s += rng.normal(0.0, 0.05, s.shape) * (np.arange(model.state_size) >= 7)  # joints away from rest
    lo, hi = model.control_range.T
    u = rng.uniform(lo, hi, (batch, model.num_controls))
    f = rng.uniform(-100.0, 100.0, (batch, model.num_forces))
    return tuple(torch.from_numpy(a).float() for a in (s, u, f))


def test_the_runner_is_the_thesis_hierarchy(runner: PhysicalModel) -> None:
    emu = _random(runner)
    core = articulated_core(emu)
    assert core is not None
    cols = core.output_columns()
    assert list(cols) == [TRUNK, "left_arm", "left_leg", "right_arm", "right_leg"]
    # Table 6.1's sizes with our joints: the torso 23 (root 13, waist and neck 5 angles and rates)
    assert len(cols[TRUNK]) == 23
    assert [len(cols[n]) for n in ("left_arm", "left_leg")] == [10, 14]
    assert sorted(c for cs in cols.values() for c in cs) == list(range(runner.state_size))


def test_the_composition_equals_the_networks_run_one_after_another(runner: PhysicalModel) -> None:
    emu = _random(runner)
    core = articulated_core(emu)
    assert core is not None
    s, u, f = _inputs(runner, 8)
    with torch.no_grad():
        x = emu.network_inputs(s, u, f)
        trunk = core.trunk(x)
        y = torch.zeros(8, runner.state_size)
        cols = core.output_columns()
        y[:, cols[TRUNK]] = trunk
        for k, b in enumerate(core.branches):
            y[:, cols[b.name]] = core.branch_net(k)(torch.cat([x @ core.selection(k), trunk], dim=1))
        torch.testing.assert_close(emu(s, u, f), emu.finish(s, y), rtol=0, atol=1e-6)


def test_a_limb_network_reads_its_own_joints_and_the_trunk_not_the_other_limbs(runner: PhysicalModel) -> None:
    emu = _random(runner)
    core = articulated_core(emu)
    assert core is not None
    s, u, f = _inputs(runner, 4)
    left_leg = [b.name for b in core.branches].index("left_leg")
    right_knee = runner.layout.slice_of("right_knee.angle").start
    left_knee = runner.layout.slice_of("left_knee.angle").start
    moved = s.clone()
    moved[:, right_knee] += 0.3
    own = s.clone()
    own[:, left_knee] += 0.3
    with torch.no_grad():
        x, x_moved, x_own = (emu.network_inputs(a, u, f) for a in (s, moved, own))
        sel = core.selection(left_leg)
        assert torch.equal(x @ sel, x_moved @ sel)  # the right knee is not among its inputs
        assert not torch.equal(x @ sel, x_own @ sel)  # its own knee is
        # the other leg still reaches it through the trunk's prediction, as through the pelvis
        u2 = u.clone()
        u2[:, runner.control_names.index("right_knee")] += 0.2
        assert torch.equal(emu.network_inputs(s, u2, f) @ sel, x @ sel)  # its controls are its own


def test_onnx_equals_torch(runner: PhysicalModel) -> None:
    emu = _random(runner)
    s, u, f = _inputs(runner, 64)
    onnx = OnnxEmulator(to_onnx(emu)).step(s.numpy(), u.numpy(), f.numpy())
    with torch.no_grad():
        np.testing.assert_allclose(onnx, emu(s, u, f).numpy(), atol=2e-5, rtol=0)


def test_the_artifact_describes_five_networks_in_two_stages_and_loads_back(
    runner: PhysicalModel, tmp_path: Path
) -> None:
    emu = _random(runner)
    cfg = TrainConfig(substeps=6, hidden=(16,), progress=False)
    path = artifacts.save(tmp_path, runner, TrainResult(emu, cfg, METRICS, np.zeros((1, 1)), "0" * 64))
    graph = registry.read_manifest(path).emulator
    assert graph.stages == [[TRUNK], ["left_arm", "left_leg", "right_arm", "right_leg"]]
    nets = {n.name: n for n in graph.networks}
    assert nets["left_leg"].reads.predicted == nets[TRUNK].writes
    assert nets["left_leg"].reads.controls == [
        f"left_{j}" for j in ("hip_x", "hip_z", "hip_y", "knee", "ankle_y", "ankle_x", "toe")
    ]
    assert sum(n.weights for n in graph.networks) == sum(p.numel() for p in emu.parameters())
    assert all(n.input_size == sum(g.size for g in n.normalization.input_groups) for n in graph.networks)
    loaded = artifacts.load_torch(path)
    s, u, f = _inputs(runner, 16)
    with torch.no_grad():
        torch.testing.assert_close(loaded(s, u, f), emu(s, u, f), rtol=0, atol=0)
    onnx = OnnxEmulator(path / registry.ONNX_FILE).step(s.numpy(), u.numpy(), f.numpy())
    np.testing.assert_allclose(onnx, loaded(s, u, f).detach().numpy(), atol=2e-5, rtol=0)


def test_bad_branches_are_refused(runner: PhysicalModel) -> None:
    emu = training.build_emulator(
        runner.__class__(runner.xml, runner.spec.model_copy(update={"branches": []})),
        TrainConfig(hidden=(8,), skip=False),
    )
    names = runner.control_names
    with pytest.raises(ValueError, match=re.escape("unknown ['nose.angle']")):
        check_branches(emu, [Branch(name="a", groups=["nose.angle"])], names)
    with pytest.raises(ValueError, match=re.escape("twice ['left_knee.angle']")):
        check_branches(
            emu,
            [Branch(name="a", groups=["left_knee.angle"]), Branch(name="b", groups=["left_knee.angle"])],
            names,
        )
    with pytest.raises(ValueError, match="the trunk network would write nothing"):
        check_branches(emu, [Branch(name="a", groups=[g.name for g in runner.layout])], names)
    with pytest.raises(ValueError, match=re.escape("reads unknown controls ['tail']")):
        check_branches(emu, [Branch(name="a", groups=["left_knee.angle"], controls=["tail"])], names)
    with pytest.raises(ValueError, match="not 'trunk'"):
        ArticulatedCore(emu, [Branch(name=TRUNK, groups=["left_knee.angle"])], names, (4,), (4,), "tanh")


CART_WITH_TWO_ARMS = """
<mujoco model="cart-arms">
  <option timestep="0.005"/>
  <worldbody>
    <body name="cart">
      <joint name="slide" type="slide" axis="1 0 0" damping="0.5"/>
      <geom type="box" size="0.2 0.1 0.05" mass="2"/>
      <body name="left" pos="0 0.15 0">
        <joint name="left" type="hinge" axis="0 1 0" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03" mass="0.5"/>
      </body>
      <body name="right" pos="0 -0.15 0">
        <joint name="right" type="hinge" axis="0 1 0" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="slide" ctrlrange="-5 5"/>
    <motor name="left" joint="left" ctrlrange="-1 1"/>
    <motor name="right" joint="right" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


@pytest.mark.parametrize("members", [1, 2])
def test_a_small_articulated_emulator_trains_below_its_linear_baselines(members: int) -> None:
    """A cart with two swinging arms, each arm a branch: every network learns, and beats a linear map of
    its own inputs; the same with every network an ensemble of two."""
    probe = PhysicalModel(CART_WITH_TWO_ARMS, catalog.ModelSpec(name="cart-arms"))
    groups = [g.name for g in probe.layout]
    arms = [
        Branch(name=side, groups=[g for g in groups if g.startswith(f"{side}.")], controls=[side])
        for side in ("left", "right")
    ]
    model = PhysicalModel(CART_WITH_TWO_ARMS, catalog.ModelSpec(name="cart-arms", branches=arms, substeps=10))
    # ends by its epochs and patience in a few seconds; the cap is only a guard, so a loaded machine
    # trains the same epochs rather than fewer
    cfg = TrainConfig(substeps=10, hidden=(32,), examples=3000, test_examples=500, max_seconds=120,
                      rollout_steps=0, members=members, progress=False)  # fmt: skip
    result = training.train(model, cfg)
    nets = result.metrics["networks"]
    assert set(nets) == {TRUNK, "left", "right"}
    assert [nets[n]["outputs"] for n in (TRUNK, "left", "right")] == [2, 2, 2]
    for name, m in nets.items():
        assert m["one_step_rel_error"] < 0.5 * m["linear_baseline_rel_error"], name


def test_the_committed_runner_emulator_runs_a_short_closed_loop_finite_and_upright(
    runner: PhysicalModel,
) -> None:
    """The catalog's runner emulator (``neuro train runner``) driven by the running controller for half
    a second from a running start: it stays finite and up, and close to MuJoCo's run."""
    from neuroanimator.catalog.runner import gait as rc

    path = registry.resolve(ROOT / "artifacts", "runner")
    manifest = registry.read_manifest(path)
    assert manifest.emulator.stages[0] == [TRUNK] and len(manifest.emulator.stages[1]) == 4
    onnx = OnnxEmulator(path / registry.ONNX_FILE)

    def step(s: np.ndarray, u: np.ndarray, f: np.ndarray) -> np.ndarray:
        return np.asarray(onnx.step(s.astype(np.float32), u.astype(np.float32), f.astype(np.float32)), float)

    m = runner.mj_model
    start = rc.running_start(m, 2.2)
    emulated = rc.run_emulated(runner, step, manifest.substeps, start, 2.2, 0.5)
    assert np.isfinite(emulated.states).all() and not np.isfinite(emulated.fell_at).any()
    z = emulated.states[0, :, runner.layout.slice_of("root.pos").start + 2]
    assert z.min() > 0.75
    ref = rc.run(m, start, 2.2, 0.5, control_every=manifest.substeps, kinematic=True)
    pos = runner.layout.slice_of("root.pos")
    sim = runner.from_physics(ref.states[0])
    # 0.06 m and 0.11 m for the last two committed emulators from this start (1.1 m run); a broken step
    # (a frame or a control order mixed up) is metres off or down
    assert np.linalg.norm(emulated.states[0, len(sim) - 1, pos] - sim[-1, pos]) < 0.2


def _ensembled(model: PhysicalModel, members: int) -> StructuredEmulator:
    torch.manual_seed(3)
    emu = training.build_emulator(model, TrainConfig(substeps=6, hidden=(16,), members=members))
    with torch.no_grad():
        emu.y_std.uniform_(0.005, 0.02)
        for p in emu.core.parameters():
            p.normal_(0.0, 0.3)
    return emu.eval()


def test_an_ensembled_network_is_the_mean_of_its_members(runner: PhysicalModel, tmp_path: Path) -> None:
    """``members``: each network is the mean of K MLPs beside one linear path; its artifact says so and
    loads back, and its ONNX graph computes the same step."""
    emu = _ensembled(runner, 3)
    core = articulated_core(emu)
    assert core is not None and core.members == 3
    s, u, f = _inputs(runner, 16)
    with torch.no_grad():
        x = emu.network_inputs(s, u, f)
        each = core.trunk.member_outputs(x)  # (K, B, T)
        assert each.shape == (3, 16, 23) and not torch.allclose(each[0], each[1])
        torch.testing.assert_close(core.trunk(x), each.mean(dim=0), rtol=0, atol=1e-5)
    cfg = TrainConfig(substeps=6, hidden=(16,), members=3, progress=False)
    path = artifacts.save(tmp_path, runner, TrainResult(emu, cfg, METRICS, np.zeros((1, 1)), "0" * 64))
    graph = registry.read_manifest(path).emulator
    assert {n.members for n in graph.networks} == {3}
    assert sum(n.weights for n in graph.networks) == sum(p.numel() for p in emu.parameters())
    loaded = artifacts.load_torch(path)
    with torch.no_grad():
        torch.testing.assert_close(loaded(s, u, f), emu(s, u, f), rtol=0, atol=0)
    onnx = OnnxEmulator(path / registry.ONNX_FILE).step(s.numpy(), u.numpy(), f.numpy())
    np.testing.assert_allclose(onnx, loaded(s, u, f).detach().numpy(), atol=2e-5, rtol=0)


def test_each_member_learns_on_its_own_error(runner: PhysicalModel) -> None:
    """The training loss is the mean of the members' own squared errors (not the error of their mean),
    so a member's gradient does not depend on the others; with one member it is the plain mean squared
    error."""
    s, u, f = _inputs(runner, 32)
    single = _ensembled(runner, 1).train()
    core1 = articulated_core(single)
    assert core1 is not None
    x = single.network_inputs(s, u, f).detach()
    y = torch.randn(32, runner.state_size)
    torch.testing.assert_close(core1.training_loss(x, y), torch.mean((core1(x) - y) ** 2))
    emu = _ensembled(runner, 2).train()
    core = articulated_core(emu)
    assert core is not None
    loss = core.training_loss(x, y)
    assert loss.item() > torch.mean((core(x) - y) ** 2).item()  # the members' errors, not their mean's
    loss.backward()
    first = core.trunk.mlp[-1].weight.grad
    assert first is not None
    with torch.no_grad():  # moving the other member changes nothing in this one's gradient
        for p in core.trunk.more.parameters():
            p.add_(0.5)
    core.zero_grad()
    core.training_loss(x, y).backward()
    torch.testing.assert_close(core.trunk.mlp[-1].weight.grad, first)


def test_members_are_for_a_hierarchy() -> None:
    with pytest.raises(ValueError, match="members"):
        training.build_emulator(catalog.get("lander"), TrainConfig(members=2))
