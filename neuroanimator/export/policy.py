"""ONNX export of a policy: ``π(state (B,S), goal (B,G)[, time_left (B,1)]) → controls (B,U)``.

The graph is whatever module is given with that signature (``control.policy_net.PolicyNet``); the
batch axis is dynamic and ``time_left`` an input only for a timed policy. A module that knows the
range its controls never leave (``output_range()``) has it written in the graph's metadata
(``CONTROLS_RANGE``): a driven step composed from it then needs no clip of its own
(``export.driven``).
"""

from __future__ import annotations

import io
import json
import warnings

import onnx
import torch
from torch import Tensor, nn

from neuroanimator.export.driven import CONTROLS_RANGE
from neuroanimator.export.onnx import OPSET


class _Untimed(nn.Module):
    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, state: Tensor, goal: Tensor) -> Tensor:
        out: Tensor = self.net(state, goal, torch.zeros(state.shape[0], 1))
        return out


def policy_input_names(timed: bool) -> list[str]:
    return ["state", "goal", "time_left"] if timed else ["state", "goal"]


def policy_to_onnx(
    net: nn.Module, state_size: int, goal_size: int, timed: bool, reads_time: bool = True
) -> bytes:
    """The policy's ONNX graph (bytes); ``reads_time`` False: ``net`` is ``π(state, goal)`` already
    (a reward policy: ``goal`` its task's parameters, possibly none)."""
    net = net.eval()
    b = 2
    args: tuple[Tensor, ...] = (torch.zeros(b, state_size), torch.zeros(b, goal_size))
    module: nn.Module = net if timed or not reads_time else _Untimed(net)
    if timed:
        args = (*args, torch.zeros(b, 1))
    names = policy_input_names(timed)
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            args,
            buf,  # type: ignore[arg-type]  # a file-like object is accepted
            input_names=names,
            output_names=["controls"],
            dynamic_axes={n: {0: "batch"} for n in [*names, "controls"]},
            opset_version=OPSET,
            dynamo=False,
        )
    output_range = getattr(net, "output_range", None)
    if output_range is None:
        return buf.getvalue()
    graph = onnx.load_from_string(buf.getvalue())
    entry = graph.metadata_props.add()
    entry.key, entry.value = CONTROLS_RANGE, json.dumps(output_range())
    return graph.SerializeToString()
