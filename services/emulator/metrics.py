"""Prometheus metrics of one app instance (its own registry, so several apps can coexist in tests)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

_LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
_BATCH_BUCKETS = tuple(float(2**k) for k in range(13))  # 1 .. 4096


class LatencySeries:
    """One label set of ``BufferedHistogram``: ``observe`` appends to a list (tens of nanoseconds,
    where a prometheus_client ``Histogram.observe`` takes microseconds under a lock); the values are
    folded into bucket counts when the list is long and at every scrape."""

    FOLD_AT = 8192

    def __init__(self, bounds: NDArray[np.float64]) -> None:
        self.bounds = bounds
        self.pending: list[float] = []
        self.counts = np.zeros(len(bounds) + 1, np.int64)  # per bucket, the last one is +Inf
        self.total = 0.0

    def observe(self, seconds: float) -> None:
        self.pending.append(seconds)
        if len(self.pending) >= self.FOLD_AT:
            self.fold()

    def fold(self) -> None:
        if not self.pending:
            return
        values = np.asarray(self.pending)
        self.pending = []
        # bucket i counts values <= bounds[i] (prometheus' "le"), hence side="left"
        idx = np.searchsorted(self.bounds, values, side="left")
        self.counts += np.bincount(idx, minlength=len(self.counts))
        self.total += float(values.sum())


class BufferedHistogram(Collector):
    """A labelled latency histogram for per-message hot paths, exposed like a prometheus Histogram."""

    def __init__(
        self, name: str, documentation: str, labelnames: tuple[str, ...], buckets: tuple[float, ...]
    ) -> None:
        self.name = name
        self.documentation = documentation
        self.labelnames = labelnames
        self.bounds = np.asarray(buckets, np.float64)
        self.series: dict[tuple[str, ...], LatencySeries] = {}

    def labels(self, *values: str) -> LatencySeries:
        series = self.series.get(values)
        if series is None:
            series = self.series[values] = LatencySeries(self.bounds)
        return series

    def collect(self) -> Iterator[Metric]:
        family = HistogramMetricFamily(self.name, self.documentation, labels=list(self.labelnames))
        for values, series in list(self.series.items()):
            series.fold()
            cumulative = np.cumsum(series.counts)
            buckets = [(repr(float(b)), int(c)) for b, c in zip(self.bounds, cumulative[:-1], strict=True)]
            buckets.append(("+Inf", int(cumulative[-1])))
            family.add_metric(list(values), buckets, series.total)
        yield family


class Metrics:
    """Step latency (per request, per super-step), batch sizes and ORT time, sessions, divergences."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.step_latency = BufferedHistogram(
            "emulator_step_latency_seconds",
            "time from a step request's arrival to its new state, per super-step",
            ("model", "transport"),
            _LATENCY_BUCKETS,
        )
        r.register(self.step_latency)
        self.batch_size = Histogram(
            "emulator_batch_size", "rows per ONNX Runtime call", ["model"], buckets=_BATCH_BUCKETS, registry=r
        )
        self.ort_seconds = Histogram(
            "emulator_ort_call_seconds",
            "duration of one ONNX Runtime call",
            ["model"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
        self.session_steps = Counter(
            "emulator_session_steps", "session super-steps served", ["model"], registry=r
        )
        self.diverged = Counter("emulator_diverged_sessions", "sessions that diverged", ["model"], registry=r)
        self.sessions = Gauge("emulator_sessions", "live sessions", ["model", "version"], registry=r)
        self._per_batch: dict[str, tuple[Any, Any, Any]] = {}

    def latency(self, model: str, transport: str) -> LatencySeries:
        """The step-latency series of (model, transport) (every step observes it)."""
        return self.step_latency.labels(model, transport)

    def observe_batch(self, model: str, rows: int, seconds: float) -> None:
        children = self._per_batch.get(model)
        if children is None:  # looked up once per model: this runs for every ORT call
            children = self._per_batch[model] = (
                self.batch_size.labels(model),
                self.ort_seconds.labels(model),
                self.session_steps.labels(model),
            )
        size, ort, steps = children
        size.observe(rows)
        ort.observe(seconds)
        steps.inc(rows)

    def render(self) -> bytes:
        return generate_latest(self.registry)
