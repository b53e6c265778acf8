"""The catalog (``GET /models``, ``GET /models/{model}``), and new artifact versions served without a
restart."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

from fastapi.testclient import TestClient

from services.emulator.app import create_app
from services.emulator.settings import Settings


def test_models_lists_loaded_emulators(client: TestClient) -> None:
    r = client.get("/models")
    assert r.status_code == 200
    models = {m["model"]: m for m in r.json()["models"]}
    assert {"pendulum-active", "lander"} <= set(models)
    lander = models["lander"]
    assert (lander["state_size"], lander["num_controls"], lander["num_forces"]) == (13, 4, 0)
    assert lander["substeps"] == 10
    assert lander["version"] in lander["versions"]


def test_model_detail_has_the_manifest(client: TestClient) -> None:
    r = client.get("/models/lander")
    assert r.status_code == 200
    d = r.json()
    kinds = [g["kind"] for g in d["layout"]]
    assert "quaternion" in kinds
    assert len(d["state_labels"]) == 13
    assert [c["low"] <= c["high"] for c in d["controls"]] == [True] * 4
    assert d["super_timestep"] > d["timestep"] > 0
    assert "one_step" in json.dumps(d["metrics"]) or d["metrics"]


def test_unknown_model_and_version_are_404(client: TestClient) -> None:
    r = client.get("/models/nosuch")
    assert r.status_code == 404
    body = r.json()
    assert body["error"] == "unknown_model"
    assert "'nosuch'" in body["message"] and "pendulum-active" in body["message"]
    r = client.get("/models/lander", params={"version": "n10-nope"})
    assert r.status_code == 404
    assert r.json()["error"] == "unknown_version"
    assert "'n10-nope'" in r.json()["message"]


def _copy_as_new_version(root: Path, model: str, new: str) -> None:
    """A new version folder (same graph), then the ``latest`` pointer moved to it atomically."""
    model_dir = root / model
    old = (model_dir / "latest").read_text().strip()
    shutil.copytree(model_dir / old, model_dir / new)
    manifest = json.loads((model_dir / new / "manifest.json").read_text())
    manifest["version"] = new
    (model_dir / new / "manifest.json").write_text(json.dumps(manifest))
    (model_dir / ".tmp-latest").write_text(new + "\n")
    os.replace(model_dir / ".tmp-latest", model_dir / "latest")


def test_new_version_is_served_without_restart_and_sessions_keep_theirs(
    service_root: Path, tmp_path: Path, make_settings: Callable[..., Settings]
) -> None:
    root = tmp_path / "reg"
    shutil.copytree(service_root, root)
    with TestClient(create_app(make_settings(artifacts_dir=root))) as c:
        old = c.get("/models/pendulum-active").json()["version"]
        sid = c.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
        _copy_as_new_version(root, "pendulum-active", "n10-later")
        d = c.get("/models/pendulum-active").json()
        assert d["version"] == "n10-later"
        assert set(d["versions"]) == {old, "n10-later"}
        assert c.get(f"/sessions/{sid}").json()["version"] == old
        r = c.post(f"/sessions/{sid}/step", json={"controls": [0, 0, 0]})
        assert r.status_code == 200
        new = c.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()
        assert new["version"] == "n10-later"
        pinned = c.post("/sessions", json={"model": "pendulum-active", "version": old, "seed": 1}).json()
        assert pinned["version"] == old
