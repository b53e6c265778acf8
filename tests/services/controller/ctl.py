"""Helpers and fixtures of the controller tests: a real Redis (the session's ``redis_url``), real
worker processes, and the API in a ``TestClient``. Each test gets its own key prefix and RQ queue,
so concurrent test runs on one Redis do not see each other's jobs.

Jobs run the real built-in tasks on the committed emulators in ``artifacts/`` (n = 50).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient

from services.controller.app import create_app
from services.controller.settings import Settings

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


def wait_for(what: str, check: Callable[[], Any], timeout: float = 60.0, every: float = 0.05) -> Any:
    """Poll ``check`` until it returns something truthy; fail after ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while True:
        got = check()
        if got:
            return got
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(every)


class Controller:
    """One test's controller deployment: settings, API clients and worker processes."""

    def __init__(self, redis_url: str, tmp: Path) -> None:
        tag = uuid.uuid4().hex[:10]
        self.tag = tag
        self.redis_url = redis_url
        self.tmp = tmp
        self.env: dict[str, str] = {
            "REDIS_URL": redis_url,
            "REDIS_PREFIX": f"test-controller:{tag}",
            "QUEUE_NAME": f"test-controller-{tag}",
            "ARTIFACTS_DIR": str(ARTIFACTS),
            "API_KEYS": "",
            "API_KEY_SECRET": "test-secret",
            "RESULT_TTL_S": "600",
            "QUEUED_TTL_S": "600",
            "LEASE_TTL_S": "1.5",
            "REAP_INTERVAL_S": "0.5",
            "JOB_RETRIES": "2",
            "WORKER_THREADS": "1",
            "LOG_LEVEL": "info",
        }
        self.workers: list[subprocess.Popen[bytes]] = []
        self.clients: list[TestClient] = []
        self.r = redis.Redis.from_url(redis_url)

    def settings(self, **kw: Any) -> Settings:
        base = {k.lower(): v for k, v in self.env.items()}
        return Settings(**{**base, **kw})

    def client(self, **kw: Any) -> TestClient:
        c = TestClient(create_app(self.settings(**kw)))
        c.__enter__()
        self.clients.append(c)
        return c

    def name(self, short: str) -> str:
        """A worker name unique to this test: RQ refuses a name whose earlier holder died by SIGKILL
        until its registration expires."""
        return f"{short}-{self.tag}"

    def worker(self, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
        """A worker process (``python -m services.controller.worker``); its log goes to a file."""
        log = open(self.tmp / f"worker-{len(self.workers)}.log", "wb")  # noqa: SIM115
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.controller.worker", *args],
            env={**os.environ, **self.env, **(env or {})},
            cwd=self.tmp,  # MuJoCo writes MUJOCO_LOG.TXT into the working directory on warnings
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        self.workers.append(proc)
        return proc

    def logs(self) -> str:
        return "\n".join(p.read_text(errors="replace") for p in sorted(self.tmp.glob("worker-*.log")))

    def close(self) -> None:
        for c in self.clients:
            c.__exit__(None, None, None)
        for p in self.workers:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in self.workers:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        # the job processes of killed workers (tests kill them with SIGKILL, and clean up here)
        prefix, queue = self.env["REDIS_PREFIX"], self.env["QUEUE_NAME"]
        keys = list(self.r.scan_iter(match=f"{prefix}:*"))
        job_ids = {k.decode().rsplit(":", 1)[1] for k in keys if b":job:" in k}
        for job_id in job_ids:
            keys += list(self.r.scan_iter(match=f"rq:*{job_id}-*"))
        keys += list(self.r.scan_iter(match=f"rq:*{queue}"))
        if keys:
            self.r.delete(*keys)
        self.r.close()


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
