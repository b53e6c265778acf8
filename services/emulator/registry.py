"""The emulators this service serves, loaded from the artifact registries (``neuroanimator.artifacts.registry``:
the data directory's uploads and trainings over the committed defaults).

It loads every model's ``latest`` version into an ``OnnxEmulator`` and re-reads the pointer files at
most every ``poll_s`` seconds, so a new version (or a new model, e.g. one the trainer service just
exported) is served without a restart, and a deleted model is no longer listed. Versions already
loaded stay loaded: a session keeps the version it started with. An older version named explicitly
is loaded on demand. A model uploaded with an API key is listed and served to that key (and
operators) only, until it is published (``services.common.tenancy``). Nothing here imports torch.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from neuroanimator.artifacts import registry
from neuroanimator.core.manifest import Manifest
from neuroanimator.core.state import QUATERNION_KINDS, heading_columns
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel
from services.common import tenancy
from services.emulator.envelope import StateEnvelope
from services.emulator.errors import UnknownModel
from services.emulator.inputs import InputRange
from services.emulator.scene import Kinematics

log = logging.getLogger(__name__)


@dataclass
class LoadedEmulator:
    """One loaded version: its manifest, the ORT emulator, the trained range of its inputs and the
    envelope of its training states (None when the manifest has none)."""

    model: str
    version: str
    path: Path
    manifest: Manifest
    emulator: OnnxEmulator
    inputs: InputRange = field(init=False)
    envelope: StateEnvelope | None = field(init=False)
    quaternion_slices: list[slice] = field(init=False)

    def __post_init__(self) -> None:
        m = self.manifest
        self.inputs = InputRange(m.controls, m.forces)
        self.envelope = None if m.envelope is None else StateEnvelope(m.state_layout(), m.envelope)
        self.quaternion_slices = [
            slice(g.offset, g.offset + g.size) for g in m.layout if g.kind in QUATERNION_KINDS
        ]
        e = self.emulator
        if (e.state_size, e.num_controls, e.num_forces) != (
            self.state_size,
            self.num_controls,
            self.num_forces,
        ):
            raise ValueError(f"{self.path}: the ONNX graph's inputs do not match the manifest")

    @property
    def state_size(self) -> int:
        return self.manifest.state_size

    @property
    def num_controls(self) -> int:
        return self.manifest.num_controls

    @property
    def num_forces(self) -> int:
        return self.manifest.num_forces

    @property
    def super_timestep(self) -> float:
        return self.manifest.super_timestep

    @cached_property
    def physical(self) -> PhysicalModel:
        """The MuJoCo model the artifact was trained on (for typical initial states)."""
        return registry.load_physical_model(self.path, self.manifest)

    @cached_property
    def kinematics(self) -> Kinematics:
        """Body poses for states of this model (for ``/geometry``, ``/poses`` and ``poses: true``)."""
        return Kinematics(self.physical)

    @property
    def substeps(self) -> int:
        return self.manifest.substeps

    def initial_state(self, seed: int) -> NDArray[np.float32]:
        """(S,) a random typical start, deterministic for the seed."""
        s = self.physical.initial_states(np.random.default_rng(seed), 1)[0]
        return s.astype(np.float32)


class Registry:
    """Loaded emulators by (model, version); ``latest`` maps a model to its current version."""

    def __init__(self, root: registry.Root, threads: int = 1, poll_s: float = 2.0) -> None:
        self.root = root
        self.threads = threads
        self.poll_s = poll_s
        self.loaded: dict[tuple[str, str], LoadedEmulator] = {}
        self.latest: dict[str, str] = {}
        self._checked = 0.0
        self._lock = threading.Lock()

    def _load(self, model: str, version: str) -> LoadedEmulator:
        key = (model, version)
        if key not in self.loaded:
            path = registry.resolve(self.root, model, version)
            manifest = registry.read_manifest(path)
            # a heading is reported wrapped to [-π, π) (frames interpolate it along the shorter arc)
            emu = OnnxEmulator(path / registry.ONNX_FILE, self.threads, wrap=heading_columns(manifest.layout))
            self.loaded[key] = LoadedEmulator(model, version, path, manifest, emu)
            log.info("loaded emulator", extra={"model": model, "version": version})
        return self.loaded[key]

    def refresh(self) -> None:
        """Re-read every ``latest`` pointer; load versions not yet loaded. A broken new version is
        logged and skipped (the previous latest keeps serving)."""
        with self._lock:
            self._checked = time.monotonic()
            models = registry.list_models(self.root)
            for gone in set(self.latest) - set(models):  # deleted: no longer listed (sessions keep theirs)
                del self.latest[gone]
            for model in models:
                try:
                    version = registry.latest_version(self.root, model)
                    if self.latest.get(model) != version:
                        self._load(model, version)
                        self.latest[model] = version
                except (OSError, ValueError, registry.ArtifactError) as exc:
                    log.error("cannot load %s: %s", self.root / model, exc)

    def maybe_refresh(self) -> None:
        if time.monotonic() - self._checked >= self.poll_s:
            self.refresh()

    def models(self) -> list[str]:
        """The models the current request's caller sees."""
        self.maybe_refresh()
        return sorted(m for m in self.latest if tenancy.can_see(self.root, m))

    def versions(self, model: str) -> list[str]:
        return sorted(v for m, v in self.loaded if m == model)

    def get(self, model: str, version: str | None = None) -> LoadedEmulator:
        """The named version (loaded on demand) or the latest; ``UnknownModel`` when there is none."""
        self.maybe_refresh()
        if model not in self.latest or not tenancy.can_see(self.root, model):
            known = self.models()
            raise UnknownModel(
                f"unknown model {model!r}; loaded models are {known}",
                field="model",
                expected=known,
                got=model,
            )
        if version is None:
            return self.loaded[(model, self.latest[model])]
        if (model, version) in self.loaded:
            return self.loaded[(model, version)]
        # (a version no pointer names, fine-tuned for a policy, may be in another registry)
        if registry.version_folder(self.root, model, version) is not None:
            with self._lock:
                try:
                    return self._load(model, version)
                except (OSError, ValueError, registry.ArtifactError) as exc:
                    log.error("cannot load %s: %s", self.root / model / version, exc)
        raise UnknownModel(
            f"model {model!r} has no version {version!r}; loaded versions are {self.versions(model)}",
            code="unknown_version",
            field="version",
            expected=self.versions(model),
            got=version,
        )
