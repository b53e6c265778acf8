"""ONNX export of the *whole* emulator step (``to_onnx``); ``export.runtime`` serves what it writes.

The graph's inputs are ``state`` (B, S) and, where the model has them, ``controls`` (B, U) and
``forces`` (B, F); its output is ``next_state`` (B, S). The batch axis is dynamic. Every transform
(local frame, normalisation, state change, quaternion renormalisation) is inside the graph.
"""

from __future__ import annotations

import io
import warnings
from typing import Any

import torch
from torch import Tensor, nn

from neuroanimator.emulator.folding import fold_normalization
from neuroanimator.emulator.hierarchy import HierarchicalEmulator
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.export.stacked import StackedStep, stackable

Emulator = StructuredEmulator | HierarchicalEmulator

OPSET = 17


def _step_module(emu: StructuredEmulator) -> Any:
    """The exported step as an ``nn.Module``: the emulator's transforms around the folded core,
    with the call signature fixed to the inputs the model really has."""

    class Step(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.emu = emu
            self.core = fold_normalization(emu)

        def forward(self, state: Tensor, *rest: Tensor) -> Tensor:
            it = iter(rest)
            u = next(it) if emu.num_controls else None
            f = next(it) if emu.num_forces else None
            frame = emu.local_frame(state)  # computed once, used by T'_x and T'_y
            cols = emu.local_inputs(state, u, f, frame, place=False)
            nxt = emu.apply_delta(state, self.core(cols), frame)
            return nxt if emu.regularizer is None else emu.regularizer(nxt, u)

    return Step()


def input_names(emu: Emulator) -> list[str]:
    names = ["state"]
    if emu.num_controls:
        names.append("controls")
    if emu.num_forces:
        names.append("forces")
    return names


def to_onnx(emu: Emulator) -> bytes:
    """Serialise the emulator's full step as an ONNX model (bytes). A hierarchical emulator is one graph
    too (global network, local networks, back to world values), with the same inputs and output; its
    local networks stacked (``export.stacked.StackedStep``), so the graph's size does not grow with
    the number of parts."""
    emu = emu.eval()
    b = 2
    args: list[Tensor] = [torch.zeros(b, emu.layout.size)]
    for sl in emu.quaternion_slices:
        args[0][:, sl.start] = 1.0  # identity quaternions for the trace
    if emu.num_controls:
        args.append(torch.zeros(b, emu.num_controls))
    if emu.num_forces:
        args.append(torch.zeros(b, emu.num_forces))
    names = input_names(emu)
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        if isinstance(emu, HierarchicalEmulator):  # the parts' networks stacked where they can be
            module = StackedStep(emu) if stackable(emu) else emu
        else:
            module = _step_module(emu)
        torch.onnx.export(
            module,
            tuple(args),
            buf,  # type: ignore[arg-type]  # a file-like object is accepted
            input_names=names,
            output_names=["next_state"],
            dynamic_axes={n: {0: "batch"} for n in [*names, "next_state"]},
            opset_version=OPSET,
            dynamo=False,
        )
    return buf.getvalue()
