"""A torch-free reader of the artifact registry, ``<root>/<model>/<version>/``.

It loads every model's ``latest`` version into an ``OnnxEmulator`` and re-reads the pointer files at
most every ``poll_s`` seconds, so a new version is served without a restart. Versions already loaded
stay loaded: a session keeps the version it started with. An older version named explicitly is
loaded on demand. (``neuroanimator.artifacts`` itself imports torch for saving; this module does not.)
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from neuroanimator.export import OnnxEmulator
from neuroanimator.physics.model import PhysicalModel
from neuroanimator.physics.spec import ModelSpec
from services.common.errors import ApiError
from services.emulator.scene import Kinematics

log = logging.getLogger(__name__)
FORMAT = 1
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
QUATERNION_KINDS = ("quaternion", "local_quaternion")


@dataclass
class Loaded:
    """One loaded version: its manifest, the ORT emulator and the input ranges (U, 2) / (F, 2)."""

    model: str
    version: str
    path: Path
    manifest: dict[str, Any]
    emulator: OnnxEmulator
    control_range: NDArray[np.float64] = field(init=False)
    force_range: NDArray[np.float64] = field(init=False)
    quaternion_slices: list[slice] = field(init=False)
    input_low: NDArray[np.float32] = field(init=False)  # (U+F,) controls then forces, as binary frames
    input_high: NDArray[np.float32] = field(init=False)

    def __post_init__(self) -> None:
        m = self.manifest
        self.control_range = np.array([[c["low"], c["high"]] for c in m["controls"]], float).reshape(-1, 2)
        self.force_range = np.array([[f["low"], f["high"]] for f in m["forces"]], float).reshape(-1, 2)
        both = np.concatenate([self.control_range, self.force_range])
        self.input_low, self.input_high = both[:, 0].astype(np.float32), both[:, 1].astype(np.float32)
        self.quaternion_slices = [
            slice(g["offset"], g["offset"] + g["size"]) for g in m["layout"] if g["kind"] in QUATERNION_KINDS
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
        return int(self.manifest["state_size"])

    @property
    def num_controls(self) -> int:
        return len(self.manifest["controls"])

    @property
    def num_forces(self) -> int:
        return len(self.manifest["forces"])

    @property
    def super_timestep(self) -> float:
        return float(self.manifest["super_timestep"])

    @cached_property
    def physical(self) -> PhysicalModel:
        """The MuJoCo model the artifact was trained on (for typical initial states)."""
        return PhysicalModel((self.path / "model.xml").read_text(), ModelSpec(**self.manifest["spec"]))

    @cached_property
    def kinematics(self) -> Kinematics:
        """Body poses for states of this model (for ``/geometry``, ``/poses`` and ``poses: true``)."""
        return Kinematics(self.physical)

    @property
    def substeps(self) -> int:
        return int(self.manifest["substeps"])

    def initial_state(self, seed: int) -> NDArray[np.float32]:
        """(S,) a random typical start, deterministic for the seed."""
        s = self.physical.initial_states(np.random.default_rng(seed), 1)[0]
        return s.astype(np.float32)


def read_manifest(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((path / "manifest.json").read_text())
    if data.get("format") != FORMAT:
        raise ValueError(f"{path}: manifest format {data.get('format')!r}, expected {FORMAT}")
    return data


class Registry:
    """Loaded emulators by (model, version); ``latest`` maps a model to its current version."""

    def __init__(self, root: Path, threads: int = 1, poll_s: float = 2.0) -> None:
        self.root = Path(root)
        self.threads = threads
        self.poll_s = poll_s
        self.loaded: dict[tuple[str, str], Loaded] = {}
        self.latest: dict[str, str] = {}
        self._checked = 0.0
        self._lock = threading.Lock()

    def _load(self, model: str, version: str) -> Loaded:
        key = (model, version)
        if key not in self.loaded:
            path = self.root / model / version
            manifest = read_manifest(path)
            emu = OnnxEmulator(path / "emulator.onnx", threads=self.threads)
            self.loaded[key] = Loaded(model, version, path, manifest, emu)
            log.info("loaded emulator", extra={"model": model, "version": version})
        return self.loaded[key]

    def refresh(self) -> None:
        """Re-read every ``latest`` pointer; load versions not yet loaded. A broken new version is
        logged and skipped (the previous latest keeps serving)."""
        with self._lock:
            self._checked = time.monotonic()
            if not self.root.is_dir():
                return
            for model_dir in sorted(self.root.iterdir()):
                ptr = model_dir / "latest"
                if not (model_dir.is_dir() and ptr.is_file() and _NAME.match(model_dir.name)):
                    continue
                try:
                    version = ptr.read_text().strip()
                    if self.latest.get(model_dir.name) != version:
                        self._load(model_dir.name, version)
                        self.latest[model_dir.name] = version
                except (OSError, ValueError, KeyError) as exc:
                    log.error("cannot load %s: %s", model_dir, exc)

    def maybe_refresh(self) -> None:
        if time.monotonic() - self._checked >= self.poll_s:
            self.refresh()

    def models(self) -> list[str]:
        self.maybe_refresh()
        return sorted(self.latest)

    def versions(self, model: str) -> list[str]:
        return sorted(v for m, v in self.loaded if m == model)

    def get(self, model: str, version: str | None = None) -> Loaded:
        """The named version (loaded on demand) or the latest; 404 ``ApiError`` when there is none."""
        self.maybe_refresh()
        if model not in self.latest:
            raise ApiError(
                404,
                "unknown_model",
                f"unknown model {model!r}; loaded models are {sorted(self.latest)}",
                field="model",
                expected=sorted(self.latest),
                got=model,
            )
        if version is None:
            return self.loaded[(model, self.latest[model])]
        if (model, version) in self.loaded:
            return self.loaded[(model, version)]
        path = self.root / model / version
        if _NAME.match(version) and (path / "manifest.json").is_file():
            with self._lock:
                try:
                    return self._load(model, version)
                except (OSError, ValueError, KeyError) as exc:
                    log.error("cannot load %s: %s", path, exc)
        raise ApiError(
            404,
            "unknown_version",
            f"model {model!r} has no version {version!r}; loaded versions are {self.versions(model)}",
            field="version",
            expected=self.versions(model),
            got=version,
        )
