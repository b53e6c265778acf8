"""Hierarchical emulators (thesis 4.4): the composition of a global and local networks, its ONNX graph."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuroanimator import physics, sampling
from neuroanimator.export import OnnxEmulator, to_onnx
from neuroanimator.hierarchy import HierarchicalEmulator, check_parts
from neuroanimator.physics.model import PhysicalModel


@pytest.fixture(scope="module")
def dolphin() -> PhysicalModel:
    return physics.get("dolphin")


@pytest.fixture(scope="module")
def examples(dolphin: PhysicalModel) -> sampling.Examples:
    return sampling.generate(dolphin, 50, 48, seed=3, progress=False)


def make(model: PhysicalModel, seed: int = 0) -> HierarchicalEmulator:
    """A hierarchy with random weights and random normalisation statistics (nothing cancels)."""
    torch.manual_seed(seed)
    emu = HierarchicalEmulator(model.layout, model.num_controls, model.spec.parts, (16,), (12,), skip=True)
    with torch.no_grad():
        for _, net in emu.networks:
            for buf in (net.x_mean, net.y_mean):
                buf.normal_(0.0, 0.1)
            for buf in (net.x_std, net.y_std):
                buf.uniform_(0.5, 2.0)
            net.y_std.mul_(0.01)
    return emu.eval()


def tensors(ex: sampling.Examples) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (
        torch.from_numpy(ex.states).double(),
        torch.from_numpy(ex.controls).double(),
        torch.from_numpy(ex.next_states).double(),
    )


def test_networks_that_predict_no_change_give_the_identity(
    dolphin: PhysicalModel, examples: sampling.Examples
) -> None:
    emu = make(dolphin).double()
    with torch.no_grad():
        for _, net in emu.networks:
            for p in net.parameters():
                p.zero_()
            net.y_mean.zero_()
        s, u, _ = tensors(examples)
        assert torch.allclose(emu(s, u), s, atol=1e-9)


def test_the_hierarchy_is_the_composition_of_its_networks(
    dolphin: PhysicalModel, examples: sampling.Examples
) -> None:
    emu = make(dolphin).double()
    s, u, _ = tensors(examples)
    with torch.no_grad():
        out = emu(s, u)
        frames = emu.frames_of(s)
        # stage 1: the global network on the frames, centres relative to their mean
        rel, _ = emu.global_inputs(s, s)
        shift = frames - rel
        next_frames = emu.glob(rel, u) + shift
        assert torch.allclose(emu.global_step(s, u), next_frames)
        # stage 2: each part's network, read back from the output in the predicted next frame
        covered = torch.zeros(s.shape[1], dtype=torch.bool)
        for k, (name, net) in enumerate(emu.networks[1:]):
            part_state, frame_in = emu.local_inputs(k, s, next_frames)
            predicted = net(part_state, u, frame_in)
            m = emu.part_map(k)
            assert torch.allclose(m.to_local(out, next_frames), predicted, atol=1e-9), name
            cols = m.pick.sum(dim=1) > 0
            assert not (covered & cols).any()
            covered |= cols
        assert covered.all()


def test_local_targets_map_back_to_the_next_state(
    dolphin: PhysicalModel, examples: sampling.Examples
) -> None:
    emu = make(dolphin).double()
    _, _, nxt = tensors(examples)
    with torch.no_grad():
        frames = emu.frames_of(nxt)
        back = sum(emu.part_map(k).to_world(emu.local_target(k, nxt), frames) for k in range(len(emu.parts)))
    assert isinstance(back, torch.Tensor)
    assert torch.allclose(back, nxt, atol=1e-9)


def test_moving_the_body_moves_the_prediction(dolphin: PhysicalModel, examples: sampling.Examples) -> None:
    emu = make(dolphin).double()
    s, u, _ = tensors(examples)
    move = torch.zeros(s.shape[1], dtype=torch.float64)
    for g, sl in dolphin.layout.group_slices():
        if g.name.endswith(".pos"):
            move[sl] = torch.tensor([3.0, -2.0, 0.5], dtype=torch.float64)
    with torch.no_grad():
        assert torch.allclose(emu(s + move, u), emu(s, u) + move, atol=1e-8)


def test_the_onnx_graph_equals_torch(dolphin: PhysicalModel, examples: sampling.Examples) -> None:
    emu = make(dolphin)
    onnx = OnnxEmulator(to_onnx(emu))
    assert onnx.input_names == ["state", "controls"] and onnx.state_size == dolphin.state_size
    s, u = examples.states.astype(np.float32), examples.controls.astype(np.float32)
    with torch.no_grad():
        expected = emu(torch.from_numpy(s), torch.from_numpy(u)).numpy()
    got = onnx.step(s, u)
    np.testing.assert_allclose(got, expected, atol=2e-5, rtol=1e-4)
    assert np.abs(got - s).max() > 1e-3  # the networks do change the state


def test_parts_must_partition_the_state(dolphin: PhysicalModel) -> None:
    parts = list(dolphin.spec.parts)
    with pytest.raises(ValueError, match="every state group once"):
        check_parts(dolphin.layout, parts[:-1])
    bad = parts[0].model_copy(update={"centre": [1.0] * len(parts[0].points)})
    with pytest.raises(ValueError, match="summing to 1"):
        check_parts(dolphin.layout, [bad, *parts[1:]])
