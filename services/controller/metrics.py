"""Prometheus metrics of the controller: the queue's, read from Redis at each scrape so that they cover
every worker (``services.common.job_metrics``), plus this API process's own counters (submissions,
rejections)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, generate_latest

from services.common.job_metrics import QueueCollector, histograms
from services.controller.store import ITERATION_BUCKETS, JobStore

_HISTOGRAMS = histograms(
    "job",
    (
        "iterations",
        "job_iterations",
        "optimisation iterations of a finished job",
        ITERATION_BUCKETS,
    ),
)


class Metrics:
    """One app's registry (several apps coexist in tests)."""

    def __init__(self, store: JobStore) -> None:
        self.registry = CollectorRegistry()
        self.registry.register(QueueCollector(store, "controller", "job", _HISTOGRAMS))
        self.submitted = Counter(
            "controller_jobs_submitted", "jobs queued by this API process", registry=self.registry
        )
        self.rejected = Counter(
            "controller_jobs_rejected",
            "submissions refused (invalid, queue_full, redis_unavailable)",
            ["reason"],
            registry=self.registry,
        )

    def render(self) -> bytes:
        return generate_latest(self.registry)
