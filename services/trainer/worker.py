"""A training worker: ``python -m services.trainer.worker``.

A ``services.common.job_worker.JobWorker`` on the trainer's queue: it re-queues abandoned trainings,
shuts down cleanly on SIGTERM (the running training goes back on the queue), reports itself alive with
RQ's heartbeats and runs nothing but training deliveries. It first lowers its own CPU priority by
``WORKER_NICE`` (``os.nice``), which the job processes it forks and their training processes inherit,
so that a training takes the CPU the services leave (give it a CPU limit too: ``cpus`` in compose).
Start one per core you can spare for training, on one machine or many: they share Redis, the
artifact registry and the trainer's work folder (``WORK_DIR``).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import redis

from services.common import job_worker, logs
from services.trainer import execution, leftovers
from services.trainer.settings import Settings
from services.trainer.store import TrainingStore

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m services.trainer.worker",
        description="Run trainings from the Redis queue (settings from the environment).",
    )
    job_worker.add_arguments(p)
    return p


def lower_priority(nice: int, idle: bool = False) -> int:
    """Lower this process's CPU priority by ``nice`` and, with ``idle``, put it in Linux's idle scheduling
    class (SCHED_IDLE: it runs on what the services leave, a weight of 3 against their 1,024), both
    inherited by every process and thread forked or started from here; returns the new niceness. Where the worker leads a session of its own (a container, a service
    manager), Linux first shares the CPU fairly between sessions' autogroups, whatever the niceness inside
    them, so the autogroup's niceness is lowered too (best effort: /proc/self/autogroup)."""
    niceness = os.nice(nice)
    if idle and hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        except OSError as e:
            log.info("the worker keeps the normal scheduling class", extra={"reason": str(e)})
    autogroup = Path("/proc/self/autogroup")
    if nice and os.getsid(0) == os.getpid() and autogroup.exists():
        try:
            autogroup.write_text(str(niceness))
        except OSError as e:
            log.info("the worker's autogroup keeps its priority", extra={"reason": str(e)})
    return niceness


def run(args: argparse.Namespace, settings: Settings | None = None) -> int:
    settings = settings or Settings()
    # the trainings this worker starts compile the upload in the sandbox, refusing where it cannot confine
    os.environ["REQUIRE_LANDLOCK"] = "true" if settings.require_landlock else "false"
    niceness = lower_priority(settings.worker_nice, settings.worker_idle)
    store = TrainingStore(job_worker.connect(settings), settings)
    execution.configure(settings)  # the forked job processes inherit these settings
    with contextlib.suppress(redis.RedisError):  # what trainings killed with the last worker left
        leftovers.reap(settings, store)
    return job_worker.work(store, args, "training worker", nice=niceness)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = Settings()
    logs.setup(settings.log_level)
    return run(args, settings)


if __name__ == "__main__":
    sys.exit(main())
