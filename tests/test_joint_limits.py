"""Joint limits: a limited joint enters the network as ramps past its limits (structured.JointLimit)."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.structured import LIMIT_FRACTIONS, JointLimit, StructuredEmulator, limit_margin
from neuroanimator.export.onnx import to_onnx
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim import sampling
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.train import build_emulator, joint_limits, train
from tests.helpers import ARM_XML, RAIL_XML

MakeEmulator = Callable[..., StructuredEmulator]


def _model(xml: str, substeps: int = 10) -> PhysicalModel:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "model.xml"
        path.write_text(xml)
        return load_mjcf(path, substeps=substeps)


def _rail(substeps: int = 10) -> PhysicalModel:
    return _model(RAIL_XML, substeps)


def test_limited_joints_are_found_with_their_columns_and_range() -> None:
    model = _rail()
    (lim,) = joint_limits(model)  # the slider; the pole's hinge is not limited
    labels = model.layout.labels()
    assert labels[lim.position] == "slider.pos"
    assert lim.velocity is not None and labels[lim.velocity] == "slider.vel"
    assert (lim.low, lim.high) == (-0.5, 0.5)


def test_a_model_without_limits_reads_no_ramps() -> None:
    model = _model(ARM_XML)
    assert joint_limits(model) == []
    emu = build_emulator(model, TrainConfig(hidden=(8,), progress=False))
    assert "limits" not in dict(emu.input_groups)


def test_ramps_are_zero_inside_and_grow_past_each_limit() -> None:
    model = _rail(substeps=10)
    emu = build_emulator(model, TrainConfig(substeps=10, hidden=(8,), progress=False))  # horizon 0.1 s
    width = dict(emu.input_groups)["limits"]
    assert width == 2 * len(LIMIT_FRACTIONS)
    s = torch.zeros(4, model.state_size)
    labels = model.layout.labels()
    pos, vel = labels.index("slider.pos"), labels.index("slider.vel")
    s[1, pos] = 0.45  # inside, moving out fast enough to pass the limit within the super-step
    s[1, vel] = 1.0
    s[2, pos] = 0.55  # already past the high limit
    s[3, pos] = -0.45  # inside, moving away from the low limit
    s[3, vel] = 2.0
    u = torch.zeros(4, 1)
    ramps = emu.local_inputs(s, u, None)[:, -width:]
    k = len(LIMIT_FRACTIONS)
    past_high, past_low = ramps[:, :k], ramps[:, k:]
    assert torch.all(ramps[0] == 0) and torch.all(ramps[3] == 0)
    torch.testing.assert_close(past_high[1], torch.tensor([0.0, 0.0, 0.05]))  # 0.45 + 1.0·0.1 − 0.5
    torch.testing.assert_close(past_high[2], torch.full((k,), 0.05))
    assert torch.all(past_low == 0)


def test_onnx_graph_computes_the_same_ramps(make_emulator: MakeEmulator) -> None:
    model = _rail()
    emu = make_emulator(model, seed=3)
    assert emu.limits
    rng = np.random.default_rng(0)
    s = model.initial_states(rng, 32)
    s[:, model.layout.labels().index("slider.pos")] = rng.uniform(-0.6, 0.6, 32)  # both sides of each limit
    u = rng.uniform(-1, 1, (32, 1))
    with torch.no_grad():
        expected = emu(torch.from_numpy(s).float(), torch.from_numpy(u).float()).numpy()
    got = OnnxEmulator(to_onnx(emu)).step(s, u)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)


def test_the_margin_is_wider_than_any_pass_in_the_data() -> None:
    lim = JointLimit(0, 1, -0.5, 0.5)
    assert limit_margin(lim, torch.tensor([-0.2, 0.1, 0.4])) == pytest.approx(
        0.02
    )  # never past: 2% of the range
    assert limit_margin(lim, torch.tensor([-0.58, 0.0, 0.53])) == pytest.approx(
        1.5 * 0.08
    )  # the farthest pass


def test_a_predicted_position_stays_within_the_margin(make_emulator: MakeEmulator) -> None:
    """A prediction that would take a joint farther past its limit than the margin stops at the
    margin, in torch and in the ONNX graph; one that ends within it is left as predicted; without a
    margin (an artifact from before margins) nothing is bounded."""
    model = _rail()
    emu = make_emulator(model, seed=3)
    pos = model.layout.labels().index("slider.pos")
    last = emu.core[-1]
    assert isinstance(last, torch.nn.Linear)
    with torch.no_grad():  # a network that moves the slider by about +0.3 whatever the state
        last.weight.zero_()
        if emu.skip is not None:
            emu.skip.weight.zero_()
        bias = torch.zeros(model.state_size)
        bias[pos] = (0.3 - emu.y_mean[pos]) / emu.y_std[pos]
        last.bias.copy_(bias)
    s = np.zeros((3, model.state_size))
    s[:, pos] = [0.0, 0.4, -0.6]  # inside; pushed past the high limit; from past the low limit, inside
    u = np.zeros((3, 1))

    def step(e: StructuredEmulator) -> list[np.ndarray]:
        with torch.no_grad():
            torch_next = e(torch.from_numpy(s).float(), torch.from_numpy(u).float()).numpy()
        return [torch_next, OnnxEmulator(to_onnx(e)).step(s, u)]

    unbounded = step(emu)[0][1, pos]
    assert unbounded > 0.6
    states = torch.zeros(2, model.state_size)
    states[:, pos] = torch.tensor([0.52, -0.5])  # the data pass the high limit by 0.02: margin 0.03
    emu.set_limit_margins(states)
    assert emu.limits[0].margin == pytest.approx(0.03)
    for nxt in step(emu):
        moved = nxt[0, pos]  # from 0.0: the step the network predicts, well inside the range
        assert 0.2 < moved < 0.5
        assert nxt[1, pos] == pytest.approx(0.53, abs=1e-6)  # 0.4 + that step would pass 0.53: at the margin
        assert nxt[2, pos] == pytest.approx(-0.6 + moved, abs=1e-5)  # ends inside: as predicted


def test_limits_travel_through_the_manifest(tmp_path: Path) -> None:
    model = _rail()
    cfg = TrainConfig(substeps=10, examples=300, test_examples=50, hidden=(8,), max_epochs=2, progress=False)
    cfg.rollout_steps = 0
    path = artifacts.save(tmp_path, model, train(model, cfg))
    (net,) = registry.read_manifest(path).emulator.networks
    assert [(lim.low, lim.high, lim.horizon) for lim in net.limits] == [(-0.5, 0.5, pytest.approx(0.1))]
    (margin,) = [lim.margin for lim in net.limits]  # set from the training data
    assert margin is not None and 0.02 <= margin < 0.5
    back = artifacts.load_torch(path)
    assert [replace(lim, margin=None) for lim in back.limits] == list(build_emulator(model, cfg).limits)
    assert back.limits[0].margin == pytest.approx(margin) and back.horizon == pytest.approx(0.1)


def test_the_ramps_learn_a_cart_hitting_its_limit() -> None:
    """Trained the same way with and without the ramps, the emulator with them predicts the super-steps
    in which the cart hits the end of its rail better: the kink is given, not rounded off."""
    model = _rail(substeps=20)
    test = sampling.generate(model, 20, 1000, seed=99, progress=False)
    pos = model.layout.labels().index("slider.pos")
    hits = np.abs(test.next_states[:, pos]) > 0.45  # ended at (or pushed into) a limit
    assert hits.mean() > 0.05, "the typical motions must reach the limits for this test to say anything"
    errors = {}
    for limits in (True, False):
        cfg = TrainConfig(substeps=20, examples=4000, hidden=(32, 32), max_epochs=40, test_examples=200)
        cfg.progress, cfg.max_seconds = False, 600.0  # the same epochs for both, whatever the load
        cfg.limits, cfg.rollout_steps = limits, 0
        emu = train(model, cfg).emulator
        s = torch.from_numpy(test.states).float()
        u = torch.from_numpy(test.controls).float()
        with torch.no_grad():
            pred = emu(s, u).numpy()
        errors[limits] = float(np.abs(pred - test.next_states)[hits][:, pos].mean())
    assert errors[True] < 0.85 * errors[False], errors


@pytest.mark.parametrize("mode", ["group", "variable"])
def test_ramps_are_normalised_by_their_engaged_values(mode: str) -> None:
    """A ramp is zero in most rows: its normalisation keeps zero at zero and scales what is engaged to
    unit root mean square, rather than dividing by a deviation that the zeros make small (the runner's
    limit ramps reached 120 deviations that way)."""
    model = _rail(substeps=10)
    emu = build_emulator(model, TrainConfig(substeps=10, hidden=(8,), progress=False))
    rng = np.random.default_rng(0)
    s = torch.from_numpy(model.initial_states(rng, 2000)).float()
    labels = model.layout.labels()
    pos = labels.index("slider.pos")
    s[:, pos] = torch.linspace(-0.45, 0.45, 2000)  # inside the rail's ±0.5
    s[:20, pos] = 0.52 + 0.01 * torch.arange(20)  # a few past the upper limit
    u = torch.zeros(2000, model.num_controls)
    x_local = emu.local_inputs(s, u, None)
    emu.set_normalization(x_local, torch.randn(2000, model.state_size), mode)
    groups = dict(emu.input_groups)
    start = sum(w for name, w in emu.input_groups[: [n for n, _ in emu.input_groups].index("limits")])
    cols = slice(start, start + groups["limits"])
    x = emu.normalize_inputs(x_local)[:, cols]
    assert torch.all(emu.x_mean[cols] == 0)
    assert torch.all(x[x_local[:, cols] == 0] == 0)  # zero stays zero
    engaged = x[x_local[:, cols] != 0]
    if mode == "group":
        assert float(engaged.pow(2).mean().sqrt()) == pytest.approx(1.0, rel=1e-4)
    assert float(engaged.abs().max()) < 5  # not tens of deviations out
