"""The trainer's share of the services' hardening, as the controller's tests check it there: its queue
carries JSON (never a pickle), its live-worker count follows a SIGKILL, a Redis that is down is 503
without saying where Redis is, and ``/readyz`` names a folder it cannot write by its setting, not its
path (it answers anybody)."""

from __future__ import annotations

import json
import socket
import zlib
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from tests.services.controller.ctl import kill
from tests.services.trainer.trn import TINY, TINYBOT, Trainer, upload, wait_for, zipped


@pytest.fixture(name="trn")
def trn_fixture(redis_url: str, tmp_path: Path) -> Iterator[Trainer]:
    t = Trainer(redis_url, tmp_path)
    try:
        yield t
    finally:
        t.close()


def _workers(api: TestClient) -> int:
    r = api.get("/readyz")  # 503 "no workers" while none is heard from
    assert r.status_code == 200 or r.json()["status"] == "no workers", r.text
    return int(r.json()["workers"])


def test_the_queue_is_json_and_a_killed_worker_drops_out_of_the_count(trn: Trainer) -> None:
    api = trn.client()
    r = upload(api, "tinybot.zip", zipped(TINYBOT), **TINY)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    raw = trn.r.hget(f"rq:job:{job_id}-1", "data")
    assert isinstance(raw, bytes)
    func, _instance, args, _kwargs = json.loads(zlib.decompress(raw))  # JSON, not a pickle
    assert func == "services.trainer.execution.perform" and args == [job_id, 1]
    assert api.delete(f"/trainings/{job_id}").json()["status"] == "cancelled"  # nothing to train

    worker = trn.worker("--name", trn.name("w"))
    wait_for("the worker", lambda: _workers(api) == 1, timeout=60)
    kill(worker.pid)
    worker.wait(10)
    wait_for("no worker", lambda: _workers(api) == 0, timeout=trn.settings().worker_alive_s() + 5)
    assert "trainer_workers 0.0" in api.get("/metrics").text


def test_redis_down_is_503_without_saying_where_redis_is(trn: Trainer) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])  # nothing listens there once closed
    api = trn.client(redis_url=f"redis://127.0.0.1:{port}/0", redis_timeout_s=0.5)
    calls = [
        ("GET", "/trainings"),
        ("GET", "/trainings/abc"),
        ("GET", "/trainings/abc/events"),
        ("DELETE", "/trainings/abc"),
        ("GET", "/models"),
    ]
    for method, path in calls:
        r = api.request(method, path)
        assert r.status_code == 503 and r.json()["error"] == "redis_unavailable", (path, r.text)
        assert str(port) not in r.text and "127.0.0.1" not in r.text
    r = upload(api, "tinybot.zip", zipped(TINYBOT), **TINY)
    assert r.status_code == 503 and str(port) not in r.text, r.text
    ready = api.get("/readyz")
    assert ready.status_code == 503 and ready.json()["status"] == "redis unavailable"
    assert str(port) not in ready.text and "127.0.0.1" not in ready.text
    assert "trainer_redis_up 0.0" in api.get("/metrics").text


def test_readyz_names_an_unwritable_folder_by_its_setting(trn: Trainer, tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    api = trn.client(data_dir=blocker / "data")
    r = api.get("/readyz")
    assert r.status_code == 503 and r.json()["status"] == "not writable", r.text
    assert "DATA_DIR" in r.json()["message"] and str(tmp_path) not in r.text
