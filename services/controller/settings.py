"""Controller settings, read from the environment (``REDIS_URL=... MAX_QUEUE=...``); the API and the
workers read the same variables, so one environment file configures both."""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import Field

from services.common.settings import ApiSettings, Port


class Settings(ApiSettings):
    """Every knob of the controller API and its workers (beside host, port, log level, API keys and CORS
    origins); environment variables have the upper-case names."""

    redis_url: str = Field("redis://127.0.0.1:6379/0", description="the Redis that holds the queue and jobs")
    redis_prefix: str = Field(
        "neuroanimator:controller", min_length=1, description="prefix of the service's own Redis keys"
    )
    queue_name: str = Field(
        "neuroanimator-controller",
        pattern=r"^[A-Za-z0-9_.:-]+$",
        description="the RQ queue (RQ's keys are rq:queue:<name>, rq:wip:<name>, ...)",
    )
    redis_timeout_s: float = Field(2.0, gt=0.0, description="connect and command timeout of the API's Redis")
    artifacts_dir: Path = Path("artifacts")
    max_body_bytes: int = Field(
        1024 * 1024,
        ge=1024,
        description="the largest request body (a job's spec): 413 beyond, before it is read or parsed",
    )
    max_queue: int = Field(100, ge=1, description="queued (not yet running) jobs; beyond, POST /jobs is 503")
    job_timeout_s: float = Field(
        600.0,
        gt=0.0,
        description="time limit of one job: it then stops and ends failed, best controller kept",
    )
    job_timeout_grace_s: float = Field(
        30.0, gt=0.0, description="past the limit by this much, the job's process is killed (hard limit)"
    )
    job_retries: int = Field(
        2, ge=0, le=20, description="re-runs of a job whose process crashed, raised or was abandoned"
    )
    result_ttl_s: int = Field(
        86_400, ge=1, description="a finished job (status, result, events) is kept this long"
    )
    queued_ttl_s: int = Field(7 * 86_400, ge=1, description="an unfinished job's records expire after this")
    max_list: int = Field(200, ge=1, description="most jobs listed by GET /jobs")
    sse_keepalive_s: float = Field(15.0, gt=0.0, description="an SSE comment is sent when idle this long")
    # workers
    worker_threads: int = Field(1, ge=1, le=64, description="torch threads of one job")
    lease_ttl_s: float = Field(
        15.0,
        gt=0.0,
        description="a running job renews its lease this often ×3; an expired lease means a dead worker",
    )
    reap_interval_s: float = Field(
        5.0,
        gt=0.0,
        description="how often an idle worker looks for jobs whose lease expired and re-queues them",
    )
    port: Port = 8001

    def heartbeat_s(self) -> int:
        """How often a worker reports itself alive: RQ's dequeue timeout while idle (the reap interval)
        and its job monitoring interval while a job runs (the lease's time to live), whole seconds."""
        return max(1, min(30, math.ceil(self.lease_ttl_s)), math.ceil(self.reap_interval_s))

    def worker_alive_s(self) -> float:
        """A worker not heard from for this long is counted gone (killed, or cut off from Redis)."""
        return 3.0 * self.heartbeat_s()
