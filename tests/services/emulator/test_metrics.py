"""The buffered step-latency histogram exposes what a prometheus_client Histogram would, folded or not."""

from __future__ import annotations

import numpy as np
from prometheus_client import CollectorRegistry, Histogram, generate_latest

from services.emulator.metrics import _LATENCY_BUCKETS, BufferedHistogram, LatencySeries


def _samples(text: bytes, name: str) -> dict[str, float]:
    out = {}
    for line in text.decode().splitlines():
        if line.startswith(name) and not line.startswith(f"{name}_created"):
            key, value = line.rsplit(" ", 1)
            out[key] = float(value)
    return out


def test_same_exposition_as_a_prometheus_histogram() -> None:
    values = np.random.default_rng(0).lognormal(-6, 2, LatencySeries.FOLD_AT + 1234)
    values[:3] = _LATENCY_BUCKETS[:3]  # on a bucket's bound: counted in that bucket ("le")
    ours, ref = CollectorRegistry(), CollectorRegistry()
    buffered = BufferedHistogram("lat_seconds", "doc", ("model", "transport"), _LATENCY_BUCKETS)
    ours.register(buffered)
    plain = Histogram("lat_seconds", "doc", ["model", "transport"], buckets=_LATENCY_BUCKETS, registry=ref)
    for v in values.tolist():  # more than FOLD_AT: folded once on the way, the rest at the scrape
        buffered.labels("m", "ws").observe(v)
        plain.labels("m", "ws").observe(v)
    got, want = _samples(generate_latest(ours), "lat_seconds"), _samples(generate_latest(ref), "lat_seconds")
    assert got.keys() == want.keys() and len(got) == len(_LATENCY_BUCKETS) + 3
    for key in want:
        assert np.isclose(got[key], want[key], rtol=1e-9), key
    assert buffered.labels("m", "ws").pending == []
