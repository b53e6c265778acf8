"""Prometheus metrics of a job queue, read from Redis at each scrape, so they cover every worker.

Workers write their counts into the store's ``stats`` hash as jobs end (``JobStore._final``); the API
reads it, with the queue depth, running jobs and live workers, when ``/metrics`` is scraped, under the
service's name (``controller_queue_depth``, ``trainer_queue_depth``, ...).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence

import redis
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from services.common.jobs import DURATION_BUCKETS, FINAL, JobStore

log = logging.getLogger(__name__)

Histogram = tuple[str, str, str, tuple[float, ...]]
"""(key in the stats hash, metric name without the service prefix, help text, buckets)."""


def histograms(noun: str, *more: Histogram) -> tuple[Histogram, ...]:
    """The run time and turnaround of the finished jobs, then ``more``."""
    return (
        ("duration", f"{noun}_duration_seconds", f"run time of a {noun}'s last attempt", DURATION_BUCKETS),
        ("turnaround", f"{noun}_turnaround_seconds", "from submission to the end", DURATION_BUCKETS),
        *more,
    )


class QueueCollector(Collector):
    """Queue depth, running jobs, workers, and the finished jobs' counts and histograms, named
    ``<prefix>_<name>``; the jobs are called ``noun`` (``<prefix>_<noun>s_finished``)."""

    def __init__(self, store: JobStore, prefix: str, noun: str, hists: Sequence[Histogram]) -> None:
        self.store, self.prefix, self.noun, self.hists = store, prefix, noun, hists

    def collect(self) -> Iterator[Metric]:
        s, p, noun = self.store, self.prefix, self.noun
        up = f"{p}_redis_up"
        try:
            depth = s.queue_depth()
            running = int(s.r.zcard(s.keys.running))
            workers = s.worker_count()
            stats = s.stats()
        except redis.RedisError as exc:
            log.warning("metrics: Redis unreachable", extra={"error": str(exc)})
            yield GaugeMetricFamily(up, "1 when Redis answered this scrape", value=0.0)
            return
        yield GaugeMetricFamily(up, "1 when Redis answered this scrape", value=1.0)
        yield GaugeMetricFamily(f"{p}_queue_depth", f"{noun}s waiting for a worker", value=float(depth))
        yield GaugeMetricFamily(f"{p}_{noun}s_running", f"{noun}s running now", value=float(running))
        yield GaugeMetricFamily(f"{p}_workers", "workers listening on the queue", value=float(workers))
        finished = CounterMetricFamily(
            f"{p}_{noun}s_finished", f"{noun}s ended, by final status", labels=["status"]
        )
        for status in sorted(FINAL, key=("succeeded", "failed", "cancelled").index):
            finished.add_metric([status], float(stats.get(f"finished:{status}", 0)))
        yield finished
        yield CounterMetricFamily(
            f"{p}_{noun}s_requeued",
            "runs put back on the queue (crashed, abandoned, worker shut down)",
            value=float(stats.get("requeued", 0)),
        )
        for key, name, doc, buckets in self.hists:
            les = [f"{b:g}" for b in buckets] + ["+Inf"]
            h = HistogramMetricFamily(f"{p}_{name}", doc)
            h.add_metric(
                [],
                buckets=[(le, float(stats.get(f"{key}_bucket:{le}", 0))) for le in les],
                sum_value=float(stats.get(f"{key}_sum", 0.0)),
            )
            yield h
