"""The artifact registry: ``<root>/<model>/<version>/`` folders, written atomically.

A version folder holds ``emulator.onnx`` (the whole step), ``weights.pt`` (the torch emulator's
state dict), ``linear_baseline.npy``, ``model.xml`` (the MJCF it was trained on) and
``manifest.json``. Pointer files name the current versions: ``latest`` (the model's default
super-step, or the first trained) and ``latest-n<N>`` for each super-step N. A version folder is
renamed into place only when complete, and pointers are replaced atomically, so a crash never
leaves a half-written version marked latest.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator.export import to_onnx
from neuroanimator.physics.model import ModelError, PhysicalModel
from neuroanimator.physics.spec import ModelSpec
from neuroanimator.structured import FrameConfig, StructuredEmulator
from neuroanimator.training import TrainResult

FORMAT = 1
DEFAULT_ROOT = Path("artifacts")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class ArtifactError(LookupError):
    """An artifact that does not exist or cannot be read; the message says which."""


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _write_pointer(path: Path, version: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-ptr-")
    with os.fdopen(fd, "w") as fh:
        fh.write(version + "\n")
    os.replace(tmp, path)


def save(root: Path, model: PhysicalModel, result: TrainResult) -> Path:
    """Write a trained emulator as a new version of ``model``; returns the version folder."""
    if not _NAME.match(model.name):
        raise ModelError(
            f"model name {model.name!r} cannot name a folder: use letters, digits, '.', '_' or '-'"
        )
    emu, cfg = result.emulator, result.config
    model_dir = root / model.name
    model_dir.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%S")
    version = f"n{cfg.substeps}-{stamp}"
    k = 1
    while (model_dir / version).exists():
        k += 1
        version = f"n{cfg.substeps}-{stamp}-{k}"
    onnx_bytes = to_onnx(emu)
    manifest: dict[str, Any] = {
        "format": FORMAT,
        "model": model.name,
        "version": version,
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "substeps": cfg.substeps,
        "timestep": model.dt,
        "super_timestep": model.dt * cfg.substeps,
        **{k: v for k, v in model.describe().items() if k not in ("name", "timestep")},
        "io": {
            "inputs": ["state"]
            + (["controls"] if model.num_controls else [])
            + (["forces"] if model.num_forces else []),
            "output": "next_state",
        },
        "normalization": {
            "mode": cfg.normalization,
            "input_groups": [list(g) for g in emu.input_groups],
            "x_mean": emu.x_mean.tolist(),
            "x_std": emu.x_std.tolist(),
            "y_mean": emu.y_mean.tolist(),
            "y_std": emu.y_std.tolist(),
        },
        "architecture": emu.architecture(),
        "train_config": cfg.to_dict(),
        "metrics": result.metrics,
        "hashes": {
            "mjcf_sha256": model.mjcf_sha256(),
            "training_data_sha256": result.data_sha256,
            "onnx_sha256": _sha256(onnx_bytes),
        },
        "spec": model.spec.model_dump(),
    }
    tmp = Path(tempfile.mkdtemp(dir=model_dir, prefix=f".tmp-{version}-"))
    try:
        (tmp / "emulator.onnx").write_bytes(onnx_bytes)
        torch.save(emu.state_dict(), tmp / "weights.pt")
        np.save(tmp / "linear_baseline.npy", result.linear)
        (tmp / "model.xml").write_text(model.xml)
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
        os.rename(tmp, model_dir / version)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _write_pointer(model_dir / f"latest-n{cfg.substeps}", version)
    if cfg.substeps == model.spec.substeps or not (model_dir / "latest").exists():
        _write_pointer(model_dir / "latest", version)
    return model_dir / version


def resolve(root: Path, model: str, version: str | None = None, substeps: int | None = None) -> Path:
    """The folder of a model's version: the named one, else the latest for ``substeps``, else ``latest``."""
    model_dir = root / model
    if not model_dir.is_dir():
        known = list_models(root)
        raise ArtifactError(f"no artifacts for model {model!r} in {str(root)!r}; found {known}")
    if version is None:
        ptr = model_dir / ("latest" if substeps is None else f"latest-n{substeps}")
        if not ptr.is_file():
            what = "a latest version" if substeps is None else f"a version with substeps={substeps}"
            raise ArtifactError(f"model {model!r} has no {what} in {str(root)!r}")
        version = ptr.read_text().strip()
    path = model_dir / version
    if not (path / "manifest.json").is_file():
        raise ArtifactError(f"model {model!r} has no version {version!r} in {str(root)!r}")
    return path


def list_models(root: Path) -> list[str]:
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "latest").is_file())


def available_substeps(root: Path, model: str) -> list[int]:
    model_dir = root / model
    out = []
    for p in model_dir.glob("latest-n*"):
        m = re.fullmatch(r"latest-n(\d+)", p.name)
        if m:
            out.append(int(m.group(1)))
    return sorted(out)


def load_manifest(path: Path) -> dict[str, Any]:
    try:
        data: dict[str, Any] = json.loads((path / "manifest.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ArtifactError(f"cannot read the manifest of {str(path)!r}: {exc}") from exc
    if data.get("format") != FORMAT:
        raise ArtifactError(f"{str(path)!r}: manifest format {data.get('format')!r}, expected {FORMAT}")
    return data


def load_physical_model(path: Path) -> PhysicalModel:
    """Rebuild the physical model an artifact was trained on, from the artifact alone."""
    manifest = load_manifest(path)
    return PhysicalModel((path / "model.xml").read_text(), ModelSpec(**manifest["spec"]))


def load_torch(path: Path) -> StructuredEmulator:
    """The torch emulator of an artifact (same weights as its ONNX graph)."""
    manifest = load_manifest(path)
    model = load_physical_model(path)
    arch = manifest["architecture"]
    fr = arch["frame"]
    emu = StructuredEmulator(
        model.layout,
        model.num_controls,
        model.num_forces,
        FrameConfig(tuple(fr["translate"]), bool(fr["rotate"]), tuple(tuple(p) for p in fr["force_pairs"])),
        tuple(arch["hidden"]),
        arch["activation"],
    )
    emu.load_state_dict(torch.load(path / "weights.pt", weights_only=True))
    return emu.eval()
