"""Helpers and fixtures of the trainer tests: a real Redis (the session's ``redis_url``), real worker
processes, and the API in a ``TestClient``, over an artifact registry of the test's own. Each deployment
gets its own key prefix and RQ queue, so concurrent test runs on one Redis do not see each other's.

Models are the project's own small model folder (tests/data/tinybot: an include, an OBJ mesh and a
texture in assets/) and variants of it written by the tests.
"""

from __future__ import annotations

import contextlib
import io
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.testclient import TestClient

from neuroanimator.artifacts import registry
from services.trainer.app import create_app
from services.trainer.settings import Settings
from tests.helpers import uvicorn_serving
from tests.services.queues import Deployment, wait_for

__all__ = [
    "KEYS",
    "TINY",
    "TINYBOT",
    "Trainer",
    "auth",
    "ended",
    "serve",
    "tarred",
    "upload",
    "wait_for",
    "zipped",
]

ROOT = Path(__file__).resolve().parents[3]
TINYBOT = ROOT / "tests" / "data" / "tinybot"
# A training as small as the trainer allows: it takes seconds.
TINY = {
    "super_step": "10",
    "examples": "200",
    "epochs": "3",
    "hidden": "8",
    "rollout_steps": "0",
    "force": "true",
}
KEYS = {"API_KEYS": "key-a,key-b", "OPERATOR_KEYS": "key-op", "API_KEY_SECRET": "test-secret"}


def auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def zipped(folder: Path, top: str = "tinybot", extra: dict[str, bytes] | None = None) -> bytes:
    """A .zip of a model folder (its files under ``top/``), plus ``extra`` entries by name."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(folder.rglob("*")):
            if p.is_file():
                zf.write(p, f"{top}/{p.relative_to(folder).as_posix()}")
        for name, data in (extra or {}).items():
            zf.writestr(name, data)
    return buf.getvalue()


def tarred(members: dict[str, bytes], links: dict[str, str] | None = None) -> bytes:
    """A .tar.gz of files (name -> content) and symbolic links (name -> target)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
        for name, target in (links or {}).items():
            info = tarfile.TarInfo(name)
            info.type = tarfile.SYMTYPE
            info.linkname = target
            tf.addfile(info)
    return buf.getvalue()


class Trainer(Deployment):
    """One test's trainer deployment: settings, API clients, training workers and its own registry."""

    service = "trainer"
    worker_module = "services.trainer.worker"

    def __init__(self, redis_url: str, tmp: Path, **env: str) -> None:
        self.data = tmp / "data"  # the data directory: uploads and their trainings
        self.defaults = tmp / "defaults"  # the committed defaults' place: read, never written
        self.data.mkdir(exist_ok=True)
        self.defaults.mkdir(exist_ok=True)
        folders = {"DATA_DIR": str(self.data), "ARTIFACTS_DIR": str(self.defaults)}
        defaults = {"LEASE_TTL_S": "2", "REAP_INTERVAL_S": "0.5", "EVAL_TRIALS": "2", "EVAL_SECONDS": "2"}
        super().__init__(redis_url, tmp, {**folders, **defaults, **env})

    def settings(self, **kw: Any) -> Settings:
        base = {k.lower(): v for k, v in self.env.items()}
        return Settings(**{**base, **kw})

    def app(self, **kw: Any) -> FastAPI:
        return create_app(self.settings(**kw))

    def models(self) -> list[str]:
        """The model folders in the registry (claimed names included; the policies' folder is none)."""
        return sorted(p.name for p in self.data.iterdir() if registry.name_problem(p.name) is None)


def upload(client: TestClient, filename: str, data: bytes, key: str | None = None, **fields: str) -> Any:
    """``POST /trainings`` of one file with the form's fields."""
    headers = auth(key) if key else {}
    return client.post("/trainings", files={"file": (filename, data)}, data=fields, headers=headers)


def ended(
    client: TestClient, training_id: str, timeout: float = 120.0, key: str | None = None
) -> dict[str, Any]:
    """The training once it reached a final status."""

    def check() -> dict[str, Any] | None:
        r = client.get(f"/trainings/{training_id}", headers=auth(key) if key else {})
        assert r.status_code == 200, r.text
        out: dict[str, Any] = r.json()
        return out if out["status"] in ("succeeded", "failed", "cancelled") else None

    found: dict[str, Any] = wait_for(f"training {training_id} to end", check, timeout, every=0.25)
    return found


@contextlib.contextmanager
def serve(app: FastAPI) -> Iterator[str]:
    """The app under a real uvicorn on a free port (for concurrent clients); its base URL."""
    with uvicorn_serving(app) as port:
        yield f"http://127.0.0.1:{port}"
