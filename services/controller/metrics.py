"""Prometheus metrics of the controller: read from Redis at each scrape, so they cover every worker.

Workers write their counts into the ``stats`` hash as jobs end (``JobStore._final``); the API reads
it, with the queue depth, running jobs and live workers, when ``/metrics`` is scraped. Counters of
this API process itself (submissions, rejections) are ordinary in-process metrics.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import redis
from prometheus_client import CollectorRegistry, Counter, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from neuroanimator.controller_schemas import FINAL_STATES
from services.controller.store import DURATION_BUCKETS, ITERATION_BUCKETS, JobStore

log = logging.getLogger(__name__)

_HISTOGRAMS = (
    ("duration", "controller_job_duration_seconds", "run time of a job's last attempt", DURATION_BUCKETS),
    ("turnaround", "controller_job_turnaround_seconds", "from submission to the end", DURATION_BUCKETS),
    (
        "iterations",
        "controller_job_iterations",
        "optimisation iterations of a finished job",
        ITERATION_BUCKETS,
    ),
)


class QueueCollector(Collector):
    """Queue depth, running jobs, workers, and the finished jobs' counts and histograms."""

    def __init__(self, store: JobStore) -> None:
        self.store = store

    def collect(self) -> Iterator[Metric]:
        s = self.store
        try:
            depth = s.queue_depth()
            running = int(s.r.zcard(s.keys.running))
            workers = s.worker_count()
            stats = s.stats()
        except redis.RedisError as exc:
            log.warning("metrics: Redis unreachable", extra={"error": str(exc)})
            yield GaugeMetricFamily("controller_redis_up", "1 when Redis answered this scrape", value=0.0)
            return
        yield GaugeMetricFamily("controller_redis_up", "1 when Redis answered this scrape", value=1.0)
        yield GaugeMetricFamily("controller_queue_depth", "jobs waiting for a worker", value=float(depth))
        yield GaugeMetricFamily("controller_jobs_running", "jobs running now", value=float(running))
        yield GaugeMetricFamily("controller_workers", "workers listening on the queue", value=float(workers))
        finished = CounterMetricFamily(
            "controller_jobs_finished", "jobs ended, by final status", labels=["status"]
        )
        for status in FINAL_STATES:
            finished.add_metric([status], float(stats.get(f"finished:{status}", 0)))
        yield finished
        yield CounterMetricFamily(
            "controller_jobs_requeued",
            "runs put back on the queue (crashed, abandoned, worker shut down)",
            value=float(stats.get("requeued", 0)),
        )
        for key, name, doc, buckets in _HISTOGRAMS:
            les = [f"{b:g}" for b in buckets] + ["+Inf"]
            h = HistogramMetricFamily(name, doc)
            h.add_metric(
                [],
                buckets=[(le, float(stats.get(f"{key}_bucket:{le}", 0))) for le in les],
                sum_value=float(stats.get(f"{key}_sum", 0.0)),
            )
            yield h


class Metrics:
    """One app's registry (several apps coexist in tests)."""

    def __init__(self, store: JobStore) -> None:
        self.registry = CollectorRegistry()
        self.registry.register(QueueCollector(store))
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
