"""Prometheus metrics of the trainer: the queue's, read from Redis at each scrape so that they cover
every worker (``services.common.job_metrics``), plus this API process's own counters (uploads queued
and refused, by why)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, generate_latest

from services.common.job_metrics import QueueCollector, histograms
from services.trainer.store import TrainingStore


class Metrics:
    """One app's registry (several apps coexist in tests)."""

    def __init__(self, store: TrainingStore) -> None:
        self.registry = CollectorRegistry()
        self.registry.register(QueueCollector(store, "trainer", "training", histograms("training")))
        self.submitted = Counter(
            "trainer_trainings_submitted", "trainings queued by this API process", registry=self.registry
        )
        self.rejected = Counter(
            "trainer_uploads_rejected",
            "uploads refused, by the error they got (compile_error, missing_file, limit_exceeded, ...)",
            ["reason"],
            registry=self.registry,
        )

    def render(self) -> bytes:
        return generate_latest(self.registry)
