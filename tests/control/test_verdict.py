"""A job's verdict: ``succeeded`` only when its controller meets the success criterion on MuJoCo; a
job that states no criterion is "done, no criterion", whatever its final error."""

from __future__ import annotations

import pytest

from neuroanimator.contracts.controller import JobOutcome, JobResult
from neuroanimator.goals import criteria
from neuroanimator.goals.verdict import EMULATOR_ONLY, MISSED, NO_CRITERION, SUCCEEDED, verdict


def test_a_job_without_criterion_is_done_not_succeeded() -> None:
    # the run ended normally (status succeeded) with the pendulum 2.83 rad from its goal
    out = JobOutcome(
        status="succeeded",
        stop="max_iterations",
        final_error_physics=2.83,
        final_errors_physics={"angle0": 2.83},
        success_criterion=None,
        success_emulator=None,
        success_physics=None,
    )
    assert out.status == "succeeded"  # the job's state is unchanged for the API
    assert out.verdict == NO_CRITERION == "done, no criterion"
    body = out.model_dump(mode="json")
    assert body["verdict"] == "done, no criterion" and body["final_error_physics"] == 2.83


@pytest.mark.parametrize(
    ("emulator", "physics", "expected"),
    [(True, True, SUCCEEDED), (False, True, SUCCEEDED), (True, False, EMULATOR_ONLY), (False, False, MISSED)],
)
def test_a_criterion_is_judged_on_mujoco(emulator: bool, physics: bool, expected: str) -> None:
    out = JobOutcome(
        status="succeeded",
        success_criterion="x within 0.5 m",
        success_emulator=emulator,
        success_physics=physics,
    )
    assert out.verdict == expected


@pytest.mark.parametrize("status", ["failed", "cancelled"])
def test_a_run_that_did_not_end_normally_says_so(status: str) -> None:
    assert verdict(status, None, None, None) == status
    assert JobOutcome(status=status, success_criterion="x", success_physics=True).verdict == status


def test_a_task_without_criterion_as_the_runner_reports_it() -> None:
    # run_job describes an empty criterion in words and judges neither side (dolphin-swim)
    out = JobOutcome(
        status="succeeded", success_criterion=criteria.describe((), [0.0], ["x"]), objective=-53.9
    )
    assert out.success_criterion and out.verdict == "done, no criterion"


def test_a_stored_result_without_the_field_gets_its_verdict() -> None:
    stored = {"id": "j1", "status": "succeeded", "success_criterion": None, "final_error_physics": 2.83}
    assert JobResult.model_validate(stored).verdict == "done, no criterion"
