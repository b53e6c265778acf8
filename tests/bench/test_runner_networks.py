"""bench/runner_networks.py runs end to end at a tiny scale on the committed runner emulator (real
MuJoCo runs, the real artifact)."""

from __future__ import annotations

from tests.helpers import run_bench


def test_runner_networks_small() -> None:
    lines, r = run_bench(
        "bench/runner_networks.py", *("--seeds", "1", "--test", "200", "--fit", "400"), timeout=240
    )
    assert [s["seed"] for s in r["sets"]] == [1]
    nets = r["sets"][0]["networks"]
    assert set(nets) == {"trunk", "left_arm", "right_arm", "left_leg", "right_leg"}
    for e in nets.values():
        assert 0 < e["one_step_rel_error"] < e["linear_baseline_rel_error"]
        assert 0 < e["worst_1pct_share"] <= e["worst_10pct_share"] <= 1
    assert set(r["summary"]) == set(nets)
    assert any(line.startswith("left_leg") for line in lines)
