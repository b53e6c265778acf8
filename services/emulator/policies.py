"""Trained feedback policies served as a session's driver (``neuroanimator.artifacts.policies``).

A policy is ``π(state (B,S), goal (B,G)[, time_left (B,1)]) → controls (B,U)``, an ONNX graph stored
beside the emulator version it was trained through. ``PolicyRegistry`` finds and loads a model's
policies (the data directory over the committed defaults, as emulators are found) and keeps them
loaded; a ``LoadedPolicy`` evaluates a batch of states and goals in one ONNX Runtime call, checks a
client's goal and names the goal variables outside the goals it was trained for.

A timed policy also reads ``time_left = max(0, check_steps − steps since the goal was set) /
goal_period_steps``: the share of a goal's period left until its check, as in its training.
Torch-free, like the rest of the service.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray
from onnxruntime.capi import onnxruntime_pybind11_state as ort_errors

from neuroanimator.artifacts import registry
from neuroanimator.artifacts.policies import (
    POLICY_ONNX,
    PolicyError,
    list_policies,
    read_policy,
    resolve_policy,
)
from neuroanimator.core.policy_manifest import PolicyManifest
from neuroanimator.export.driven import declared_range, keeps_within
from neuroanimator.export.runtime import PerThreadRow, session_options
from services.emulator.errors import BadInput, PolicyMismatch, UnknownPolicy
from services.emulator.inputs import check_vector

log = logging.getLogger(__name__)
# what ONNX Runtime raises for a graph it cannot load (its exceptions share no base of their own)
_ORT_LOAD_ERRORS = (
    ort_errors.Fail,
    ort_errors.InvalidGraph,
    ort_errors.InvalidProtobuf,
    ort_errors.InvalidArgument,
    ort_errors.NoSuchFile,
)


def _outward(low: Sequence[float], high: Sequence[float]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """float32 bounds rounded outwards, so that a float32 goal given as a bound is inside."""
    lo, hi = np.asarray(low, np.float64), np.asarray(high, np.float64)
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    return (
        np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32),
        np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32),
    )


@dataclass
class LoadedPolicy:
    """One stored policy version, loaded: its manifest and ONNX Runtime session."""

    manifest: PolicyManifest
    path: Path
    session: ort.InferenceSession
    goal_low: NDArray[np.float32] = field(init=False)
    goal_high: NDArray[np.float32] = field(init=False)
    default_goal: NDArray[np.float32] = field(init=False)
    calls: int = field(init=False, default=0)  # ONNX Runtime calls made (tests compare it with ticks)

    def __post_init__(self) -> None:
        m = self.manifest
        self.goal_low, self.goal_high = _outward(m.goal_low, m.goal_high)
        self.default_goal = np.asarray(m.goal_default, np.float32)
        names = {i.name: i for i in self.session.get_inputs()}
        want = ["state", "goal", "time_left"] if m.timed else ["state", "goal"]
        if sorted(names) != sorted(want) or self.session.get_outputs()[0].name != "controls":
            raise ValueError(
                f"{self.path / POLICY_ONNX}: inputs {sorted(names)} and output "
                f"{self.session.get_outputs()[0].name!r}; a {'timed ' if m.timed else ''}policy takes "
                f"{want} and gives 'controls'"
            )
        widths = {"state": m.state_size, "goal": m.goal_size} | ({"time_left": 1} if m.timed else {})
        self._row = PerThreadRow(self.session, widths, {"controls": len(m.control_names)})
        self._range = declared_range(self.session.get_modelmeta().custom_metadata_map)
        self._within: dict[bytes, bool] = {}

    def keeps_within(self, low: NDArray[np.float32], high: NDArray[np.float32]) -> bool:
        """Whether this policy's controls never leave [low, high] (U,), as its graph declares: a tick
        then needs no clip of its own (remembered per range)."""
        key = low.tobytes() + high.tobytes()
        known = self._within.get(key)
        if known is None:
            known = self._within[key] = keeps_within(self._range, low, high)
        return known

    @property
    def name(self) -> str:
        return self.manifest.name

    @property
    def version(self) -> str:
        return self.manifest.version

    @property
    def goal_size(self) -> int:
        return self.manifest.goal_size

    @property
    def num_controls(self) -> int:
        return len(self.manifest.control_names)

    @cached_property
    def label(self) -> str:  # (read every driven tick: made once)
        return f"{self.manifest.model}/{self.name}/{self.version}"

    def time_left(self, since_goal: NDArray[np.int64]) -> NDArray[np.float32]:
        """(B,) super-steps since each goal was set -> (B, 1) the share of the goal's period left
        until its check (0 once past it)."""
        m = self.manifest
        left = (m.check_steps - since_goal[:, None]).astype(np.float32)
        np.maximum(left, 0, out=left)
        left /= np.float32(m.goal_period_steps)
        return left

    def controls(
        self, states: NDArray[np.float32], goals: NDArray[np.float32], since_goal: NDArray[np.int64]
    ) -> NDArray[np.float32]:
        """States (B, S) and goals (B, G), float32, and (B,) super-steps since each goal was set ->
        controls (B, U), in one ONNX Runtime call."""
        self.calls += 1
        feed = {"state": states, "goal": goals}
        if self.manifest.timed:
            feed["time_left"] = self.time_left(since_goal)
        if len(states) == 1:
            return self._row.run(feed)[0]
        out: NDArray[np.float32] = self.session.run(None, feed)[0]
        return out

    def check_goal(self, values: Sequence[float], field: str) -> NDArray[np.float32]:
        """A client's goal as (G,) float32; ``BadInput`` naming ``field`` on a wrong length or a value
        that is not a finite float32."""
        m = self.manifest
        return check_vector(field, values, m.goal_size, f"policy {m.name!r} (goal {m.goal_variables})").copy()

    def goal_outside(self, goal: NDArray[np.float32]) -> list[str]:
        """The goal variables of (G,) ``goal`` outside the goals the policy was trained for."""
        out = (goal < self.goal_low) | (goal > self.goal_high)
        if not out.any():
            return []
        return [v for v, o in zip(self.manifest.goal_variables, out.tolist(), strict=True) if o]

    def check_emulator(self, model: str, version: str) -> None:
        """``PolicyMismatch`` unless the policy was trained through this emulator version."""
        m = self.manifest
        if (m.model, m.emulator_version) != (model, version):
            raise PolicyMismatch(
                f"policy {m.name!r} was trained for emulator version {m.emulator_version}; this session "
                f"runs {version}",
                field="version",
                expected=m.emulator_version,
                got=version,
            )


class PolicyRegistry:
    """The policies of the served models, loaded on first use and kept (a session keeps its version)."""

    def __init__(self, root: registry.Root, threads: int = 1) -> None:
        self.root = root
        self.threads = threads
        self.loaded: dict[tuple[str, str, str], LoadedPolicy] = {}
        self._lock = threading.Lock()

    def names(self, model: str) -> list[str]:
        return [m.name for m in list_policies(self.root, model)]

    def get(self, model: str, name: str, version: str | None = None) -> LoadedPolicy:
        """The named version of a model's policy (its latest when None); ``UnknownPolicy`` naming what is
        missing and the model's policies."""
        try:
            folder = resolve_policy(self.root, model, name, version)
        except PolicyError as exc:
            known = self.names(model)
            raise UnknownPolicy(
                f"{exc}; the policies of {model!r} are {known}",
                field="policy.version" if version is not None and name in known else "policy.name",
                expected=known,
                got=name if version is None else f"{name} {version}",
            ) from None
        key = (model, name, folder.name)
        with self._lock:
            hit = self.loaded.get(key)
            if hit is None:
                hit = self.loaded[key] = self._load(folder)
        return hit

    def _load(self, folder: Path) -> LoadedPolicy:
        try:
            manifest = read_policy(folder)
            session = ort.InferenceSession(
                str(folder / POLICY_ONNX), session_options(self.threads), providers=["CPUExecutionProvider"]
            )
            policy = LoadedPolicy(manifest, folder, session)
        except (PolicyError, OSError, ValueError, *_ORT_LOAD_ERRORS) as exc:
            raise UnknownPolicy(
                f"the policy at {folder.parent.name}/{folder.name} cannot be loaded: {exc}",
                field="policy.name",
                got=folder.parent.name,
            ) from None
        log.info("loaded policy", extra={"policy": policy.label})
        return policy


def check_drive(policy: LoadedPolicy, state_size: int, num_controls: int) -> None:
    """``BadInput`` when the policy's shapes are not the emulator's (a policy stored by hand)."""
    m = policy.manifest
    if (m.state_size, policy.num_controls) != (state_size, num_controls):
        raise BadInput(
            f"policy {m.name!r} reads {m.state_size} state values and sets {policy.num_controls} controls; "
            f"the emulator has {state_size} and {num_controls}",
            code="policy_shape",
            field="policy.name",
            expected=[state_size, num_controls],
            got=[m.state_size, policy.num_controls],
        )
