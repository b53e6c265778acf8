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
from neuroanimator.artifacts.policies import POLICY_ONNX, list_policies, read_policy, resolve_policy
from neuroanimator.core.model_spec import MOVED_MODULES, current_module
from neuroanimator.core.policy_manifest import PolicyManifest
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


POLICIES = [
    resolve_policy(registry.DEFAULTS_DIR, p.model, p.name, p.version)
    for p in list_policies(registry.DEFAULTS_DIR)
]


def test_the_committed_policies_are_all_here() -> None:
    names = {f"{p.parent.parent.name}/{p.parent.name}" for p in POLICIES}
    assert names >= {"lander/lander-landing", "truck/truck-parking", "runner/runner-run"}


@pytest.mark.parametrize("path", POLICIES, ids=lambda p: f"{p.parent.parent.name}/{p.parent.name}")
def test_a_committed_policy_acts_within_its_controls_from_where_its_sessions_start(path: Path) -> None:
    import onnxruntime as ort

    policy = read_policy(path)
    emulator = registry.resolve(registry.DEFAULTS_DIR, policy.model, policy.emulator_version)
    assert registry.read_manifest(emulator).state_size == policy.state_size
    starts = np.asarray(policy.starts, np.float32)
    if not len(starts):
        model = registry.load_physical_model(emulator, registry.read_manifest(emulator))
        starts = model.initial_states(np.random.default_rng(0), 2).astype(np.float32)
    graph = ort.InferenceSession(str(path / POLICY_ONNX), providers=["CPUExecutionProvider"])
    goal = np.repeat(np.asarray([policy.goal_default], np.float32), len(starts), axis=0)
    feeds = {"state": starts, "goal": goal}
    names = {i.name for i in graph.get_inputs()}
    feeds.update(
        {n: np.zeros((len(starts), 1), np.float32) for n in names - set(feeds)}
    )  # a timed one's clock
    controls = graph.run(None, feeds)[0]
    assert controls.shape == (len(starts), len(policy.control_names)) and np.isfinite(controls).all()
    low = np.array([c.low for c in registry.read_manifest(emulator).controls])
    high = np.array([c.high for c in registry.read_manifest(emulator).controls])
    assert np.all(controls >= low - 1e-4) and np.all(controls <= high + 1e-4)
    if policy.name == "runner-run":  # its sessions start running at the middle of its commands
        vx = starts[:, policy.state_labels.index("root.vel.x")]
        np.testing.assert_allclose(vx, 2.0, atol=0.05)


def test_a_policy_whose_starts_are_not_states_is_refused() -> None:
    policy = read_policy(resolve_policy(registry.DEFAULTS_DIR, "runner", "runner-run"))
    with pytest.raises(ValueError, match="do not have the state's 71 values"):
        PolicyManifest.model_validate({**policy.model_dump(), "starts": [[0.0, 1.0]]})
