"""``perform(job_id, delivery)``: one run of a controller job, inside the worker's forked job process.

This is the only module of the service that loads PyTorch (through ``neuroanimator.control``), and it
does so here, after the fork, with the thread count set first. While ``run_job`` optimises, a small
thread renews the job's lease in Redis and reads its flags (cancel, worker shutdown, superseded), which
``should_stop`` returns; every iteration's progress goes to Redis as it happens.

How a run ends:
- ``run_job`` returned: its result is the job's (succeeded, or failed with the reason and the best
  finite controller so far, e.g. when the optimisation diverged);
- cancelled by DELETE: cancelled, with the best controller so far;
- past ``JOB_TIMEOUT_S``: failed ("time limit"), with the best controller so far;
- its worker is shutting down: back on the queue, without counting as a failure;
- an exception (or RQ's hard time limit): back on the queue while ``JOB_RETRIES`` allows, else failed.
"""

from __future__ import annotations

import json
import logging
import os
import time
from typing import Any

import redis

from neuroanimator.contracts.controller import JobOutcome
from services.common.job_worker import Watch, connect_job
from services.controller.settings import Settings
from services.controller.store import JobStore

log = logging.getLogger(__name__)

_settings: Settings | None = None


def configure(settings: Settings) -> None:
    """Set the settings of the jobs this process (and the job processes it forks) will run."""
    global _settings
    _settings = settings


def settings() -> Settings:
    """The worker's settings (set by the worker before it forks), else read from the environment."""
    return _settings if _settings is not None else Settings()


def perform(job_id: str, delivery: int) -> str:
    """Run delivery ``n`` of a job; returns how it ended (for RQ's log)."""
    s = settings()
    store = JobStore(connect_job(s), s)
    worker = os.environ.get("RQ_WORKER_ID", f"pid-{os.getpid()}")
    rec, why = store.start(job_id, delivery, worker, os.getpid())
    if rec is None:
        log.info("job not run", extra={"job": job_id, "delivery": delivery, "reason": why})
        return why
    attempt = int(rec["attempt"])
    # Before torch loads: its OpenMP pool reads these once.
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(s.worker_threads)
    spec: dict[str, Any] = json.loads(rec["spec"])
    watch = Watch(store, job_id, delivery, worker)
    watch.start()
    deadline = time.monotonic() + s.job_timeout_s
    timed_out = False

    def should_stop() -> bool:
        nonlocal timed_out
        if time.monotonic() > deadline:
            timed_out = True
        return timed_out or watch.stop_requested

    best_at: dict[str, Any] = {}
    unrecorded = 0  # iterations in a row whose progress Redis did not take

    def on_progress(p: dict[str, Any]) -> None:
        nonlocal unrecorded
        # the iteration of the best objective so far: where "the best controller so far" comes from
        if p.get("objective") is not None and p.get("objective") == p.get("best_objective"):
            best_at["best_iteration"] = p.get("iteration")
        try:
            store.progress(job_id, attempt, {**p, **best_at})
        except redis.RedisError as exc:  # progress is best effort; the result is what counts
            if not unrecorded:  # once while Redis is away, not at every iteration
                log.warning("progress not recorded", extra={"job": job_id, "error": str(exc)})
            unrecorded += 1
        else:
            if unrecorded:
                log.info("progress recorded again", extra={"job": job_id, "missed": unrecorded})
            unrecorded = 0

    log.info("job started", extra={"job": job_id, "attempt": attempt, "task": spec.get("task")})
    try:
        from neuroanimator.control.job import run_job
        from neuroanimator.goals.errors import JobSpecError

        try:
            result = run_job(
                spec,
                s.roots(),
                on_progress=on_progress,
                should_stop=should_stop,
                threads=s.worker_threads,
            )
        except (
            JobSpecError
        ) as exc:  # e.g. this worker's artifacts lack the model: a re-run fails the same way
            store.finish(job_id, delivery, JobOutcome(status="failed", reason=f"{exc.field}: {exc}"))
            return "failed"
    except Exception as exc:
        outcome = store.requeue_or_fail(job_id, delivery, f"{type(exc).__name__}: {exc}", count_failure=True)
        log.exception("job raised", extra={"job": job_id, "outcome": outcome})
        raise
    finally:
        watch.stop()

    if result.status == "cancelled" and not watch.cancelled:
        if watch.superseded:  # another run of this job took over (this worker had seemed dead)
            return "superseded"
        if watch.yielding:
            store.requeue_or_fail(job_id, delivery, f"worker {worker} shut down", count_failure=False)
            return "requeued"
        if timed_out:
            reason = (
                f"time limit of {s.job_timeout_s:g} s (JOB_TIMEOUT_S) reached after {result.iterations} "
                "iterations; the best controller so far is kept"
            )
            result = result.model_copy(update={"status": "failed", "reason": reason})
    store.finish(job_id, delivery, result)
    return result.status
