"""``neuro train --mjcf`` on a model folder as robots are shipped (tests/data/tinybot: an include, an OBJ
mesh and a texture in assets/ through ``<compiler assetdir>``), from the folder, a .zip and a .tar.gz:
the artifact is self-contained (the model and the assets it uses, stored by content and shared by the
versions), and the registry, ONNX Runtime, the emulator service and the MuJoCo replay use it after the
source is deleted. Bad input writes nothing."""

from __future__ import annotations

import pickle
import shutil
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.cli import main
from neuroanimator.control.replay import simulate_held
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.bundle import SourceError
from neuroanimator.sim.mirror import MirrorError

ROOT = Path(__file__).resolve().parents[1]
TINYBOT = ROOT / "tests" / "data" / "tinybot"
# a tiny budget: its emulator misses the acceptance bar, and is kept anyway (--force)
BUDGET = [
    "--substeps",
    "10",
    "--examples",
    "200",
    "--epochs",
    "3",
    "--hidden",
    "8",
    "--rollout-steps",
    "0",
    "--force",
]


@dataclass
class Trained:
    root: Path
    versions: list[Path]


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Trained:
    base = tmp_path_factory.mktemp("sources")
    folder = shutil.copytree(TINYBOT, base / "tinybot")
    archive_zip = base / "tinybot.zip"
    with zipfile.ZipFile(archive_zip, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(folder.rglob("*")):
            zf.write(p, "tinybot/" + p.relative_to(folder).as_posix())
    archive_tgz = base / "tinybot.tar.gz"
    with tarfile.open(archive_tgz, "w:gz") as tf:
        tf.add(folder, arcname="tinybot")
    root = base / "registry"
    for source, extra in ((folder, []), (archive_zip, []), (archive_tgz, ["--entry", "robot.xml"])):
        rc = main(["train", "--mjcf", str(source), *extra, *BUDGET, "--out", str(root), "--quiet"])
        assert rc == 0, source
    shutil.rmtree(folder)  # the source is gone: everything below reads the artifact alone
    archive_zip.unlink()
    archive_tgz.unlink()
    versions = [root / "tinybot" / v for v in registry.versions(root, "tinybot")]
    return Trained(root, versions)


def test_three_versions_share_the_assets_they_use(trained: Trained) -> None:
    assert len(trained.versions) == 3
    stored = sorted(p.name for p in (trained.root / "tinybot" / registry.ASSETS_DIR).iterdir())
    assert len(stored) == 2  # the mesh and the texture once, not unused.obj, not notes.txt
    for path in trained.versions:
        manifest = registry.read_manifest(path)
        assert sorted(a.name for a in manifest.assets) == stored
        assert sorted((a.kind, a.source) for a in manifest.assets) == [
            ("mesh", "assets/knob.obj"),
            ("texture", "assets/checker.png"),
        ]
        xml = (path / registry.MJCF_FILE).read_text()
        assert "<include" not in xml and all(name in xml for name in stored)


def test_the_artifact_works_without_its_source(trained: Trained) -> None:
    path = trained.versions[-1]
    model = registry.load_physical_model(path)
    assert model.mj_model.nmesh == 1 and model.mj_model.ntex == 1
    s0 = model.initial_states(np.random.default_rng(0), 2)
    states = simulate_held(model, s0, np.zeros((2, 3, 1)), 10)  # the controller's MuJoCo replay
    assert states.shape == (2, 4, 2) and np.all(np.isfinite(states))
    onnx = OnnxEmulator(path / registry.ONNX_FILE)
    out = onnx.step(s0.astype(np.float32), np.zeros((2, 1), np.float32))
    assert out.shape == (2, 2) and np.all(np.isfinite(out))
    assert artifacts.load_torch(path).layout.size == 2


def test_the_emulator_service_serves_it(trained: Trained) -> None:
    from services.emulator.app import create_app
    from services.emulator.settings import Settings

    app = create_app(Settings(artifacts_dir=trained.root, registry_poll_s=0.0, redis_url="", api_keys=""))
    with TestClient(app) as client:
        detail = client.get("/models/tinybot").json()
        assert [c["name"] for c in detail["controls"]] == ["motor"]
        assert detail["controls"][0]["unit"] == "N·m"
        geometry = client.get("/models/tinybot/geometry")
        assert geometry.status_code == 200
        types = [g["type"] for b in geometry.json()["bodies"] for g in b["geoms"]]
        assert "mesh" in types
        sid = client.post("/sessions", json={"model": "tinybot", "seed": 1}).json()["id"]
        step = client.post(f"/sessions/{sid}/step", json={"controls": [0.5], "steps": 2})
        assert step.status_code == 200 and len(step.json()["state"]) == 2


def test_the_emulator_service_serves_its_mesh_file(trained: Trained, tmp_path: Path) -> None:
    """``/geometry`` names the knob's OBJ among the artifact's assets with its material; ``/assets/{name}``
    serves that file as stored, to the keys that may see the model only."""
    from services.common import tenancy
    from services.common.auth import ApiKeys
    from services.emulator.app import create_app
    from services.emulator.settings import Settings

    root = tmp_path / "registry"
    shutil.copytree(trained.root, root)
    common: dict[str, Any] = {"artifacts_dir": root, "registry_poll_s": 0.0, "redis_url": ""}
    with TestClient(create_app(Settings(**common, api_keys=""))) as client:
        geoms = client.get("/models/tinybot/geometry").json()["bodies"][0]["geoms"]
        knob = next(g for g in geoms if g["name"] == "knob")
        assert knob["material"]["name"] == "checker" and knob["material"]["rgba"] == [1, 1, 1, 1]
        assert knob["mesh"]["name"] == "knob" and knob["mesh"]["scale"] == [1, 1, 1]
        rod = next(g for g in geoms if g["name"] == "rod")
        assert rod["mesh"] is None and rod["material"] is None
        asset = knob["mesh"]["asset"]
        r = client.get(f"/models/tinybot/assets/{asset}")
        assert r.status_code == 200 and r.content == (TINYBOT / "assets" / "knob.obj").read_bytes()
        assert r.headers["content-type"].startswith("model/obj")
        assert r.headers["etag"] == f'"{asset.split(".")[0]}"' and "immutable" in r.headers["cache-control"]
        version = trained.versions[0].name
        assert client.get(f"/models/tinybot/assets/{asset}", params={"version": version}).status_code == 200
        texture = client.get(f"/models/tinybot/assets/{asset.replace('.obj', '.png')}")
        assert texture.status_code == 404 and texture.json()["error"] == "unknown_asset"
        assert "has no asset" in texture.json()["message"]
        assert client.get(f"/models/nosuch/assets/{asset}").json()["error"] == "unknown_model"

    keys = ApiKeys("alpha,beta", "test-secret")
    tenancy.write(root, "tinybot", tenancy.Ownership.new(keys.id_of("alpha")))
    authed = Settings(**common, api_keys="alpha,beta", api_key_secret="test-secret")
    with TestClient(create_app(authed)) as client:
        url = f"/models/tinybot/assets/{asset}"
        assert client.get(url).status_code == 401
        assert client.get(url, headers={"Authorization": "Bearer alpha"}).status_code == 200
        other = client.get(url, headers={"Authorization": "Bearer beta"})
        assert other.status_code == 404 and other.json()["error"] == "unknown_model"  # as if it did not exist


def test_neuro_models_shows_the_size(trained: Trained, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    assert main(["models", "--artifacts", str(trained.root), "--json"]) == 0
    rows = {r["model"]: r for r in json.loads(capsys.readouterr().out.strip().splitlines()[-1])}
    row = rows["tinybot"]
    assert row["versions"] == 3
    assets = sum(a.size for a in registry.read_manifest(trained.versions[-1]).assets)
    assert row["latest_bytes"] > assets > 0
    assert row["size_bytes"] < 3 * row["latest_bytes"]  # the assets are stored once


def test_a_missing_or_altered_asset_is_named(trained: Trained, tmp_path: Path) -> None:
    root = tmp_path / "copy"
    shutil.copytree(trained.root, root)
    path = root / "tinybot" / trained.versions[0].name
    mesh = next(a for a in registry.read_manifest(path).assets if a.kind == "mesh")
    (root / "tinybot" / registry.ASSETS_DIR / mesh.name).write_bytes(b"v 0 0 0\n")
    with pytest.raises(registry.ArtifactError, match="not the file it names"):
        registry.load_physical_model(path)
    (root / "tinybot" / registry.ASSETS_DIR / mesh.name).unlink()
    with pytest.raises(registry.ArtifactError, match=r"assets/knob\.obj is missing"):
        registry.load_physical_model(path)


@pytest.mark.parametrize(
    "content",
    [b"<mujoco><worldbody>", b'<mujoco><asset><mesh name="m" file="gone.stl"/></asset></mujoco>'],
    ids=["not-xml", "missing-mesh"],
)
def test_bad_input_writes_nothing(tmp_path: Path, content: bytes) -> None:
    source = tmp_path / "model.xml"
    source.write_bytes(content)
    root = tmp_path / "registry"
    assert main(["train", "--mjcf", str(source), *BUDGET, "--out", str(root), "--quiet"]) == 2
    assert not root.exists()


@pytest.mark.parametrize(
    ("error", "field"),
    [
        (SourceError("too_costly", "the model took more than 10 s of CPU"), "kind"),
        (registry.ArtifactError("model", "no model named 'cheetah'"), "what"),
        (MirrorError("no partner for 'left_hip'"), "why"),
    ],
)
def test_a_model_error_raised_in_a_worker_process_reaches_the_parent_whole(
    error: Exception, field: str
) -> None:
    """A seed's or a compile's process sends its error back pickled: the same kind, message and field,
    not a TypeError from rebuilding it with the message alone."""
    again = pickle.loads(pickle.dumps(error))
    assert type(again) is type(error) and str(again) == str(error)
    assert getattr(again, field) == getattr(error, field)
