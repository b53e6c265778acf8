"""bench/batch_api.py runs end to end at a tiny scale (a real server over loopback, bounded)."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import run_bench


def test_batch_api_small(service_root: Path) -> None:
    _, r = run_bench(
        "bench/batch_api.py",
        "--sessions",
        "16",
        "--duration",
        "0.3",
        "--rollout-max-s",
        "0.3",
        "--idle-sessions",
        "50",
        "--compare-off",
        "--concurrency",
        "4",
        "--artifacts",
        str(service_root),
        timeout=120,
    )
    assert r["sessions"] == 16 and r["errors"] == 0
    assert {"session_steps_per_s", "rollout_session_steps_per_s", "ratio", "rss_per_10k_idle_mb"} <= set(r)
    assert r["httpx_session_steps_per_s"] > 0
    for label in ("on", "off"):
        assert r[f"single_requests_batching_{label}_session_steps_per_s"] > 0
