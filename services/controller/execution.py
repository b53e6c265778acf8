"""``perform(job_id, delivery)``: one run of a controller job, inside the worker's forked job process
(a policy job's run: ``policy_execution``).

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

import logging
import os
import time
from collections.abc import Mapping

import redis

from neuroanimator.contracts.controller import JobOutcome
from neuroanimator.goals.spec import JobSpec
from services.common.job_worker import Watch, connect_job
from services.controller.policies import POLICY, job_kind
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
    # Before torch loads: its OpenMP pool reads these once.
    # (a policy job may then ask for more: its torch_threads sets the count it trains with)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(s.worker_threads or 1)
    if job_kind(rec.spec) == POLICY:
        from services.controller.policy_execution import perform_policy  # it imports this module

        return perform_policy(store, s, rec, delivery, worker)
    spec = JobSpec.model_validate_json(rec.spec)
    watch = Watch(store, job_id, delivery, worker)
    watch.start()
    clock = Deadline(watch, s.job_timeout_s)
    log.info("job started", extra={"job": job_id, "attempt": rec.attempt, "task": spec.task})
    try:
        from neuroanimator.control.job import run_job
        from neuroanimator.goals.errors import JobSpecError

        try:
            result = run_job(
                spec,
                s.roots(),
                on_progress=ProgressRecorder(store, job_id, rec.attempt),
                should_stop=clock.should_stop,
                threads=s.worker_threads or 1,
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
    return _conclude(store, s, job_id, delivery, worker, watch, clock.timed_out, result)


class Deadline:
    """``should_stop`` of a run: past ``JOB_TIMEOUT_S`` (then ``timed_out``), or asked to stop."""

    def __init__(self, watch: Watch, timeout_s: float) -> None:
        self.watch = watch
        self.deadline = time.monotonic() + timeout_s
        self.timed_out = False

    def should_stop(self) -> bool:
        if time.monotonic() > self.deadline:
            self.timed_out = True
        return self.timed_out or self.watch.stop_requested


class ProgressRecorder:
    """``on_progress`` of a run: each iteration's report (``run_job``'s JSON object, with the iteration
    of the best objective so far added) into Redis, best effort."""

    def __init__(self, store: JobStore, job_id: str, attempt: int) -> None:
        self.store, self.job_id, self.attempt = store, job_id, attempt
        self.best_at: dict[str, object] = {}
        self.unrecorded = 0  # iterations in a row whose progress Redis did not take

    def record(self, p: Mapping[str, object]) -> None:
        """Record one iteration's report (what a run of another kind records: a subclass's)."""
        # the iteration of the best objective so far: where "the best controller so far" comes from
        if p.get("objective") is not None and p.get("objective") == p.get("best_objective"):
            self.best_at["best_iteration"] = p.get("iteration")
        self.store.progress(self.job_id, self.attempt, {**p, **self.best_at})

    def __call__(self, p: Mapping[str, object]) -> None:
        try:
            self.record(p)
        except redis.RedisError as exc:  # progress is best effort; the result is what counts
            if not self.unrecorded:  # once while Redis is away, not at every iteration
                log.warning("progress not recorded", extra={"job": self.job_id, "error": str(exc)})
            self.unrecorded += 1
        else:
            if self.unrecorded:
                log.info("progress recorded again", extra={"job": self.job_id, "missed": self.unrecorded})
            self.unrecorded = 0


def _conclude(
    store: JobStore,
    s: Settings,
    job_id: str,
    delivery: int,
    worker: str,
    watch: Watch,
    timed_out: bool,
    result: JobOutcome,
) -> str:
    """End the job with the run's outcome; a run cancelled by anything but DELETE goes back on the queue
    (its worker shut down), stops (another run took over) or fails (past the time limit)."""
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
