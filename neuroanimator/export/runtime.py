"""The ONNX Runtime session that serves an exported emulator (``OnnxEmulator``): what the emulator
service steps. It imports neither torch nor MuJoCo; ``export.onnx`` builds the graphs it runs."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from neuroanimator.core.quaternion import wrap_angle


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


class SingleRow:
    """A bound call for one row: each input (1, width) copied into a buffer that ONNX Runtime already
    holds, each output (1, width) written into one it holds too.

    ``session.run`` wraps every input array in a new OrtValue and allocates the outputs on each call;
    at batch 1 that costs as much as a small network itself (10–15 µs of 35–50). The binding is made
    once; its buffers belong to one thread (``PerThreadRow``)."""

    def __init__(
        self, session: ort.InferenceSession, inputs: dict[str, int], outputs: dict[str, int]
    ) -> None:
        self.inputs = {name: np.zeros((1, w), dtype=np.float32) for name, w in inputs.items()}
        self.outs = [np.zeros((1, w), dtype=np.float32) for w in outputs.values()]
        self.binding = session.io_binding()
        for name, buf in self.inputs.items():
            self.binding.bind_cpu_input(name, buf)
        for name, buf in zip(outputs, self.outs, strict=True):
            self.binding.bind_output(name, "cpu", 0, np.float32, buf.shape, buf.ctypes.data)
        self.session = session

    def run(self, feed: dict[str, NDArray[np.float32]]) -> list[NDArray[np.float32]]:
        """The outputs (each (1, width), in the order given) for one row of every input."""
        for name, values in feed.items():
            np.copyto(self.inputs[name], values)
        self.session.run_with_iobinding(self.binding)
        return [out.copy() for out in self.outs]  # the buffers are overwritten by the next call


class PerThreadRow:
    """``SingleRow`` calls of one session, a binding per calling thread (made on its first call)."""

    def __init__(
        self, session: ort.InferenceSession, inputs: dict[str, int], outputs: dict[str, int]
    ) -> None:
        self.session, self.inputs, self.outputs = session, inputs, outputs
        self._local = threading.local()

    def run(self, feed: dict[str, NDArray[np.float32]]) -> list[NDArray[np.float32]]:
        row: SingleRow | None = getattr(self._local, "row", None)
        if row is None:
            row = self._local.row = SingleRow(self.session, self.inputs, self.outputs)
        return row.run(feed)


class OnnxEmulator:
    """An emulator served by ONNX Runtime: ``step(state (B,S), controls (B,U), forces (B,F)) -> (B,S)``."""

    def __init__(self, model: bytes | str | Path, threads: int = 1, wrap: Sequence[int] = ()) -> None:
        """``wrap``: state columns (a ``heading``, ``state.heading_columns``) that each step reports
        wrapped to [-π, π)."""
        src = str(model) if isinstance(model, Path) else model
        self.wrap = list(wrap)
        self.threads = threads
        self.session = ort.InferenceSession(src, session_options(threads), providers=["CPUExecutionProvider"])
        ins = {i.name: i for i in self.session.get_inputs()}
        self.input_names = list(ins)
        self.state_size = int(ins["state"].shape[1])
        self.num_controls = int(ins["controls"].shape[1]) if "controls" in ins else 0
        self.num_forces = int(ins["forces"].shape[1]) if "forces" in ins else 0
        widths = {"state": self.state_size, "controls": self.num_controls, "forces": self.num_forces}
        self._row = PerThreadRow(
            self.session,
            {name: w for name, w in widths.items() if w},
            {self.session.get_outputs()[0].name: self.state_size},
        )

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
        out: NDArray[np.float32] = self._row.run(feed)[0] if one_row else self.session.run(None, feed)[0]
        if self.wrap:
            out[:, self.wrap] = wrap_angle(out[:, self.wrap])
        return out

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
