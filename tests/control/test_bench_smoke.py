"""bench/control.py runs end to end with tiny settings and prints one JSON object last."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import run_bench


def test_bench_control_quick(tmp_path: Path) -> None:
    lines, result = run_bench(
        "bench/control.py", "--quick", "--tasks", "pendulum-swing", "--out", str(tmp_path)
    )
    assert lines[0].startswith("| task |")
    (row,) = result["tasks"]
    for key in (
        "task",
        "iterations_to_success",
        "wall_s",
        "success_emulator",
        "success_physics",
        "final_error_emulator",
        "final_error_physics",
        "gradient_free_iterations",
        "iteration_ratio",
        "wall_ratio",
    ):
        assert key in row
    assert row["task"] == "pendulum-swing" and row["control_variables"] == 60
    assert row["gradient_free_budget"] == 40
    methods = [g["method"] for g in row["gradient_free"]]
    assert methods == [
        "simulated_annealing(step=0.3)",
        "nelder_mead(step=0.3)",
        "cma_es(sigma=0.3)",
        "simulated_annealing(step=0.03)",
        "nelder_mead(step=0.03)",
        "cma_es(sigma=0.03)",
    ]
    assert row["bptt_networks"] == "all" and row["forward_distance_m"] is None
    assert all(g["total_evaluations"] <= 40 for g in row["gradient_free"])
    assert (tmp_path / "control_pendulum-swing.png").stat().st_size > 10_000
