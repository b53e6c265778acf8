"""ONNX export of the *whole* structured step, and the ONNX Runtime session that serves it.

The graph's inputs are ``state`` (B, S) and, where the model has them, ``controls`` (B, U) and
``forces`` (B, F); its output is ``next_state`` (B, S). The batch axis is dynamic. Every transform
(local frame, normalisation, state change, quaternion renormalisation) is inside the graph.

PyTorch is imported only inside ``to_onnx``: a serving process that needs just ``OnnxEmulator``
and ``session_options`` (the emulator service) never loads it.
"""

from __future__ import annotations

import copy
import io
import threading
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from neuroanimator.quaternion import wrap_angle

if TYPE_CHECKING:
    from neuroanimator.hierarchy import HierarchicalEmulator
    from neuroanimator.structured import StructuredEmulator

    Emulator = StructuredEmulator | HierarchicalEmulator

OPSET = 17


def fold_normalization(emu: StructuredEmulator) -> Any:
    """A copy of the core (nn.Sequential) with T^σ_x folded into its first layer and T^σ_y into its last.

    (x - μ)/σ followed by W x + b is W' x + b' with W' = W / σ and b' = b - W' μ; likewise the
    output scaling. The input placement x = ext @ P folds in too (W'' = W' Pᵀ), so the first layer
    reads the unplaced local columns. The map is the same; the graph has five fewer nodes per call.
    """
    import torch
    from torch import nn

    class WithSkip(nn.Module):
        """The folded MLP plus the folded linear path: ``core(cols) + skip(cols)``."""

        def __init__(self, core: nn.Module, skip: nn.Module) -> None:
            super().__init__()
            self.core = core
            self.skip = skip

        def forward(self, cols: torch.Tensor) -> torch.Tensor:
            return self.core(cols) + self.skip(cols)

    from neuroanimator.articulated import NormalizedCore, articulated_core

    if articulated_core(emu) is not None:  # a composed core: its normalisation stays around it
        return NormalizedCore(emu)
    core = copy.deepcopy(emu.core)
    first, last = core[0], core[-1]
    assert isinstance(first, nn.Linear) and isinstance(last, nn.Linear)

    def fold_input(layer: nn.Linear) -> None:
        w = layer.weight / emu.x_std  # (H, D) / (D,)
        layer.bias.copy_(layer.bias - w @ emu.x_mean)
        placed = w @ emu.input_placement.T  # (H, E)
        layer.weight = nn.Parameter(placed)
        layer.in_features = placed.shape[1]

    with torch.no_grad():
        fold_input(first)
        last.weight.copy_(last.weight * emu.y_std[:, None])
        last.bias.copy_(last.bias * emu.y_std + emu.y_mean)
        if emu.skip is None:
            return core
        skip = copy.deepcopy(emu.skip)
        fold_input(skip)
        skip.weight.copy_(skip.weight * emu.y_std[:, None])
        skip.bias.copy_(skip.bias * emu.y_std)  # y_mean is added once, by the MLP's last layer
    return WithSkip(core, skip)


def _step_module(emu: StructuredEmulator) -> Any:
    """The exported step as an ``nn.Module``: the emulator's transforms around the folded core,
    with the call signature fixed to the inputs the model really has."""
    from torch import Tensor, nn

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
    local networks stacked (``hierarchy_export.StackedStep``), so the graph's size does not grow with
    the number of parts."""
    import torch
    from torch import Tensor

    from neuroanimator.hierarchy import HierarchicalEmulator
    from neuroanimator.hierarchy_export import StackedStep, stackable

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


def session_options(threads: int = 1) -> ort.SessionOptions:
    """ORT settings for a small model on CPU: few threads, no busy-waiting between calls."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


class _SingleRow:
    """A bound call for one row: ``state`` (1, S), ``controls`` (1, U), ``forces`` (1, F) copied into
    buffers that ONNX Runtime already holds, and ``next_state`` written into one it holds too.

    ``session.run`` wraps every input array in a new OrtValue and allocates the output on each call;
    at batch 1 that costs as much as the network itself (10–15 µs of 35–50). The binding is made once.
    """

    def __init__(self, session: ort.InferenceSession, widths: dict[str, int], output: str) -> None:
        self.inputs = {name: np.zeros((1, w), dtype=np.float32) for name, w in widths.items() if w}
        self.out = np.zeros((1, widths["state"]), dtype=np.float32)
        self.binding = session.io_binding()
        for name, buf in self.inputs.items():
            self.binding.bind_cpu_input(name, buf)
        self.binding.bind_output(output, "cpu", 0, np.float32, self.out.shape, self.out.ctypes.data)
        self.session = session

    def run(self, feed: dict[str, NDArray[np.float32]]) -> NDArray[np.float32]:
        for name, values in feed.items():
            np.copyto(self.inputs[name], values)
        self.session.run_with_iobinding(self.binding)
        return self.out.copy()  # the buffer is overwritten by the next call


