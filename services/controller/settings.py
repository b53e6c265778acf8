"""Controller settings, read from the environment (``REDIS_URL=... MAX_QUEUE=...``); the API and the
workers read the same variables, so one environment file configures both."""

from __future__ import annotations

from pydantic import Field

from services.common.jobs import QueueSettings
from services.common.settings import Port


class Settings(QueueSettings):
    """Every knob of the controller API and its workers (beside host, port, log level, API keys and CORS
    origins, and the queue's: ``QueueSettings``); environment variables have the upper-case names."""

    redis_prefix: str = Field(
        "neuroanimator:controller", min_length=1, description="prefix of the service's own Redis keys"
    )
    queue_name: str = Field(
        "neuroanimator-controller",
        pattern=r"^[A-Za-z0-9_.:-]+$",
        description="the RQ queue (RQ's keys are rq:queue:<name>, rq:wip:<name>, ...)",
    )
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
    max_list: int = Field(200, ge=1, description="most jobs listed by GET /jobs")
    policy_max_seconds: float = Field(
        1800.0, ge=5.0, description="the longest training budget a policy job may ask for (POST /policies)"
    )
    policy_overhead_s: float = Field(
        300.0,
        gt=0.0,
        description="time a policy job may take beyond its budget (drawing goals on MuJoCo, the final "
        "evaluation, storing): past its budget plus this it stops, ends failed, best policy stored",
    )
    # workers
    worker_threads: int | None = Field(
        None,
        ge=1,
        le=64,
        description="torch threads of one job; unset, a policy job takes its task's own (the acrobot's "
        "two, at most the machine's cores) and every other job one",
    )
    port: Port = 8001
