"""bench/policies.py end to end on the lander with tiny budgets: the policy learned through the
emulator, one open-loop job and SAC on MuJoCo, judged on the same held-out runs, one JSON object last."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import run_bench


def test_quick_policy_bench_reports_all_three_on_the_same_held_out_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NEUROANIMATOR_DATA_DIR", str(tmp_path))  # nothing written beside the defaults
    lines, result = run_bench("bench/policies.py", "--quick", "--tasks", "lander-landing", timeout=180)
    assert lines[0].startswith("| task | held-out | policy: MuJoCo |")
    assert any(line.startswith("| lander-landing | 16 |") for line in lines)
    assert result["held_out"] == 16 and result["settings"]["quick"] is True
    (row,) = result["tasks"]
    assert row["task"] == "lander-landing" and row["held_out"] == 16
    for key in ("success_physics", "success_emulator"):
        assert 0.0 <= row[key] <= 1.0
        assert row[key] * 16 == pytest.approx(round(row[key] * 16))  # a share of the 16 runs
    # the goal pool's runs at least: a batch of 256 runs of 20 s at MuJoCo's 10 ms
    assert row["mujoco_steps"] >= 256 * 2_000
    assert 0.0 < row["wall_s"] < 60.0 and row["iterations"] >= 1

    loop = row["open_loop"]
    assert loop["applicable"] is True and loop["reason"] is None and loop["runs"] == 1
    assert loop["success_physics"] in (0.0, 1.0) and loop["policy_success_physics"] in (0.0, 1.0)
    assert loop["wall_s"] > 0 and loop["mujoco_steps"] >= 80 * 25  # one 80-step replay at least

    free = row["model_free"]
    assert free["algorithm"] == "sac"
    assert 0.0 <= free["success_physics"] <= 1.0
    assert free["env_steps"] > 0 and free["mujoco_steps"] > free["env_steps"] * 25
    # the same wall time as the policy's training, give or take the update that crosses the deadline
    assert free["wall_s"] >= row["wall_s"] and free["wall_s"] < row["wall_s"] + 10.0
