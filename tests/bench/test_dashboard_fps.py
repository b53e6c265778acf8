"""bench/dashboard_fps.py runs end to end at a tiny scale: a real stack, the Playground in headless
Chromium with a live lander session and its ghost, its frames timed in windows."""

from __future__ import annotations

import pytest

from tests.e2e.harness import missing
from tests.helpers import run_bench

pytestmark = pytest.mark.skipif(missing() is not None, reason=missing() or "")


def test_dashboard_fps_small(redis_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("REDIS_URL", redis_url)
    _, r = run_bench(
        "bench/dashboard_fps.py", "--settle", "1", "--windows", "2", "--seconds", "1", timeout=180
    )
    (run,) = r["runs"]
    assert len(run["windows"]) == 2
    for w in run["windows"]:
        assert w["frames"] > 0 and 0 < w["fps"] <= 65, w
        assert 0 <= w["late"] <= w["frames"]
        assert 0.4 <= w["scale"] <= 1
    assert run["renderer"]  # what draws: SwiftShader here, a GPU elsewhere
    assert run["fps_min"] <= run["fps_mean"]
