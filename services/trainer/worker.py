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
import logging
import os
import sys
from collections.abc import Sequence

from services.common import job_worker, logs
from services.trainer import execution
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


def run(args: argparse.Namespace, settings: Settings | None = None) -> int:
    settings = settings or Settings()
    niceness = os.nice(settings.worker_nice)  # inherited by every process forked or started from here
    store = TrainingStore(job_worker.connect(settings), settings)
    execution.configure(settings)  # the forked job processes inherit these settings
    return job_worker.work(store, args, "training worker", nice=niceness)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = Settings()
    logs.setup(settings.log_level)
    return run(args, settings)


if __name__ == "__main__":
    sys.exit(main())
