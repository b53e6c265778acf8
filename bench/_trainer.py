"""Shared by the benchmarks that train through the service: a trainer API and one training worker on a
registry of their own, with Redis keys under a prefix of their own that are removed afterwards."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import redis
from _server import serve


@dataclass
class Trainer:
    url: str  # the trainer API
    registry: Path  # where its worker writes artifacts
    env: dict[str, str]  # REDIS_URL, REDIS_PREFIX, QUEUE_NAME of this trainer
    ids: list[str] = field(default_factory=list)  # the trainings uploaded

    def upload(self, model: Path, **fields: str) -> tuple[dict[str, Any], float]:
        """POST /trainings with ``model`` (an XML or an archive) and form ``fields``: (the answer,
        seconds until it came)."""
        data = model.read_bytes()
        t0 = time.perf_counter()
        r = httpx.post(f"{self.url}/trainings", files={"file": (model.name, data)}, data=fields, timeout=60)
        elapsed = time.perf_counter() - t0
        r.raise_for_status()
        answer: dict[str, Any] = r.json()
        self.ids.append(answer["id"])
        return answer, elapsed

    def status(self, tid: str) -> dict[str, Any]:
        got: dict[str, Any] = httpx.get(f"{self.url}/trainings/{tid}", timeout=10).json()
        return got


@contextlib.contextmanager
def trainer(redis_url: str, log_dir: Path, registry: Path | None = None) -> Iterator[Trainer]:
    """A trainer API and one training worker (``python -m services.trainer.worker``, at its default lower
    priority) on ``registry`` (default: a temporary one, removed afterwards). On exit both stop, every
    training still running is cancelled, and this trainer's Redis keys are removed."""
    tag = uuid.uuid4().hex[:8]
    ids: list[str] = []
    prefix, queue = f"bench-trainer:{tag}", f"bench-trainer-{tag}"
    env = {"REDIS_URL": redis_url, "REDIS_PREFIX": prefix, "QUEUE_NAME": queue}
    own = registry is None
    root = Path(tempfile.mkdtemp(prefix="bench-registry-")) if registry is None else registry
    try:
        with serve(str(root), "services.trainer", ready="/healthz", **env) as (url, _pid):
            log = (log_dir / "training-worker.log").open("wb")
            worker = subprocess.Popen(
                [sys.executable, "-m", "services.trainer.worker"],
                env={**os.environ, **env, "ARTIFACTS_DIR": str(root)},
                cwd=log_dir,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
            t = Trainer(url, root, env, ids)
            try:
                yield t
            finally:
                for tid in t.ids:
                    with contextlib.suppress(httpx.HTTPError):
                        httpx.delete(f"{url}/trainings/{tid}", timeout=10)
                worker.terminate()
                worker.wait(30)
                log.close()
    finally:
        if own:
            shutil.rmtree(root, ignore_errors=True)
        conn = redis.Redis.from_url(redis_url)
        keys = [*conn.scan_iter(match=f"{prefix}:*"), *conn.scan_iter(match=f"rq:*{queue}*")]
        for tid in ids:
            keys += conn.scan_iter(match=f"rq:*{tid}-*")
        if keys:
            conn.delete(*keys)
        conn.close()
