"""Helpers and fixtures of the controller tests: a real Redis (the session's ``redis_url``), real
worker processes, and the API in a ``TestClient``. Each test gets its own key prefix and RQ queue,
so concurrent test runs on one Redis do not see each other's jobs.

Jobs run the real built-in tasks on the committed emulators in ``artifacts/`` (n = 50).
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from services.controller.app import create_app
from services.controller.settings import Settings
from tests.services.queues import Deployment, wait_for

__all__ = [
    "ARTIFACTS",
    "QUICK",
    "Controller",
    "ctl_fixture",
    "ended",
    "job",
    "kill",
    "long_job",
    "maps_torch",
    "wait_for",
]

ROOT = Path(__file__).resolve().parents[3]
ARTIFACTS = ROOT / "artifacts"
# A short job: pendulum-swing, a few iterations, no early stop.
QUICK = {"task": "pendulum-swing", "optimizer": {"max_iterations": 3}}


def long_job(iterations: int = 10_000) -> dict[str, Any]:
    """A job that runs ``iterations`` (about 20 ms each) unless stopped: steps so small that the line
    search always finds a lower objective, no tolerance, no stop on success; one start, no global
    search, so every iteration is one plain descent step."""
    return {
        "task": "pendulum-swing",
        "optimizer": {
            "starts": 1,
            "global_generations": 0,
            "learning_rate": 0.001,
            "max_iterations": iterations,
            "tolerance": 0.0,
            "stop_on_success": False,
        },
    }


class Controller(Deployment):
    """One test's controller deployment: settings, API clients and worker processes."""

    service = "controller"
    worker_module = "services.controller.worker"

    def __init__(self, redis_url: str, tmp: Path) -> None:
        super().__init__(
            redis_url,
            tmp,
            {
                "ARTIFACTS_DIR": str(ARTIFACTS),
                "LEASE_TTL_S": "1.5",
                "REAP_INTERVAL_S": "0.5",
                "JOB_RETRIES": "2",
                "WORKER_THREADS": "1",
            },
        )

    def settings(self, **kw: Any) -> Settings:
        base = {k.lower(): v for k, v in self.env.items()}
        return Settings(**{**base, **kw})

    def app(self, **kw: Any) -> FastAPI:
        return create_app(self.settings(**kw))


@pytest.fixture(name="ctl")
def ctl_fixture(redis_url: str, tmp_path: Path) -> Iterator[Controller]:
    """A fresh controller deployment on the session's Redis (REDIS_URL, 127.0.0.1:6379, or started)."""
    c = Controller(redis_url, tmp_path)
    try:
        yield c
    finally:
        c.close()


def job(client: TestClient, job_id: str) -> dict[str, Any]:
    r = client.get(f"/jobs/{job_id}")
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    return out


def ended(client: TestClient, job_id: str, timeout: float = 90.0) -> dict[str, Any]:
    """The job once it reached a final status."""
    out: dict[str, Any] = wait_for(
        f"job {job_id} to end",
        lambda: (j := job(client, job_id))["status"] in ("succeeded", "failed", "cancelled") and j,
        timeout,
        every=0.2,
    )
    return out


def kill(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def maps_torch(pid: int) -> bool:
    """Whether a live process has PyTorch's library mapped (it imported torch)."""
    return "libtorch" in Path(f"/proc/{pid}/maps").read_text()
