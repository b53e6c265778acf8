"""Every committed artifact loads and serves as it was written, whatever has moved in the code since:
its manifest reads, the modules it names (a data source, a driver) import under their current names,
its ONNX graph runs a step from its model's typical state, and the torch emulator rebuilt from its
weights steps to the same state."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator.artifacts import registry, store
from neuroanimator.core.model_spec import MOVED_MODULES, current_module
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.driver import load_driver

COMMITTED = [
    registry.resolve(registry.DEFAULTS_DIR, model, substeps=n)
    for model in registry.list_models(registry.DEFAULTS_DIR)
    for n in registry.available_substeps(registry.DEFAULTS_DIR, model)
]


def test_the_committed_defaults_are_all_here() -> None:
    assert {p.parent.name for p in COMMITTED} >= {"pendulum-passive", "lander", "truck", "dolphin", "runner"}


@pytest.mark.parametrize("path", COMMITTED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_a_committed_artifact_loads_and_steps_as_written(path: Path) -> None:
    manifest = registry.read_manifest(path)
    named = json.loads((path / registry.MANIFEST_FILE).read_text())["spec"]
    for written in filter(None, [named.get("data_source"), (named.get("driver") or {}).get("factory")]):
        assert current_module(written).split(":")[0] not in MOVED_MODULES  # read under its new name
    model = registry.load_physical_model(path, manifest)
    if manifest.spec.driver is not None:
        assert load_driver(manifest.spec.driver, model, manifest.substeps, {}) is not None
    state = model.initial_states(np.random.default_rng(0), 2).astype(np.float32)
    u = np.zeros((2, manifest.num_controls), np.float32) if manifest.num_controls else None
    f = np.zeros((2, manifest.num_forces), np.float32) if manifest.num_forces else None
    served = OnnxEmulator(path / registry.ONNX_FILE).step(state, u, f)
    assert served.shape == state.shape and np.isfinite(served).all()
    with torch.no_grad():
        inputs = [None if a is None else torch.from_numpy(a) for a in (state, u, f)]
        stepped = store.load_emulator(path)(*inputs).numpy()
    np.testing.assert_allclose(stepped, served, atol=1e-3 * max(1.0, float(np.abs(state).max())))
