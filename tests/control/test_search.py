"""The search before descent (global cross-entropy pass, several starts batched) and what a job
reports about its goal: reachability, a job without a criterion, an honest ``stop``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from neuroanimator.control.job import run_job
from neuroanimator.control.search import cross_entropy, descend_starts, starting_points
from neuroanimator.control.synthesis import Settings
from tests.helpers import run_bench

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "artifacts"


def double_well(z: np.ndarray) -> np.ndarray:
    """(B, M, U) -> (B,): Σ (z² − 1)² + 0.3 z per point: two basins, the one at z ≈ −1 lower."""
    return (((z * z - 1.0) ** 2) + 0.3 * z).sum(axis=(1, 2))


def double_well_grad(z: np.ndarray) -> np.ndarray:
    return 4.0 * z * (z * z - 1.0) + 0.3


def test_multi_start_descends_every_start_in_one_batch_and_picks_the_best() -> None:
    calls: list[int] = []

    def values_and_grads(zs: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[Any]]:
        calls.append(zs.shape[0])
        return double_well(zs), double_well_grad(zs), [None] * zs.shape[0]

    starts = np.array([[[0.9]], [[1.2]], [[-0.8]]])  # two in the worse basin, one in the better
    out = descend_starts(
        values_and_grads,
        double_well,
        starts,
        Settings(learning_rate=0.5, momentum=0.5, max_iterations=30),
        30,
        project=lambda z: np.clip(z, -2, 2),
        is_success=lambda extra: False,
    )
    assert calls and set(calls) == {3}  # every gradient evaluation is one batch of all starts
    assert out.index == 2 and out.z[0, 0] < -0.9  # the start in the lower basin, descended to it
    assert out.objective == min(out.objectives) < double_well(starts[2:3])[0]
    # each start stayed in its own basin: descent alone does not cross between them
    assert sum(1 for j in out.objectives if j > 0) == 2
    assert out.rollouts >= 3 * (out.iterations + 1)


def test_multi_start_prefers_a_start_that_meets_the_criterion() -> None:
    def values_and_grads(zs: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[Any]]:
        return double_well(zs), double_well_grad(zs), list(zs[:, 0, 0])

    out = descend_starts(
        values_and_grads,
        double_well,
        np.array([[[-1.0]], [[1.0]]]),
        Settings(learning_rate=0.5, momentum=0.5, max_iterations=5),
        5,
        project=lambda z: z,
        is_success=lambda z: z > 0,  # only the worse basin counts as success here
    )
    assert out.success and out.index == 1 and out.iterations == 0


def test_global_search_finds_the_better_basin_from_the_worse_start() -> None:
    z0 = np.full((4, 1), 1.0)  # every point in the worse basin
    starts = starting_points(z0, lambda z: np.clip(z, -2, 2))
    assert starts.shape == (3, 4, 1)  # z0, and the control shifted up and down
    found = cross_entropy(double_well, starts, lambda z: np.clip(z, -2, 2), generations=6, population=64)
    assert found.rollouts == 64 * 7
    assert found.values[0] < double_well(z0[None])[0] - 1.0
    assert (found.best[0] < 0).sum() >= 2  # points moved over the barrier, which descent never does


def test_a_goal_out_of_reach_is_reported_unreachable_with_the_reason() -> None:
    # the pendulum cannot swing up to 2.5 rad in one second with 2 N·m motors
    result = run_job(
        {
            "task": "pendulum-swing",
            "target_state": [2.5, 0, 0, 0, 0, 0],
            "horizon": 2,
            "optimizer": {"max_iterations": 3, "physics_rounds": 0},
        },
        ARTIFACTS,
    )
    assert result.success_emulator is False and result.success_physics is False
    assert result.reachable is False
    assert result.reachability is not None and "unreachable" in result.reachability
    assert "angles.j0 = 2.5" in result.reachability  # names the check it misses
    assert result.stop != "success"


def test_a_job_without_a_criterion_reports_its_errors_and_does_not_refine() -> None:
    result = run_job(
        {
            "model": "truck",
            "target_state": [3, 0, 0, 0, 0, 0],
            "horizon": 6,
            "optimizer": {"max_iterations": 4, "physics_rounds": 3},
        },
        ARTIFACTS,
    )
    assert result.status == "succeeded"
    assert result.success_emulator is None and result.success_physics is None
    assert result.emulator_phase is not None and result.emulator_phase.success_physics is None
    assert result.refinement is not None and result.refinement.rounds == []
    assert result.refinement.physics_replays == 1
    assert result.reachable is None and result.stop != "success"
    assert result.final_errors_physics and result.final_error_physics is not None


def test_stop_says_success_only_when_a_replay_meets_the_criterion() -> None:
    for task in ("pendulum-swing", "truck-parking"):
        result = run_job({"task": task, "horizon": 8, "optimizer": {"max_iterations": 6}}, ARTIFACTS)
        if result.stop == "success":
            assert result.success_emulator or result.success_physics
        assert result.search is not None and result.search.starts == 4
        assert (
            result.emulator_rollouts is not None and result.emulator_rollouts > result.search.global_rollouts
        )


def test_bench_control_goals_quick() -> None:
    lines, result = run_bench("bench/control_goals.py", "--quick", "--goals", "1", "--tasks", "truck-parking")
    assert lines[0].startswith("| task |")
    assert result["seed"] == 0 and result["goals"] == 1
    (row,) = result["tasks"]
    assert row["task"] == "truck-parking" and row["goals"] == 1
    (job,) = row["jobs"]
    x, y, heading = job["target_state"][:3]
    assert abs(x) <= 15 and abs(y) <= 15 and abs(heading) <= np.pi
    for key in ("success_emulator", "success_physics_emulator_only", "success_physics"):
        assert isinstance(job[key], bool) and row[key] == int(job[key])
    for key in ("iterations", "emulator_rollouts", "wall_s", "final_error_physics"):
        assert set(row[key]) == {"median", "worst"}
    # quick: at most 2 Levenberg-Marquardt updates after the emulator descent and after its one
    # refinement round's
    assert 0 <= job["gauss_newton_iterations"] <= 4 and result["settings"]["gauss_newton_iterations"] == 20
    assert job["iterations"] <= 5 + 2 and job["emulator_rollouts"] > 0