class OnnxEmulator:
    """An emulator served by ONNX Runtime: ``step(state (B,S), controls (B,U), forces (B,F)) -> (B,S)``."""

    def __init__(self, model: bytes | str | Path, threads: int = 1, wrap: Sequence[int] = ()) -> None:
        """``wrap``: state columns (a ``heading``, ``state.heading_columns``) that each step reports
        wrapped to [-π, π)."""
        src = str(model) if isinstance(model, Path) else model
        self.wrap = list(wrap)
        self.session = ort.InferenceSession(src, session_options(threads), providers=["CPUExecutionProvider"])
        ins = {i.name: i for i in self.session.get_inputs()}
        self.input_names = list(ins)
        self.state_size = int(ins["state"].shape[1])
        self.num_controls = int(ins["controls"].shape[1]) if "controls" in ins else 0
        self.num_forces = int(ins["forces"].shape[1]) if "forces" in ins else 0
        self._output = self.session.get_outputs()[0].name
        self._local = threading.local()  # one single-row binding per thread that steps this emulator

    def step(
        self,
        state: NDArray[np.floating],
        controls: NDArray[np.floating] | None = None,
        forces: NDArray[np.floating] | None = None,
        *,
        validate: bool = True,
    ) -> NDArray[np.float32]:
        """One super-step for a batch. ``validate=False`` skips the checks on a hot path whose
        inputs were validated at its entry."""
        feed = {"state": np.ascontiguousarray(state, dtype=np.float32)}
        for name, values, width in (
            ("controls", controls, self.num_controls),
            ("forces", forces, self.num_forces),
        ):
            if width:
                if values is None:
                    raise ValueError(f"{name} are required: this emulator takes {width} {name}")
                feed[name] = np.ascontiguousarray(values, dtype=np.float32)
            elif values is not None and np.size(values):
                raise ValueError(f"this emulator takes no {name}, got {np.shape(values)}")
        if validate:
            self._validate(feed)
        one_row = feed["state"].shape[0] == 1
        out: NDArray[np.float32] = (
            self._single_row().run(feed) if one_row else self.session.run(None, feed)[0]
        )
        if self.wrap:
            out[:, self.wrap] = wrap_angle(out[:, self.wrap])
        return out

    def _single_row(self) -> _SingleRow:
        row: _SingleRow | None = getattr(self._local, "row", None)
        if row is None:
            widths = {"state": self.state_size, "controls": self.num_controls, "forces": self.num_forces}
            row = self._local.row = _SingleRow(self.session, widths, self._output)
        return row

    def _validate(self, feed: dict[str, NDArray[np.float32]]) -> None:
        widths = {"state": self.state_size, "controls": self.num_controls, "forces": self.num_forces}
        batch = feed["state"].shape[0] if feed["state"].ndim == 2 else None
        for name, arr in feed.items():
            if arr.ndim != 2 or arr.shape[1] != widths[name]:
                raise ValueError(f"{name} must have shape (batch, {widths[name]}), got {arr.shape}")
            if arr.shape[0] != batch:
                raise ValueError(f"{name} has {arr.shape[0]} rows but state has {batch}")
            if not np.isfinite(arr).all():
                raise ValueError(f"{name} must be finite; got NaN or Inf")

    def rollout(
        self,
        state: NDArray[np.floating],
        controls: NDArray[np.floating] | None = None,
        forces: NDArray[np.floating] | None = None,
        steps: int | None = None,
    ) -> NDArray[np.float32]:
        """Iterate the step: state (B,S), controls (B,M,U), forces (B,M,F) -> states (B, M+1, S)."""
        m = steps if steps is not None else (controls.shape[1] if controls is not None else 0)
        if forces is not None and steps is None:
            m = forces.shape[1]
        s = np.asarray(state, dtype=np.float32)
        out = np.empty((s.shape[0], m + 1, s.shape[1]), dtype=np.float32)
        out[:, 0] = s
        for k in range(m):
            u = controls[:, k] if controls is not None else None
            f = forces[:, k] if forces is not None else None
            s = self.step(s, u, f, validate=k == 0)  # later steps reuse checked shapes
            out[:, k + 1] = s
        return out
