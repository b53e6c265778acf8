"""A controller worker: ``python -m services.controller.worker`` (or ``neuro worker``).

It is an RQ worker on the controller queue that forks one process per job (``execution.perform``), so a
job's PyTorch thread pools live and die with that process; this parent process never imports torch.
Start as many as you like, on one machine or many: they share only Redis.

Beyond RQ it does two things:
- **Re-queues abandoned jobs.** A running job renews a lease in Redis; while idle, the worker looks
  every ``REAP_INTERVAL_S`` for running jobs whose lease expired (their worker was killed, lost its
  machine or its Redis connection) and puts them back on the queue, up to ``JOB_RETRIES`` times.
  RQ 2's own check (``StartedJobRegistry.cleanup``) only runs in its 10-minute maintenance and only
  notices a dead job a minute or more after its last heartbeat, so it serves as a backstop only.
- **Shuts down cleanly on SIGTERM** (or Ctrl-C): a running job is asked to stop at its next
  iteration and goes back on the queue for another worker; the worker then exits. A second signal
  kills the job at once (RQ's cold shutdown); the lease then brings it back.
- **Reports itself alive** with each of RQ's heartbeats (``JobStore.worker_seen``), so that the count
  of ``/readyz`` and ``controller_workers`` drops a killed worker within ``WORKER_ALIVE_S`` and finds
  every worker again after Redis lost its data (RQ's own registry only knows workers from their start,
  and keeps a killed one for minutes).
- **Runs only controller jobs**: the queue's messages are JSON (not RQ's default pickle), and a job
  that names any function but ``execution.perform`` is refused, not run, so that whoever can write
  to Redis cannot make a worker run code of their choosing.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import socket
import sys
import time
import uuid
from collections.abc import Sequence
from typing import Any

import redis
from rq import Queue, Worker
from rq.job import Job
from rq.serializers import JSONSerializer
from rq.worker import BaseWorker

from services.common import logs
from services.controller import execution
from services.controller.settings import Settings
from services.controller.store import PERFORM, JobStore

log = logging.getLogger("services.controller.worker")


class ControllerWorker(Worker):
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
        """Run a controller delivery; refuse (fail in RQ, run nothing) a job naming another function."""
        try:
            func = job.func_name
        except Exception as exc:  # a payload that is not our JSON
            func = f"<unreadable: {type(exc).__name__}>"
        if func != PERFORM:
            log.error(
                "refused a queued job that is not a controller delivery",
                extra={"rq_job": job.id, "func": func},
            )
            self.handle_job_failure(job, queue=queue, exc_string=f"refused: {func} is not {PERFORM}")
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m services.controller.worker",
        description="Run controller-synthesis jobs from the Redis queue (settings from the environment).",
    )
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--burst", action="store_true", help="run the queued jobs, then exit (tests, batch runs)")
    p.add_argument("--name", help="the worker's name (default: host.pid.random)")
    p.add_argument("--threads", type=int, help="torch threads per job (default: WORKER_THREADS, 1)")
    p.add_argument("--max-jobs", type=int, help="exit after this many jobs")


def run(args: argparse.Namespace, settings: Settings | None = None) -> int:
    settings = settings or Settings()
    if args.threads is not None:
        settings = settings.model_copy(update={"worker_threads": max(1, args.threads)})
    conn = redis.Redis.from_url(settings.redis_url, socket_connect_timeout=5.0)
    store = JobStore(conn, settings)
    execution.configure(settings)  # the forked job processes inherit these settings
    name = args.name or f"{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:6]}"
    worker = ControllerWorker(
        [store.queue],
        store=store,
        connection=conn,
        serializer=JSONSerializer,
        name=name,
        default_result_ttl=settings.result_ttl_s,
        # RQ's heartbeat while a job runs; the job's own lease is what re-queues it
        job_monitoring_interval=settings.heartbeat_s(),
    )
    if "torch" in sys.modules:  # forking after torch started its thread pools can deadlock the child
        log.warning("the worker process has imported torch; jobs may hang after fork")
    log.info(
        "controller worker up",
        extra={"worker": name, "queue": settings.queue_name, "threads": settings.worker_threads},
    )
    try:
        worker.work(burst=args.burst, max_jobs=args.max_jobs, logging_level=settings.log_level.upper())
    finally:
        with contextlib.suppress(redis.RedisError):
            store.worker_gone(name)
    log.info("controller worker stopped", extra={"worker": name})
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = Settings()
    logs.setup(settings.log_level)
    return run(args, settings)


if __name__ == "__main__":
    sys.exit(main())
