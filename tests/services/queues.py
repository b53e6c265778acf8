"""What the tests of the services with job queues (the controller, the trainer) share: a deployment of
one service on the session's Redis with its own key prefix and RQ queue (so that concurrent test runs
do not see each other's jobs), API clients, real worker processes, and reading event streams."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import redis
from fastapi import FastAPI
from fastapi.testclient import TestClient


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


def sse(text: str) -> list[tuple[str, dict[str, Any]]]:
    """(event, data) of a text/event-stream body."""
    out = []
    for block in text.split("\n\n"):
        fields = dict(line.split(": ", 1) for line in block.splitlines() if ": " in line and line[0] != ":")
        if "event" in fields:
            out.append((fields["event"], json.loads(fields["data"])))
    return out


def drop(r: redis.Redis, prefix: str, queue: str) -> None:
    """Remove a deployment's records and its queue's RQ keys (also of jobs no worker ever took)."""
    keys = list(r.scan_iter(match=f"{prefix}:*", count=1000))
    job_ids = {k.decode().rsplit(":", 1)[1] for k in keys if b":job:" in k}
    for job_id in job_ids:
        keys += list(r.scan_iter(match=f"rq:*{job_id}-*", count=1000))
    keys += list(r.scan_iter(match=f"rq:*{queue}", count=1000))
    for i in range(0, len(keys), 1000):
        r.delete(*keys[i : i + 1000])


class Deployment:
    """One test's deployment of a service with a queue: its environment (``env``, also the workers'),
    API clients (``client``) and worker processes (``worker``), all stopped and their keys removed by
    ``close``. A service's subclass names its worker module and builds its app from settings."""

    service: ClassVar[str]  # e.g. "controller": the Redis prefix test-<service>:<tag>
    worker_module: ClassVar[str]

    def __init__(self, redis_url: str, tmp: Path, env: dict[str, str]) -> None:
        tag = uuid.uuid4().hex[:10]
        self.tag = tag
        self.redis_url = redis_url
        self.tmp = tmp
        self.env: dict[str, str] = {
            "REDIS_URL": redis_url,
            "REDIS_PREFIX": f"test-{self.service}:{tag}",
            "QUEUE_NAME": f"test-{self.service}-{tag}",
            "API_KEYS": "",
            "API_KEY_SECRET": "test-secret",
            "RESULT_TTL_S": "600",
            "QUEUED_TTL_S": "600",
            "LOG_LEVEL": "info",
            **env,
        }
        self.workers: list[subprocess.Popen[bytes]] = []
        self.clients: list[TestClient] = []
        self.r = redis.Redis.from_url(redis_url)

    def app(self, **kw: Any) -> FastAPI:
        raise NotImplementedError

    def client(self, **kw: Any) -> TestClient:
        """A client of the API with these settings (besides ``env``), closed by ``close``."""
        c = TestClient(self.app(**kw))
        c.__enter__()
        self.clients.append(c)
        return c

    def name(self, short: str) -> str:
        """A worker name unique to this test: RQ refuses a name whose earlier holder died by SIGKILL
        until its registration expires."""
        return f"{short}-{self.tag}"

    def worker(self, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
        """A worker process (``python -m <worker_module>``); its log goes to a file."""
        log = open(self.tmp / f"worker-{len(self.workers)}.log", "wb")  # noqa: SIM115
        proc = subprocess.Popen(
            [sys.executable, "-m", self.worker_module, *args],
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
        drop(self.r, self.env["REDIS_PREFIX"], self.env["QUEUE_NAME"])
        self.r.close()
