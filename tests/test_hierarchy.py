"""Hierarchical emulators (thesis 4.4): the composition of a global and local networks, its ONNX graph."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.core.manifest import ManifestError, parse_manifest
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.hierarchy import (
    LOCAL_FRAME_INPUTS,
    VECTORS,
    HierarchicalEmulator,
    check_parts,
    neighbour_inputs,
)
from neuroanimator.emulator.regularizer import regularization
from neuroanimator.export.onnx import to_onnx
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.export.stacked import StackedStep
from neuroanimator.sim import sampling
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.hierarchy import (
    HierarchyResult,
    drifted,
    group_scale,
    network_data,
    small_defaults,
    train_hierarchy,
)
from services.emulator.registry import Registry as ServiceRegistry


@pytest.fixture(scope="module")
def dolphin() -> PhysicalModel:
    return catalog.get("dolphin")


@pytest.fixture(scope="module")
def examples(dolphin: PhysicalModel) -> sampling.Examples:
    return sampling.generate(dolphin, 50, 48, seed=3, progress=False)


def make(
    model: PhysicalModel, seed: int = 0, local_hidden: tuple[int, ...] = (12,), skip: bool = True
) -> HierarchicalEmulator:
    """A hierarchy with random weights and random normalisation statistics (nothing cancels)."""
    torch.manual_seed(seed)
    emu = HierarchicalEmulator(
        model.layout, model.num_controls, model.spec.parts, (16,), local_hidden, skip=skip
    )
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


@pytest.mark.parametrize(("local_hidden", "skip"), [((12,), True), ((10, 8), False)])
def test_the_stacked_step_is_the_hierarchy(
    dolphin: PhysicalModel, examples: sampling.Examples, local_hidden: tuple[int, ...], skip: bool
) -> None:
    """The exported form (parts stacked, normalisation folded, regulariser feature-major) computes
    the same step as the torch composition, with one hidden layer and a linear path or two and none."""
    emu = make(dolphin, local_hidden=local_hidden, skip=skip)
    emu.regularizer = regularization(dolphin.layout, dolphin.spec.regularizer, dolphin.num_controls, 5)
    assert emu.regularizer is not None
    emu = emu.double()
    s, u, _ = tensors(examples)
    s = s + 0.05 * torch.randn_like(s)  # off the data too: every column and every part moves
    with torch.no_grad():
        expected, got = emu(s, u), StackedStep(emu)(s, u)
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, expected, atol=1e-10, rtol=1e-10)
    assert (expected - s).abs().max() > 1e-2


def test_the_onnx_graph_does_not_grow_with_the_parts(dolphin: PhysicalModel) -> None:
    """Six local networks cost about as many graph nodes as one: what a call at batch 1 pays for."""
    import onnx

    graph = onnx.load_from_string(to_onnx(make(dolphin))).graph
    computing = [n for n in graph.node if n.op_type != "Constant"]
    matmuls = [n for n in computing if n.op_type in ("MatMul", "Gemm")]
    assert len(computing) < 150, len(computing)  # one part's maps and network alone took about 140
    assert len(matmuls) <= 8, [n.name for n in matmuls]


def test_parts_must_partition_the_state(dolphin: PhysicalModel) -> None:
    parts = list(dolphin.spec.parts)
    with pytest.raises(ValueError, match="every state group once"):
        check_parts(dolphin.layout, parts[:-1])
    bad = parts[0].model_copy(update={"centre": [1.0] * len(parts[0].points)})
    with pytest.raises(ValueError, match="summing to 1"):
        check_parts(dolphin.layout, [bad, *parts[1:]])


def test_a_part_reads_the_points_it_is_attached_to(dolphin: PhysicalModel) -> None:
    parts = {p.name: p for p in dolphin.spec.parts}
    # segment 2's springs reach the head's section 1 and segment 3's section 3, and nothing further
    near = {pos.split(".")[0] for pos, _ in parts["segment2"].neighbours}
    assert near == {f"s{k}{c}" for k in (1, 3) for c in ("tl", "tr", "bl", "br")}
    assert {pos.split(".")[0] for pos, _ in parts["fluke"].neighbours} == {"s5tl", "s5tr", "s5bl", "s5br"}
    others = list(parts.values())
    own = parts["head"].model_copy(update={"neighbours": [parts["head"].points[0]]})
    with pytest.raises(ValueError, match="its own"):
        check_parts(dolphin.layout, [own, *others[1:]])
    stranger = parts["head"].model_copy(update={"neighbours": [("strip1_tl.pitch", "strip1_tl.rate")]})
    with pytest.raises(ValueError, match="other parts' points"):
        check_parts(dolphin.layout, [stranger, *others[1:]])


def test_a_neighbour_moves_the_part_it_is_attached_to(
    dolphin: PhysicalModel, examples: sampling.Examples
) -> None:
    """Segment 2's network reads section 3's nodes: moving one of them changes segment 2's next
    state (it would not if only the part's own groups were read), and nothing is read in world axes:
    turning the whole body about the vertical turns the neighbour inputs' frame with it."""
    emu = make(dolphin).double()
    s, _, _ = tensors(examples)
    k = [p.name for p in dolphin.spec.parts].index("segment2")
    with torch.no_grad():
        frames = emu.frames_of(s)
        _, inputs = emu.local_inputs(k, s, frames)
        nudged = s.clone()
        nudged[:, dolphin.layout.slice_of("s3tl.pos")] += torch.tensor(
            [0.03, -0.04, 0.05], dtype=torch.float64
        )
        _, nudged_inputs = emu.local_inputs(k, nudged, emu.frames_of(nudged))
        changed = ((nudged_inputs - inputs).abs().amax(dim=0) > 1e-9).nonzero().flatten().tolist()
        at = 3 * len(LOCAL_FRAME_INPUTS) + 3 * neighbour_inputs(dolphin.spec.parts[k]).index("near.s3tl.pos")
        assert changed == [at, at + 1, at + 2]  # the one neighbour position, in segment 2's axes
        # a quarter turn about z of every position and velocity leaves the part's inputs as they were
        turn = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        turned = s.clone()
        for g, sl in dolphin.layout.group_slices():
            if g.name.endswith((".pos", ".vel")):
                turned[:, sl] = s[:, sl] @ turn.T
        _, turned_inputs = emu.local_inputs(k, turned, emu.frames_of(turned))
        torch.testing.assert_close(turned_inputs, inputs)


def test_a_column_that_never_changes_takes_its_groups_scale(dolphin: PhysicalModel) -> None:
    """A body that moves only in its plane never changes its nodes' y: the composed step's error is
    scaled by the group's spread there, not divided by nothing."""
    change = torch.randn(
        200, dolphin.state_size, dtype=torch.float64, generator=torch.Generator().manual_seed(0)
    )
    sl = dolphin.layout.slice_of("s2tl.pos")
    change[:, sl.start + 1] = 0.0  # y
    change[:, sl.start] *= 3.0
    scale = group_scale(dolphin, change)
    expected = change[:, sl].std(dim=0).pow(2).mean().sqrt()
    torch.testing.assert_close(scale[sl], expected.expand(3))
    assert float(scale.min()) > 0.1


def test_drifted_states_move_each_group_by_its_share_of_a_step(
    dolphin: PhysicalModel, examples: sampling.Examples
) -> None:
    """``--state-noise``: each training state moves by about the asked share of its group's change
    over a super-step (its own scale: metres for a node, radians for a plate), the next states stay."""
    s, _, nxt = tensors(examples)
    moved = drifted(dolphin, s, nxt, 0.1, seed=0)
    scale = group_scale(dolphin, nxt - s)
    ratio = ((moved - s) / scale).std(dim=0)  # (S,) about 0.1 everywhere
    assert float(ratio.min()) > 0.07 and float(ratio.max()) < 0.13, ratio
    torch.testing.assert_close(drifted(dolphin, s, nxt, 0.1, seed=0), moved)  # the same for a seed
    assert not torch.equal(drifted(dolphin, s, nxt, 0.1, seed=1), moved)


TINY = TrainConfig(
    substeps=50,
    hidden=(8,),
    branch_hidden=(6,),  # the parts' networks narrower than the global one, as the committed dolphin's
    examples=160,
    test_examples=64,
    max_epochs=3,
    max_seconds=5.0,
    rollout_steps=0,
    regularizer_steps=5,  # not the dolphin's default (2): to check the number asked is saved and served
    progress=False,
    threads=1,
)


@pytest.fixture(scope="module")
def trained(dolphin: PhysicalModel) -> HierarchyResult:
    return train_hierarchy(dolphin, TINY)


def test_a_hierarchy_keeps_its_data_in_the_cache_and_reads_them_back(
    tmp_path: Path, dolphin: PhysicalModel, caplog: pytest.LogCaptureFixture
) -> None:
    """A second training of the dolphin (minutes of simulation at full size) reads the examples that
    the first one kept, and trains on the same ones."""
    cfg = dataclasses.replace(TINY, examples=48, test_examples=16, max_epochs=1)
    first = train_hierarchy(dolphin, cfg, data_cache=tmp_path)
    kept = sorted(p.name for p in tmp_path.glob("*.npz"))
    assert len(kept) == 2 and all(name.startswith("dolphin-examples-n50-") for name in kept), kept
    with caplog.at_level(logging.INFO, logger="neuroanimator.training.data_cache"):
        again = train_hierarchy(dolphin, cfg, data_cache=tmp_path)
    assert caplog.text.count("read from") == 2
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == kept
    assert again.metrics["network_errors"]["global"]["linear_baseline_rel_error"] == pytest.approx(
        first.metrics["network_errors"]["global"]["linear_baseline_rel_error"]
    )


def test_each_network_is_trained_on_its_own_targets(trained: HierarchyResult) -> None:
    m = trained.metrics
    names = [name for name, _ in trained.emulator.networks]
    assert names == ["global", "head", "segment2", "segment3", "segment4", "segment5", "fluke"]
    widths = {name: tuple(net.hidden) for name, net in trained.emulator.networks}
    assert widths.pop("global") == (8,) and set(widths.values()) == {(6,)}
    assert sorted(m["network_errors"]) == sorted(names)
    worst = max(e["one_step_rel_error"] for e in m["network_errors"].values())
    assert m["one_step_rel_error"] == worst
    # a budget of seconds proves the mechanics, not the accuracy (that is bench work)
    assert all(np.isfinite(e["linear_baseline_rel_error"]) for e in m["network_errors"].values())
    assert np.isfinite(worst) and np.isfinite(m["composed_rel_error"])


def test_a_saved_hierarchy_is_described_loaded_and_served(
    tmp_path: Path, dolphin: PhysicalModel, trained: HierarchyResult, examples: sampling.Examples
) -> None:
    path = artifacts.save(tmp_path, dolphin, trained)
    manifest = registry.read_manifest(path)
    graph = manifest.emulator
    assert graph.stages == [["global"], [p.name for p in dolphin.spec.parts]]
    assert [p.name for p in graph.parts] == [p.name for p in dolphin.spec.parts]
    glob, head = graph.networks[0], graph.networks[1]
    assert glob.frame.part is None and len(glob.writes) == 6 * len(graph.parts)
    assert head.frame.part == "head" and head.reads.predicted == [f"head.{q}" for q in VECTORS]
    assert head.writes == list(dolphin.spec.parts[0].groups)
    near = [g for pt in dolphin.spec.parts[0].neighbours for g in pt]
    assert near and head.reads.state == [*head.writes, *near]
    assert sorted(graph.written) == sorted(g.name for g in manifest.layout)
    assert manifest.io.inputs == ["state", "controls"]
    # the spring regulariser is part of the step, its Euler steps in the manifest (thesis 6.1.3)
    assert graph.regularizer is not None and graph.regularizer.steps == 5
    assert trained.emulator.regularizer is not None
    regularized = trained.metrics["composed_regularized_rel_error"]
    assert regularized is not None and np.isfinite(regularized)
    with pytest.raises(ManifestError, match="composed of 7 networks"):
        graph.only()
    data = json.loads((path / registry.MANIFEST_FILE).read_text())
    data["emulator"]["stages"].reverse()  # the parts before the frames they read
    with pytest.raises(ManifestError, match="which no earlier stage writes"):
        parse_manifest(data)

    loaded = artifacts.load_emulator(path)
    s, u = examples.states.astype(np.float32), examples.controls.astype(np.float32)
    with torch.no_grad():
        expected = trained.emulator(torch.from_numpy(s), torch.from_numpy(u)).numpy()
        torch.testing.assert_close(loaded(torch.from_numpy(s), torch.from_numpy(u)).numpy(), expected)
    # the emulator service loads it by the registry and ONNX only, as any model
    served = ServiceRegistry(tmp_path).get("dolphin")
    assert served.manifest.version == path.name
    # float32 both, summed in another order (the stacked graph): 3e-5 seen on plate pitch rates of 0.5 rad/s
    np.testing.assert_allclose(served.emulator.step(s, u), expected, atol=5e-5, rtol=1e-4)


def test_a_saved_hierarchy_is_evaluated_network_by_network(
    tmp_path: Path, dolphin: PhysicalModel, trained: HierarchyResult, examples: sampling.Examples
) -> None:
    """``neuro eval`` of a hierarchy: every network on fresh held-out data beside a linear fit of the
    same inputs; the emulator's one-step error is its worst network's."""
    from neuroanimator.evaluation import evaluate as evaluation

    path = artifacts.save(tmp_path, dolphin, trained)
    each = evaluation.hierarchy_one_step_errors(path, dolphin, examples)
    assert list(each) == [name for name, _ in trained.emulator.networks]
    for e in each.values():
        assert np.isfinite(e["one_step_rel_error"]) and np.isfinite(e["linear_baseline_rel_error"])
    # a linear fit to the very data it is scored on does at least as well as the global one saved
    assert (
        each["global"]["linear_baseline_rel_error"]
        <= trained.metrics["network_errors"]["global"]["linear_baseline_rel_error"] * 1.5
    )
    errs = evaluation.one_step_errors(path, dolphin, registry.read_manifest(path), count=64)
    assert errs["one_step_rel_error"] > 0 and set(errs) == {"one_step_rel_error", "linear_baseline_rel_error"}


def test_training_over_rollouts_goes_through_the_composed_step_and_the_regulariser(
    dolphin: PhysicalModel, examples: sampling.Examples
) -> None:
    """The rollout phase fine-tunes every network through the step as served (global network, local
    networks on its predicted frames, the regulariser): from random networks the rollout loss falls."""
    from neuroanimator.training.hierarchy_rollouts import composed_rollout_loss, train_hierarchy_over_rollouts

    emu = make(dolphin, seed=3)
    emu.regularizer = regularization(dolphin.layout, dolphin.spec.regularizer, dolphin.num_controls, 5)
    seq = sampling.generate_sequences(dolphin, 50, 24, 2, seed=4, progress=False)
    s, u, nxt = (
        torch.from_numpy(a).float() for a in (examples.states, examples.controls, examples.next_states)
    )
    one_step = {}
    for (name, net), d in zip(emu.networks, network_data(emu, s, u, nxt), strict=True):
        with torch.no_grad():
            x, y = (
                net.network_inputs(d.state, d.controls, d.extra),
                net.network_targets(d.state, d.next_state),
            )
        one_step[name] = (x[8:], y[8:], x[:8], y[:8])
    change = torch.from_numpy(seq.states[:, 1:] - seq.states[:, :-1]).float()
    scale = group_scale(dolphin, change.reshape(-1, change.shape[2]))
    before = {k: v.clone() for k, v in emu.state_dict().items()}
    cfg = TrainConfig(rollout_seconds=10.0, max_epochs=15, lr=3e-2, batch_size=128, seed=1)
    m = train_hierarchy_over_rollouts(emu, seq, cfg, scale, one_step)
    assert m["rollout_epochs"] >= 1 and m["rollout_loss_after"] < 0.9 * m["rollout_loss_before"]
    with torch.no_grad():
        states, controls = torch.from_numpy(seq.states).float(), torch.from_numpy(seq.controls).float()
        assert float(composed_rollout_loss(emu, states[:2], controls[:2], scale)) > 0
    changed = [k for k, v in emu.state_dict().items() if not torch.equal(v, before[k])]
    assert any(k.startswith("glob.") for k in changed) and any(k.startswith("parts_nets.") for k in changed)


def test_a_hierarchy_trains_small_unless_told_otherwise() -> None:
    cfg = small_defaults(TrainConfig(), hidden_given=False, examples_given=False)
    assert (cfg.hidden, cfg.examples, cfg.test_examples, cfg.rollout_steps) == ((16,), 5_000, 1_000, 0)
    mine = TrainConfig(hidden=(50,), examples=123, test_examples=77, rollout_steps=16)
    cfg = small_defaults(mine, hidden_given=True, examples_given=True, rollout_given=True)
    assert (cfg.hidden, cfg.examples, cfg.test_examples, cfg.rollout_steps) == ((50,), 123, 77, 16)
