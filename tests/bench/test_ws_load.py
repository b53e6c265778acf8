"""bench/ws_load.py runs end to end at a tiny scale (a real server over loopback, bounded)."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import run_bench


def test_ws_load_small(service_root: Path) -> None:
    _, r = run_bench(
        "bench/ws_load.py",
        "--clients",
        "4",
        "--duration",
        "0.5",
        "--artifacts",
        str(service_root),
        timeout=120,
    )
    assert r["clients"] == 4 and r["errors"] == 0 and isinstance(r["steps_per_s"], float)
    assert {"p50_ms", "p99_ms"} <= set(r)
