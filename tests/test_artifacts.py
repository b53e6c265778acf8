"""Writing artifacts: what a version folder holds, its manifest, how it is found, that writes are atomic,
and that the torch emulator read back is the one saved."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.core.manifest import FORMAT, TrainMetrics
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainConfig, TrainResult
from tests.helpers import METRICS, Trained

FILES = {"emulator.onnx", "weights.pt", "linear_baseline.npy", "model.xml", "manifest.json"}


def _untrained_result(model: catalog.PhysicalModel, substeps: int) -> TrainResult:
    """A TrainResult without training (random weights): enough to exercise the registry."""
    cfg = TrainConfig(substeps=substeps, hidden=(8,), progress=False)
    emu = training.build_emulator(model, cfg)
    linear = np.zeros((emu.input_size + 1, model.state_size))
    return TrainResult(emu, cfg, METRICS, linear, "0" * 64)


def test_version_folder_holds_the_documented_files(trained_pendulum: Trained) -> None:
    assert {p.name for p in trained_pendulum.path.iterdir()} == FILES == set(registry.VERSION_FILES)


@pytest.mark.parametrize("which", ["trained_pendulum", "trained_lander"])
def test_manifest_describes_the_saved_emulator(which: str, request: pytest.FixtureRequest) -> None:
    t: Trained = request.getfixturevalue(which)
    manifest = registry.read_manifest(t.path)
    assert json.loads((t.path / "manifest.json").read_text())["format"] == FORMAT
    assert manifest.model == t.model.name
    assert manifest.version == t.path.name
    assert manifest.substeps == 10
    assert manifest.timestep == pytest.approx(t.model.dt)
    assert manifest.super_timestep == pytest.approx(10 * t.model.dt)
    assert manifest.layout == t.model.layout.placed()
    assert manifest.state_layout() == t.model.layout
    assert [c.name for c in manifest.controls] == t.model.control_names
    assert manifest.forces == []
    assert manifest.metrics == TrainMetrics(**t.result.metrics)
    assert manifest.train_config == t.result.config
    assert manifest.spec == t.model.spec
    assert manifest.io.inputs == ["state", "controls"]
    emu = t.result.emulator
    net = manifest.emulator.only()
    assert manifest.emulator.stages == [[net.name]]
    assert net.writes == [g.name for g in t.model.layout]
    assert net.reads.controls == t.model.control_names
    assert (net.hidden, net.activation, net.input_size) == ([16], "tanh", emu.input_size)
    assert [(g.name, g.size) for g in net.normalization.input_groups] == list(emu.input_groups)
    np.testing.assert_allclose(net.normalization.x_mean, emu.x_mean.numpy(), rtol=1e-6)
    np.testing.assert_allclose(net.normalization.y_std, emu.y_std.numpy(), rtol=1e-6)


def test_lander_network_reads_no_root_position_in_its_frame(trained_lander: Trained) -> None:
    """Translation is a symmetry of the lander: the root position is not an input, only the frame."""
    net = registry.read_manifest(trained_lander.path).emulator.only()
    assert "position" not in net.reads.state and "position" in net.writes
    assert net.frame.part is None and net.frame.rotate and net.frame.translate == [True, True, True]


def test_manifest_hashes_match_the_files(trained_pendulum: Trained) -> None:
    path = trained_pendulum.path
    hashes = registry.read_manifest(path).hashes
    assert hashes.mjcf_sha256 == hashlib.sha256((path / "model.xml").read_bytes()).hexdigest()
    assert hashes.mjcf_sha256 == trained_pendulum.model.mjcf_sha256()
    assert hashes.training_data_sha256 == trained_pendulum.result.data_sha256
    assert hashes.onnx_sha256 == hashlib.sha256((path / "emulator.onnx").read_bytes()).hexdigest()


def test_saved_linear_baseline_and_weights(trained_pendulum: Trained) -> None:
    path, result = trained_pendulum.path, trained_pendulum.result
    np.testing.assert_array_equal(np.load(path / "linear_baseline.npy"), result.linear)
    saved = torch.load(path / "weights.pt", weights_only=True)
    for key, value in result.emulator.state_dict().items():
        torch.testing.assert_close(saved[key], value)


def test_resolve_latest_and_by_substeps(trained_pendulum: Trained) -> None:
    root = trained_pendulum.root
    assert registry.resolve(root, "pendulum-active") == trained_pendulum.path
    assert registry.resolve(root, "pendulum-active", substeps=10) == trained_pendulum.path
    assert (
        registry.resolve(root, "pendulum-active", version=trained_pendulum.path.name) == trained_pendulum.path
    )
    assert 10 in registry.available_substeps(root, "pendulum-active")
    assert "pendulum-active" in registry.list_models(root)
    assert trained_pendulum.path.name in registry.versions(root, "pendulum-active")


def test_load_physical_model_rebuilds_the_same_model(trained_lander: Trained) -> None:
    rebuilt = registry.load_physical_model(trained_lander.path)
    original = trained_lander.model
    assert rebuilt.name == original.name
    assert rebuilt.xml == original.xml
    assert rebuilt.spec == original.spec
    assert rebuilt.layout == original.layout
    assert rebuilt.control_names == original.control_names
    assert rebuilt.frame == original.frame
    rng = np.random.default_rng(3)
    s = original.initial_states(rng, 4)
    u = original.typical_controls(rng, 4, np.zeros(1))[:, 0]
    np.testing.assert_array_equal(rebuilt.step_held(s, u, None, 10), original.step_held(s, u, None, 10))


@pytest.mark.parametrize("which", ["trained_pendulum", "trained_lander"])
def test_load_torch_gives_the_same_outputs(which: str, request: pytest.FixtureRequest) -> None:
    t: Trained = request.getfixturevalue(which)
    loaded = artifacts.load_torch(t.path)
    rng = np.random.default_rng(4)
    s = torch.from_numpy(t.model.initial_states(rng, 16)).float()
    u = torch.from_numpy(t.model.typical_controls(rng, 16, np.zeros(1))[:, 0]).float()
    with torch.no_grad():
        torch.testing.assert_close(loaded(s, u), t.result.emulator.eval()(s, u), rtol=0, atol=0)
    assert loaded.architecture() == t.result.emulator.architecture()


def test_load_torch_refuses_a_composed_emulator(tmp_path: Path, trained_pendulum: Trained) -> None:
    import shutil

    path = tmp_path / "pendulum-active" / trained_pendulum.path.name
    shutil.copytree(trained_pendulum.path, path)
    data = json.loads((path / "manifest.json").read_text())
    core = data["emulator"]["networks"][0]

    def half(name: str, part: slice) -> dict[str, object]:
        norm = core["normalization"]
        y = {k: norm[k][part] for k in ("y_mean", "y_std")}
        return dict(core, name=name, writes=[name], output_size=3, normalization=dict(norm, **y))

    networks = [half("angles", slice(0, 3)), half("rates", slice(3, 6))]
    data["emulator"] = {"networks": networks, "stages": [["angles", "rates"]]}
    (path / "manifest.json").write_text(json.dumps(data))
    assert len(registry.read_manifest(path).emulator.networks) == 2  # a valid description...
    with pytest.raises(ValueError, match="composed of 2 networks"):
        artifacts.load_torch(path)  # ...that the torch path does not build yet


def test_saved_onnx_matches_saved_weights(trained_lander: Trained) -> None:
    rng = np.random.default_rng(6)
    s = trained_lander.model.initial_states(rng, 32)
    u = trained_lander.model.typical_controls(rng, 32, np.zeros(1))[:, 0]
    onnx_out = OnnxEmulator(trained_lander.path / "emulator.onnx").step(s, u)
    with torch.no_grad():
        torch_out = artifacts.load_torch(trained_lander.path)(
            torch.from_numpy(s).float(), torch.from_numpy(u).float()
        )
    np.testing.assert_allclose(onnx_out, torch_out.numpy(), atol=1e-4 * max(1.0, float(np.abs(s).max())))


def test_latest_stays_on_first_version_and_per_n_pointers_move(tmp_path: Path) -> None:
    model = catalog.get("truck")  # default substeps 50
    first = artifacts.save(tmp_path, model, _untrained_result(model, 10))
    second = artifacts.save(tmp_path, model, _untrained_result(model, 20))
    assert first != second
    assert registry.resolve(tmp_path, "truck") == first  # the first trained, since neither is n = 50
    assert registry.resolve(tmp_path, "truck", substeps=20) == second
    third = artifacts.save(tmp_path, model, _untrained_result(model, 50))
    assert registry.resolve(tmp_path, "truck") == third  # the model's default n takes over `latest`
    again = artifacts.save(tmp_path, model, _untrained_result(model, 10))
    assert registry.resolve(tmp_path, "truck", substeps=10) == again
    assert registry.available_substeps(tmp_path, "truck") == [10, 20, 50]
    assert again.name.startswith("n10-") and third.name.startswith("n50-")


def test_failed_write_leaves_nothing_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model = catalog.get("truck")
    result = _untrained_result(model, 10)

    def boom(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", boom)
    with pytest.raises(OSError, match="disk full"):
        artifacts.save(tmp_path, model, result)
    model_dir = tmp_path / "truck"
    leftovers = sorted(p.name for p in model_dir.iterdir()) if model_dir.exists() else []
    assert leftovers == []  # no version folder, no `latest` pointers, no .tmp- folder
    assert registry.list_models(tmp_path) == []
    with pytest.raises(registry.ArtifactError):
        registry.resolve(tmp_path, "truck")


def test_failed_write_keeps_the_previous_latest(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model = catalog.get("truck")
    good = artifacts.save(tmp_path, model, _untrained_result(model, 10))

    def boom(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", boom)
    with pytest.raises(OSError):
        artifacts.save(tmp_path, model, _untrained_result(model, 10))
    assert registry.resolve(tmp_path, "truck") == good
    assert registry.resolve(tmp_path, "truck", substeps=10) == good
    assert sorted(p.name for p in (tmp_path / "truck").iterdir()) == sorted(
        [good.name, "latest", "latest-n10"]
    )


def test_model_name_that_cannot_be_a_folder_is_refused(tmp_path: Path) -> None:
    model = catalog.get("truck")
    bad = catalog.PhysicalModel(model.xml, model.spec.model_copy(update={"name": "../escape"}))
    with pytest.raises(catalog.ModelError, match="folder"):
        artifacts.save(tmp_path, bad, _untrained_result(bad, 10))
    assert list(tmp_path.iterdir()) == []
