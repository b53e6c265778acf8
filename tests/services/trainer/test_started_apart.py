"""The trainer started as the README says, apart from the stack: ``python -m services.trainer`` and
``python -m services.trainer.worker`` in one folder, with the data directory given by a relative path
(``DATA_DIR=data``). A training runs in a staging folder of its own: once, every
training failed so ("'artifacts/.trainer/uploads/<id>/...' does not exist")."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from services.stack import free_port
from tests.services.trainer.trn import TINY, TINYBOT, Trainer, wait_for, zipped

ROOT = Path(__file__).resolve().parents[3]


def test_api_and_worker_started_apart_with_a_relative_registry(
    redis_url: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    trn = Trainer(redis_url, tmp_path_factory.mktemp("apart"), DATA_DIR="data", JOB_TIMEOUT_S="120")
    port = free_port()
    env = {
        **os.environ,
        **trn.env,
        "PORT": str(port),
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    with (trn.tmp / "api.log").open("wb") as log:
        api = subprocess.Popen(
            [sys.executable, "-m", "services.trainer"], cwd=trn.tmp, env=env, stdout=log, stderr=log
        )
    trn.worker(env={"PYTHONPATH": env["PYTHONPATH"]})
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{url}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert api.poll() is None and time.monotonic() < deadline, (trn.tmp / "api.log").read_text()
            time.sleep(0.2)
        r = httpx.post(
            f"{url}/trainings", files={"file": ("tinybot.zip", zipped(TINYBOT))}, data=TINY, timeout=60
        )
        assert r.status_code == 202, r.text
        job = r.json()["id"]

        def ended() -> dict[str, object] | None:
            body: dict[str, object] = httpx.get(f"{url}/trainings/{job}", timeout=10).json()
            return body if body["status"] in ("succeeded", "failed", "cancelled") else None

        done = wait_for("the training", ended, timeout=180, every=0.5)
        assert done["status"] == "succeeded", (done, trn.logs()[-2000:])
        assert (trn.tmp / "data" / "tinybot" / "latest").is_file()
    finally:
        api.terminate()
        api.wait(20)
        trn.close()
