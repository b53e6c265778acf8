"""``export.driven``: a policy and its emulator composed into one ONNX graph give what the two give
called in turn, the controls clipped to the emulator's range; graphs that do not fit are refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from neuroanimator.artifacts import registry
from neuroanimator.export.driven import CONTROLS_RANGE, DrivenStep, compose_driven
from neuroanimator.export.runtime import OnnxEmulator

ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"


def _emulator() -> Path:
    return registry.resolve(ARTIFACTS, "lander", substeps=25) / registry.ONNX_FILE


def _policy(state_size: int, controls: int, timed: bool) -> bytes:
    """A policy graph ``controls = 3 tanh([state, goal(, time_left)] W)``: controls beyond ±0.5, so
    that the composed step's clip shows."""
    names = ["state", "goal", "time_left"] if timed else ["state", "goal"]
    widths = [state_size, 2, 1][: len(names)]
    w = np.random.default_rng(0).normal(size=(sum(widths), controls)).astype(np.float32)
    graph = helper.make_graph(
        [
            helper.make_node("Concat", names, ["x"], axis=1),
            helper.make_node("MatMul", ["x", "w"], ["y"]),
            helper.make_node("Tanh", ["y"], ["t"]),
            helper.make_node("Mul", ["t", "three"], ["controls"]),
        ],
        "policy",
        [
            helper.make_tensor_value_info(n, TensorProto.FLOAT, ["batch", k])
            for n, k in zip(names, widths, strict=True)
        ],
        [helper.make_tensor_value_info("controls", TensorProto.FLOAT, ["batch", controls])],
        [numpy_helper.from_array(w, "w"), numpy_helper.from_array(np.array(3.0, np.float32), "three")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8  # (what ONNX Runtime reads; the onnx package writes newer by default)
    return model.SerializeToString()


@pytest.mark.parametrize("timed", [False, True])
def test_the_composed_step_is_the_policy_then_the_emulator(timed: bool) -> None:
    emu = OnnxEmulator(_emulator())
    policy = _policy(emu.state_size, emu.num_controls, timed)
    low, high = np.full(emu.num_controls, -0.5, np.float32), np.full(emu.num_controls, 0.5, np.float32)
    driven = DrivenStep(compose_driven(policy, _emulator().read_bytes(), low, high))
    pol = ort.InferenceSession(policy, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    for b in (1, 7):
        state = rng.normal(size=(b, emu.state_size)).astype(np.float32)
        goal = rng.normal(size=(b, 2)).astype(np.float32)
        feed = {"state": state, "goal": goal}
        left = None
        if timed:
            left = feed["time_left"] = rng.uniform(0, 1, (b, 1)).astype(np.float32)
        want_u = np.clip(pol.run(None, feed)[0], low, high)
        assert np.any(want_u == low) or np.any(want_u == high)  # the clip mattered
        u, nxt = driven.run(state, goal, left)
        np.testing.assert_allclose(u, want_u, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(nxt, emu.step(state, want_u), rtol=1e-5, atol=1e-5)
    if timed:
        with pytest.raises(ValueError, match="time_left"):
            driven.run(state, goal)


def test_graphs_that_do_not_fit_are_refused() -> None:
    emu = _emulator().read_bytes()
    with pytest.raises(ValueError, match=r"policy's outputs are \['next_state'\]"):
        compose_driven(emu, emu, [0.0], [1.0])  # an emulator in the policy's place
    with pytest.raises(ValueError, match="reading 'state' and 'controls'"):
        compose_driven(_policy(13, 4, False), _policy(13, 4, False), [0.0], [1.0])  # and a policy in its


def _declared(policy: bytes, low: float, high: float, controls: int) -> bytes:
    """The policy graph with ``CONTROLS_RANGE`` metadata declaring its controls within [low, high]."""
    model = onnx.load_from_string(policy)
    entry = model.metadata_props.add()
    entry.key, entry.value = CONTROLS_RANGE, json.dumps([[low] * controls, [high] * controls])
    return model.SerializeToString()


def test_a_policy_declaring_its_controls_within_the_range_is_not_clipped_and_one_beyond_still_is() -> None:
    """A policy's own graph may say its controls never leave a range (a squashed output): the composed
    step then has no clip of its own; a declaration wider than the emulator's range keeps the clip."""
    emu = OnnxEmulator(_emulator())
    u = emu.num_controls
    low, high = np.full(u, -3.0, np.float32), np.full(u, 3.0, np.float32)
    rng = np.random.default_rng(1)
    state = rng.normal(size=(5, emu.state_size)).astype(np.float32)
    goal = rng.normal(size=(5, 2)).astype(np.float32)
    within = compose_driven(
        _declared(_policy(emu.state_size, u, False), -3, 3, u), _emulator().read_bytes(), low, high
    )
    ops = [n.op_type for n in onnx.load_from_string(within).graph.node]
    assert "Max" not in ops and "Min" not in ops
    beyond = compose_driven(
        _declared(_policy(emu.state_size, u, False), -3, 3, u), _emulator().read_bytes(), low / 6, high / 6
    )
    controls, _ = DrivenStep(beyond).run(state, goal)
    assert controls.max() <= 0.5 and controls.min() >= -0.5 and np.any(np.abs(controls) == 0.5)
    plain, _ = DrivenStep(within).run(state, goal)
    pol = ort.InferenceSession(_policy(emu.state_size, u, False), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(plain, pol.run(None, {"state": state, "goal": goal})[0], rtol=1e-6, atol=1e-6)


def test_an_exported_policy_declares_the_range_its_controls_keep() -> None:
    """``policy_to_onnx`` writes a ``PolicyNet``'s output range (its useful range within the hard
    limits), and the controls of random inputs stay inside it."""
    from neuroanimator.control.policy_store import load_policy_net
    from neuroanimator.export.policy import policy_to_onnx

    folder = ARTIFACTS / "policies" / "lander" / "lander-landing"
    net = load_policy_net(folder / (folder / "latest").read_text().strip())
    s = net.shape
    graph = policy_to_onnx(net, s.state_size, s.goal_size, s.timed)
    meta = {e.key: e.value for e in onnx.load_from_string(graph).metadata_props}
    lows, highs = (np.array(v) for v in json.loads(meta[CONTROLS_RANGE]))
    np.testing.assert_allclose(lows, np.maximum(s.low, s.limit_low))
    np.testing.assert_allclose(highs, np.minimum(s.high, s.limit_high))
    rng = np.random.default_rng(2)
    feed = {
        "state": rng.normal(0, 50, (256, s.state_size)).astype(np.float32),
        "goal": rng.normal(0, 50, (256, s.goal_size)).astype(np.float32),
        "time_left": rng.uniform(0, 1, (256, 1)).astype(np.float32),
    }
    out = ort.InferenceSession(graph, providers=["CPUExecutionProvider"]).run(None, feed)[0]
    slack = 1e-6 * np.maximum(1, highs - lows)
    assert np.all(out >= lows - slack) and np.all(out <= highs + slack)
