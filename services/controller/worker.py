"""A controller worker: ``python -m services.controller.worker`` (or ``neuro worker``).

It is a ``services.common.job_worker.JobWorker`` on the controller queue: it forks one process per job
(``execution.perform``), so a job's PyTorch thread pools live and die with that process; this parent
process never imports torch. Start as many as you like, on one machine or many: they share only Redis.
It re-queues abandoned jobs, shuts down cleanly on SIGTERM (the running job goes back on the queue),
reports itself alive with RQ's heartbeats and runs nothing but controller deliveries (see
``job_worker``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from services.common import job_worker, logs
from services.controller import execution
from services.controller.settings import Settings
from services.controller.store import JobStore

ControllerWorker = job_worker.JobWorker


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m services.controller.worker",
        description="Run controller-synthesis jobs from the Redis queue (settings from the environment).",
    )
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    job_worker.add_arguments(p)
    p.add_argument(
        "--threads",
        type=int,
        help="torch threads per job (default: WORKER_THREADS; unset, a policy job its task's, others one)",
    )


def run(args: argparse.Namespace, settings: Settings | None = None) -> int:
    settings = settings or Settings()
    if args.threads is not None:
        settings = settings.model_copy(update={"worker_threads": max(1, args.threads)})
    store = JobStore(job_worker.connect(settings), settings)
    execution.configure(settings)  # the forked job processes inherit these settings
    return job_worker.work(store, args, "controller worker", threads=settings.worker_threads)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    settings = Settings()
    logs.setup(settings.log_level)
    return run(args, settings)


if __name__ == "__main__":
    sys.exit(main())
