"""A worker of a job queue (``services.common.jobs``): RQ's forking worker, one process per job, plus
what the services need beyond RQ; and ``Watch``, the thread that keeps a running job's lease.

Beyond RQ a ``JobWorker``:
- **Re-queues abandoned jobs.** A running job renews a lease in Redis; while idle, the worker looks
  every ``REAP_INTERVAL_S`` for running jobs whose lease expired (their worker was killed, lost its
  machine or its Redis connection) and puts them back on the queue, up to ``JOB_RETRIES`` times.
  RQ 2's own check (``StartedJobRegistry.cleanup``) only runs in its 10-minute maintenance and only
  notices a dead job a minute or more after its last heartbeat, so it serves as a backstop only.
- **Shuts down cleanly on SIGTERM** (or Ctrl-C): a running job is asked to stop soon and goes back
  on the queue for another worker; the worker then exits. A second signal kills the job at once
  (RQ's cold shutdown); the lease then brings it back.
- **Reports itself alive** with each of RQ's heartbeats (``JobStore.worker_seen``), so that the count
  of ``/readyz`` and the metrics drops a killed worker within ``WORKER_ALIVE_S`` and finds every
  worker again after Redis lost its data (RQ's own registry only knows workers from their start,
  and keeps a killed one for minutes).
- **Runs only its service's deliveries**: the queue's messages are JSON (not RQ's default pickle), and
  a job that names any function but the store's ``perform`` is refused, not run, so that whoever can
  write to Redis cannot make a worker run code of their choosing.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import socket
import sys
import threading
import time
import uuid
from collections.abc import Sequence
from typing import Any

import redis
from rq import Queue, Worker
from rq.job import Job
from rq.serializers import JSONSerializer
from rq.worker import BaseWorker

from services.common.jobs import JobStore, QueueSettings, rq_id

log = logging.getLogger("services.common.job_worker")


class JobWorker(Worker):
    """RQ's forking worker plus the lease reaper and the job-yielding shutdown."""

    def __init__(self, queues: Sequence[Queue], *, store: JobStore, **kw: Any) -> None:
        # before RQ's __init__, which reads dequeue_timeout
        self.store = store
        self.reap_every = store.settings.reap_interval_s
        self._reaped_at = 0.0
        super().__init__(list(queues), **kw)

    @property
    def dequeue_timeout(self) -> int:
        # RQ blocks this long waiting for a job; waking at the reap interval lets an idle worker reap
        # (and send its heartbeat)
        return max(1, math.ceil(self.reap_every))

    @property
    def should_run_maintenance_tasks(self) -> bool:
        return self._reap_due() or bool(BaseWorker.should_run_maintenance_tasks.fget(self))  # type: ignore[attr-defined]

    def _reap_due(self) -> bool:
        return time.monotonic() - self._reaped_at >= self.reap_every

    def run_maintenance_tasks(self) -> None:
        if self._reap_due():
            self._reaped_at = time.monotonic()
            try:
                reaped = self.store.reap()
            except redis.RedisError as exc:
                log.warning("reaper could not reach Redis", extra={"error": str(exc)})
            else:
                if reaped:
                    log.warning("re-queued abandoned jobs", extra={"jobs": reaped, "worker": self.name})
        if BaseWorker.should_run_maintenance_tasks.fget(self):  # type: ignore[attr-defined]
            super().run_maintenance_tasks()

    def heartbeat(self, timeout: int | None = None, pipeline: Any = None) -> None:
        super().heartbeat(timeout, pipeline)
        self.store.worker_seen(self.name, pipeline)

    def execute_job(self, job: Job, queue: Queue) -> None:
        """Run one of the store's deliveries; refuse (fail in RQ, run nothing) a job naming another
        function."""
        perform = self.store.perform
        try:
            func = job.func_name
        except Exception as exc:  # a payload that is not our JSON
            func = f"<unreadable: {type(exc).__name__}>"
        if func != perform:
            log.error(
                f"refused a queued job that does not run {perform}",
                extra={"rq_job": job.id, "func": func},
            )
            self.handle_job_failure(job, queue=queue, exc_string=f"refused: {func} is not {perform}")
            return
        super().execute_job(job, queue)

    def request_stop(self, signum: Any, frame: Any) -> None:
        """Warm shutdown that does not wait for a long job: the job yields and is re-queued."""
        current = self.get_current_job_id()
        if current:
            job_id = current.rsplit("-", 1)[0]
            try:
                self.store.set_yield(job_id)
                log.info("shutting down: the running job goes back on the queue", extra={"job": job_id})
            except redis.RedisError as exc:
                log.warning("could not ask the job to yield", extra={"job": job_id, "error": str(exc)})
        super().request_stop(signum, frame)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The command-line options every worker takes (``--threads`` is the service's own)."""
    p.add_argument("--burst", action="store_true", help="run the queued jobs, then exit (tests, batch runs)")
    p.add_argument("--name", help="the worker's name (default: host.pid.random)")
    p.add_argument("--max-jobs", type=int, help="exit after this many jobs")


def work(store: JobStore, args: argparse.Namespace, what: str, **log_extra: Any) -> int:
    """Run a ``JobWorker`` on the store's queue until stopped (or, with ``--burst``, the queue is empty)."""
    settings: QueueSettings = store.settings
    name = args.name or f"{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:6]}"
    worker = JobWorker(
        [store.queue],
        store=store,
        connection=store.r,
        serializer=JSONSerializer,
        name=name,
        default_result_ttl=settings.result_ttl_s,
        # RQ's heartbeat while a job runs; the job's own lease is what re-queues it
        job_monitoring_interval=settings.heartbeat_s(),
    )
    if "torch" in sys.modules:  # forking after torch started its thread pools can deadlock the child
        log.warning("the worker process has imported torch; jobs may hang after fork")
    log.info(f"{what} up", extra={"worker": name, "queue": settings.queue_name, **log_extra})
    try:
        worker.work(burst=args.burst, max_jobs=args.max_jobs, logging_level=settings.log_level.upper())
    finally:
        with contextlib.suppress(redis.RedisError):
            store.worker_gone(name)
    log.info(f"{what} stopped", extra={"worker": name})
    return 0


def connect(settings: QueueSettings) -> redis.Redis:
    """The Redis connection of a worker (no read timeout: RQ blocks on the queue up to a heartbeat)."""
    return redis.Redis.from_url(settings.redis_url, socket_connect_timeout=5.0)


def connect_job(settings: QueueSettings) -> redis.Redis:
    """The Redis connection of a job process."""
    return redis.Redis.from_url(settings.redis_url, socket_connect_timeout=5.0, socket_timeout=30.0)


class Watch(threading.Thread):
    """Renews the lease of a running job and reads its flags (cancel, worker shutdown, superseded) a
    few times a second; ``stop_requested`` says whether the job should stop."""

    def __init__(self, store: JobStore, job_id: str, delivery: int, worker: str) -> None:
        super().__init__(name=f"watch-{job_id}", daemon=True)
        self.store, self.job_id, self.worker = store, job_id, worker
        self.mine = rq_id(job_id, delivery)
        ttl = store.settings.lease_ttl_s
        self.renew_every = ttl / 3.0
        self.poll_s = min(0.25, ttl / 6.0)
        self.cancelled = self.yielding = self.superseded = False
        self._done = threading.Event()

    def run(self) -> None:
        renewed = time.monotonic()
        while not self._done.wait(self.poll_s):
            renew = time.monotonic() - renewed >= self.renew_every
            try:
                cancel, yld, current = self.store.heartbeat(self.job_id, self.worker, renew)
            except redis.RedisError as exc:  # the lease may lapse: the job then runs again elsewhere
                log.warning("job heartbeat failed", extra={"job": self.job_id, "error": str(exc)})
                continue
            if renew:
                renewed = time.monotonic()
            self.cancelled |= cancel
            self.yielding |= yld
            self.superseded |= current != self.mine

    @property
    def stop_requested(self) -> bool:
        return self.cancelled or self.yielding or self.superseded

    def stop(self) -> None:
        self._done.set()
        self.join(timeout=5.0)
