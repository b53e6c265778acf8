"""``export.driven``: a policy and its emulator composed into one ONNX graph give what the two give
called in turn, the controls clipped to the emulator's range; graphs that do not fit are refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from neuroanimator.artifacts import registry
from neuroanimator.export.driven import DrivenStep, compose_driven
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
