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
- **Outlives a Redis outage**: RQ's worker quits on a Redis error outside its wait for a job (a
  heartbeat while a job runs, the suspension check, its maintenance, the bookkeeping of a job's end,
  its records of what the worker does), so a worker busy when Redis went away for longer than a
  heartbeat interval was gone for good (its job ran on, unwatched, and the worker count dropped). Here
  those errors are logged once per outage and the worker goes on: it keeps waiting for its job, then
  waits for Redis as RQ does while idle, retrying at least every ``REAP_INTERVAL_S`` (RQ's back-off
  grows to a minute), so that it takes jobs and is counted again within seconds of Redis coming back.
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
from collections.abc import Callable, Sequence
from typing import Any

import redis
from rq import Queue, Worker
from rq.job import Job
from rq.serializers import JSONSerializer
from rq.worker import BaseWorker

from services.common.jobs import JobStore, QueueSettings, rq_id

log = logging.getLogger("services.common.job_worker")


REDIS_DOWN = (redis.ConnectionError, redis.TimeoutError)
"""What a Redis that went away raises (refused, reset, or not answering in time)."""


class JobWorker(Worker):
    """RQ's forking worker plus the lease reaper, the job-yielding shutdown and surviving Redis outages."""

    def __init__(self, queues: Sequence[Queue], *, store: JobStore, **kw: Any) -> None:
        # before RQ's __init__, which reads dequeue_timeout
        self.store = store
        self.reap_every = store.settings.reap_interval_s
        self._reaped_at = 0.0
        self._redis_down = False
        super().__init__(list(queues), **kw)
        # RQ doubles its wait for a Redis that does not answer up to this; capped at the reap interval
        self.max_connection_wait_time = float(self.dequeue_timeout)

    def _unreachable(self, what: str, exc: Exception) -> None:
        """Log (once per outage) that Redis failed ``what``; the worker carries on."""
        if not self._redis_down:
            log.warning(
                f"Redis unreachable ({what}): carrying on, retrying",
                extra={"worker": self.name, "error": str(exc)},
            )
        self._redis_down = True

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
            try:
                super().run_maintenance_tasks()
            except REDIS_DOWN as exc:  # RQ's registry clean-up: again at the next maintenance
                self._unreachable("maintenance", exc)

    def heartbeat(self, timeout: int | None = None, pipeline: Any = None) -> None:
        if pipeline is not None:  # queued on the caller's pipeline: it talks to Redis, not this
            super().heartbeat(timeout, pipeline)
            self.store.worker_seen(self.name, pipeline)
            return
        try:
            super().heartbeat(timeout)
            self.store.worker_seen(self.name)
        except REDIS_DOWN as exc:  # idle: the wait for a job that follows waits for Redis too
            self._unreachable("heartbeat", exc)
        else:
            if self._redis_down:
                log.info("Redis answers again", extra={"worker": self.name})
            self._redis_down = False

    def _record(self, what: str, write: Callable[..., None], value: Any, pipeline: Any) -> None:
        """One of RQ's records of what the worker does: bookkeeping, which waits for Redis (queued on
        a caller's pipeline, it is the caller's to send)."""
        if pipeline is not None:
            write(value, pipeline)
            return
        try:
            write(value)
        except REDIS_DOWN as exc:
            self._unreachable(what, exc)

    def set_state(self, state: str, pipeline: Any = None) -> None:
        self._record("worker state", super().set_state, state, pipeline)

    def set_current_job_working_time(self, current_job_working_time: float, pipeline: Any = None) -> None:
        self._record(
            "job working time", super().set_current_job_working_time, current_job_working_time, pipeline
        )

    def maintain_heartbeats(self, job: Job) -> None:
        """RQ's heartbeats while a job runs; without Redis the worker keeps waiting for the job."""
        try:
            super().maintain_heartbeats(job)
        except REDIS_DOWN as exc:
            self._unreachable("heartbeat while a job runs", exc)
        else:
            self._redis_down = False

    def dequeue_job_and_maintain_ttl(self, timeout: int | None, max_idle_time: int | None = None) -> Any:
        """RQ's wait for a job, which waits out a Redis that refuses connections but quits the worker
        on one that times out (a host that no longer answers): that is waited out too."""
        while True:
            try:
                return super().dequeue_job_and_maintain_ttl(timeout, max_idle_time)
            except redis.TimeoutError as exc:
                self._unreachable("waiting for a job", exc)
                time.sleep(self.max_connection_wait_time)

    def check_for_suspension(self, burst: bool) -> None:
        try:
            super().check_for_suspension(burst)
        except REDIS_DOWN as exc:  # not suspended, as far as is known: the wait for a job waits for Redis
            self._unreachable("suspension check", exc)

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
        try:
            super().execute_job(job, queue)
        except REDIS_DOWN as exc:
            # RQ's own records of the job (before it starts, or after its process ended); the job's
            # state is the store's, which its lease and the reaper keep right
            self._unreachable(f"RQ's records of {job.id}", exc)
        while self._horse_pid:  # RQ's monitoring raised while the job's process still ran: wait for it
            try:
                self.monitor_work_horse(job, queue)
            except REDIS_DOWN as exc:
                self._unreachable(f"RQ's records of {job.id}", exc)

    def teardown(self) -> None:
        try:
            super().teardown()
        except REDIS_DOWN as exc:  # stopping while Redis is away: its record of this worker expires
            self._unreachable("deregistering", exc)

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
        self.parent = os.getppid()  # the worker that forked this job process
        self._done = threading.Event()

    def run(self) -> None:
        renewed = time.monotonic()
        failing = False
        while not self._done.wait(self.poll_s):
            if (
                os.getppid() != self.parent
            ):  # the worker died (SIGKILL, OOM): yield, never run on as an orphan
                if not self.yielding:
                    log.warning(
                        "the job's worker is gone: the job goes back on the queue", extra={"job": self.job_id}
                    )
                self.yielding = True
                continue
            renew = time.monotonic() - renewed >= self.renew_every
            try:
                cancel, yld, current = self.store.heartbeat(self.job_id, self.worker, renew)
            except redis.RedisError as exc:  # the lease may lapse: the job then runs again elsewhere
                if not failing:  # once per outage, not at every poll
                    log.warning("job heartbeat failed", extra={"job": self.job_id, "error": str(exc)})
                failing = True
                continue
            if failing:
                log.info("job heartbeat recovered", extra={"job": self.job_id})
                failing = False
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
