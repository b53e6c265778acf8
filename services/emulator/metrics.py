"""Prometheus metrics of one app instance (its own registry, so several apps can coexist in tests)."""

from __future__ import annotations

from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

_LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
_BATCH_BUCKETS = tuple(float(2**k) for k in range(13))  # 1 .. 4096


class Metrics:
    """Step latency (per request, per super-step), batch sizes and ORT time, sessions, divergences."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.step_latency = Histogram(
            "emulator_step_latency_seconds",
            "time from a step request's arrival to its new state, per super-step",
            ["model", "transport"],
            buckets=_LATENCY_BUCKETS,
            registry=r,
        )
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
        self._latency: dict[tuple[str, str], Any] = {}
        self._per_batch: dict[str, tuple[Any, Any, Any]] = {}

    def latency(self, model: str, transport: str) -> Any:
        """The step-latency histogram of (model, transport), looked up once (every step observes it)."""
        child = self._latency.get((model, transport))
        if child is None:
            child = self._latency[(model, transport)] = self.step_latency.labels(model, transport)
        return child

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
