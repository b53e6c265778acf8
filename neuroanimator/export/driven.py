"""A policy and its emulator as ONE ONNX graph: the driven super-step of a served session.

``compose_driven`` wires a policy ``π(state, goal[, time_left]) → controls`` into its emulator
``(state, controls[, forces]) → next state``: the graph reads the state once, clips the policy's
controls to the emulator's trained range (what a separate call would do between the two) and gives
both the controls and the next state. ``DrivenStep`` runs it: one ONNX Runtime call per tick of
policy-driven sessions instead of two, which at small batches halves the calls' fixed cost (a batch
of one: about 150 µs for the two calls against 150 for the one, in ``bench/driven_step.py``).

Torch-free, like ``export.runtime``: the emulator service composes the graphs it has loaded.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np
import onnx
import onnx.compose
import onnxruntime as ort
from numpy.typing import NDArray

from neuroanimator.core.quaternion import wrap_angle
from neuroanimator.export.runtime import PerThreadRow, session_options

CONTROLS = "driven/controls"  # the composed graph's outputs: the clipped controls and the next state
EMULATOR_PREFIX = "emulator/"
CONTROLS_RANGE = (
    "controls_range"  # a policy graph's metadata: JSON [lows, highs] (U,) its controls never leave
)


def _opsets(*models: onnx.ModelProto) -> list[onnx.OperatorSetIdProto]:
    """Each domain at the highest version any of the models imports."""
    versions: dict[str, int] = {}
    for m in models:
        for o in m.opset_import:
            versions[o.domain] = max(o.version, versions.get(o.domain, 0))
    return [onnx.helper.make_opsetid(d, v) for d, v in versions.items()]


def declared_range(meta: dict[str, str]) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The (U,) lows and highs a policy graph's metadata (``CONTROLS_RANGE``) says its controls never
    leave; None where it says nothing."""
    if CONTROLS_RANGE not in meta:
        return None
    lows, highs = (np.asarray(v, np.float64) for v in json.loads(meta[CONTROLS_RANGE]))
    return lows, highs


def keeps_within(
    declared: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
    low: NDArray[np.floating],
    high: NDArray[np.floating],
) -> bool:
    """Whether controls within ``declared`` stay within [low, high] (U,), so that no clip is needed
    (a float32 rounding's slack allowed: the squashing's ends may land one unit in the last place out)."""
    if declared is None:
        return False
    lows, highs = declared
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    slack = 1e-6 * np.maximum(1.0, np.abs(high - low))
    return bool(lows.shape == low.shape and np.all(lows >= low - slack) and np.all(highs <= high + slack))


def compose_driven(
    policy: bytes,
    emulator: bytes,
    low: Sequence[float] | NDArray[np.floating],
    high: Sequence[float] | NDArray[np.floating],
) -> bytes:
    """The driven step's graph: inputs ``state`` (B,S), ``goal`` (B,G)[, ``time_left`` (B,1)] and
    the emulator's ``forces`` if it takes any (named ``emulator/forces``); outputs ``CONTROLS``
    (B,U), the policy's controls clipped to [low, high] (U,), and the emulator's next state (B,S)
    (``EMULATOR_PREFIX`` + its output's name). ``ValueError`` when the two do not fit together."""
    p, e = onnx.load_from_string(policy), onnx.load_from_string(emulator)
    p_in = {i.name: i for i in p.graph.input}
    e_in = {i.name for i in e.graph.input}
    if "state" not in p_in or "state" not in e_in or "controls" not in e_in:
        raise ValueError(
            "a driven step needs a policy reading 'state' and an emulator reading 'state' and 'controls'"
        )
    if [o.name for o in p.graph.output] != ["controls"]:
        raise ValueError(f"the policy's outputs are {[o.name for o in p.graph.output]}, not ['controls']")
    lo = np.asarray(low, np.float32)[None]
    hi = np.asarray(high, np.float32)[None]
    declared = declared_range({e.key: e.value for e in p.metadata_props})
    if keeps_within(declared, lo[0], hi[0]):  # the policy's controls never leave the range: no clip
        p.graph.node.append(onnx.helper.make_node("Identity", ["controls"], [CONTROLS]))
    else:
        p.graph.initializer.extend(
            [onnx.numpy_helper.from_array(lo, "driven/low"), onnx.numpy_helper.from_array(hi, "driven/high")]
        )
        p.graph.node.extend(
            [
                onnx.helper.make_node("Max", ["controls", "driven/low"], ["driven/above_low"]),
                onnx.helper.make_node("Min", ["driven/above_low", "driven/high"], [CONTROLS]),
            ]
        )
    # the emulator reads the state the policy read: pass it through the policy's graph
    p.graph.node.append(onnx.helper.make_node("Identity", ["state"], ["driven/state"]))
    state_out = onnx.ValueInfoProto()
    state_out.CopyFrom(p_in["state"])
    state_out.name = "driven/state"
    controls_out = onnx.ValueInfoProto()
    controls_out.CopyFrom(p.graph.output[0])
    controls_out.name = CONTROLS
    del p.graph.output[:]
    p.graph.output.extend([controls_out, state_out])
    p.ir_version = e.ir_version = max(p.ir_version, e.ir_version)
    opsets = _opsets(p, e)
    for m in (p, e):
        del m.opset_import[:]
        m.opset_import.extend(opsets)
    merged = onnx.compose.merge_models(
        p,
        e,
        io_map=[(CONTROLS, "controls"), ("driven/state", "state")],
        prefix2=EMULATOR_PREFIX,
        outputs=[CONTROLS, EMULATOR_PREFIX + e.graph.output[0].name],
    )
    onnx.checker.check_model(merged)
    return merged.SerializeToString()


class DrivenStep:
    """The composed graph in an ONNX Runtime session: ``run(state (B,S), goal (B,G), time_left
    (B,1) | None, forces (B,F) | None) → (controls (B,U), next state (B,S))``, the ``wrap`` columns
    of the next state wrapped to [-π, π) as ``OnnxEmulator.step`` wraps them."""

    def __init__(self, model: bytes, threads: int = 1, wrap: Sequence[int] = ()) -> None:
        self.session = ort.InferenceSession(
            model, session_options(threads), providers=["CPUExecutionProvider"]
        )
        self.wrap = list(wrap)
        self.widths = {i.name: int(i.shape[1]) for i in self.session.get_inputs()}
        self.outputs = {o.name: int(o.shape[1]) for o in self.session.get_outputs()}
        self.forces = EMULATOR_PREFIX + "forces"
        self.calls = 0  # ONNX Runtime calls made (tests compare them with ticks)
        self._row = PerThreadRow(self.session, self.widths, self.outputs)

    def run(
        self,
        state: NDArray[np.float32],
        goal: NDArray[np.float32],
        time_left: NDArray[np.float32] | None = None,
        forces: NDArray[np.float32] | None = None,
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        feed = {"state": state, "goal": goal}
        for name, values in (("time_left", time_left), (self.forces, forces)):
            if name in self.widths:
                if values is None:
                    raise ValueError(f"this driven step reads {name!r}")
                feed[name] = values
        self.calls += 1
        if len(state) == 1:
            controls, nxt = self._row.run(feed)
        else:
            controls, nxt = self.session.run(list(self.outputs), feed)
        if self.wrap:
            nxt[:, self.wrap] = wrap_angle(nxt[:, self.wrap])
        return controls, nxt
