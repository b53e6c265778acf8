"""Export the ONNX graph of artifact versions again from their own weights, after the graph's form changed.

    python scripts/reexport.py [--artifacts artifacts] [--models lander,quadrotor]

The step an emulator computes is fixed by its weights (``weights.pt``) and its manifest; how that step is
written as an ONNX graph may get better (fewer nodes, so less ONNX Runtime overhead per call). For each
version this builds the torch emulator from the artifact (``artifacts.load_emulator``: one network or a
hierarchy), exports it with the current ``export.to_onnx``, checks that the new graph computes what the
old one did (typical states and controls of the model, 1e-5 relative), and replaces ``emulator.onnx`` and the manifest's
``onnx_sha256``; the rest of the manifest is left as it is, byte for byte. A version whose graph would
not change, or whose new graph disagrees, is left alone.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
from pathlib import Path

import numpy as np

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.export.onnx import to_onnx
from neuroanimator.export.runtime import OnnxEmulator

log = logging.getLogger("reexport")
CHECK_ROWS = 256


def _typical_inputs(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    rng = np.random.default_rng(0)
    times = np.zeros(1)
    s = model.initial_states(rng, CHECK_ROWS).astype(np.float32)
    u = (
        model.typical_controls(rng, CHECK_ROWS, times)[:, 0].astype(np.float32)
        if model.num_controls
        else None
    )
    f = model.typical_forces(rng, CHECK_ROWS, times)[:, 0].astype(np.float32) if model.num_forces else None
    return s, u, f


def reexport(path: Path) -> str:
    """Export the version folder ``path`` again; what was done, in words."""
    old_file = path / registry.ONNX_FILE
    old_bytes = old_file.read_bytes()
    new_bytes = to_onnx(artifacts.load_emulator(path))
    if new_bytes == old_bytes:
        return "unchanged"
    s, u, f = _typical_inputs(path)
    old, new = OnnxEmulator(old_bytes).step(s, u, f), OnnxEmulator(new_bytes).step(s, u, f)
    gap = float(np.max(np.abs(old - new) / (1.0 + np.abs(old))))
    if not gap <= 1e-5:
        return f"left alone: the new graph differs by {gap:.2e}"
    old_hash, new_hash = hashlib.sha256(old_bytes).hexdigest(), hashlib.sha256(new_bytes).hexdigest()
    manifest_file = path / registry.MANIFEST_FILE
    text = manifest_file.read_text()
    if text.count(old_hash) != 1:
        return "left alone: the manifest does not name the graph's hash once"
    tmp = old_file.with_suffix(".onnx.tmp")
    tmp.write_bytes(new_bytes)
    tmp.replace(old_file)
    manifest_file.write_text(text.replace(old_hash, new_hash))
    return f"exported again ({len(old_bytes):,} -> {len(new_bytes):,} bytes, outputs within {gap:.1e})"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--artifacts", type=Path, default=Path("artifacts"))
    p.add_argument("--models", help="comma-separated model names (default: every model in the registry)")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    names = args.models.split(",") if args.models else registry.list_models(args.artifacts)
    for name in names:
        for version in registry.versions(args.artifacts, name):
            path = args.artifacts / name / version
            log.info("%s/%s: %s", name, version, reexport(path))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
