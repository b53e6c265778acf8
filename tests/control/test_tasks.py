"""The thesis' tasks (6.2) solved on the real n = 50 emulators and replayed on MuJoCo."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest

from neuroanimator.catalog.tasks import TASKS
from neuroanimator.contracts.controller import JobOutcome
from neuroanimator.control.job import run_job

ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"
# the tasks with a success criterion (dolphin-swim has none, as far as it can: test_dolphin_swim.py)
WITH_CRITERION = sorted(name for name, task in TASKS.items() if task.success)


@cache
def solved(name: str) -> JobOutcome:
    """The task's job with its defaults, run once per test session (about a second each)."""
    return run_job({"task": name}, ARTIFACTS)


@pytest.mark.parametrize("name", WITH_CRITERION)
def test_task_meets_its_criterion_on_the_emulator(name: str) -> None:
    result = solved(name)
    assert result.status == "succeeded" and result.stop == "success"
    assert result.emulator_phase is not None and result.refinement is not None
    # the controller found on the emulator alone meets the criterion there
    assert result.emulator_phase.success_emulator is True
    if not result.refinement.rounds:  # not refined on MuJoCo: it is the controller returned
        assert result.success_emulator is True
        assert result.checks_emulator and all(c.passed for c in result.checks_emulator)
    # the thesis needed 20, 15 and 15 iterations; the target here is at most 20
    assert result.iterations_to_success is not None and result.iterations_to_success <= 20
    first = result.objective_history[0]
    assert result.emulator_phase.objective is not None and first is not None
    assert result.emulator_phase.objective < 0.05 * first
    # the replay ran the same held controls on MuJoCo from the same start
    assert result.physical is not None and result.state_labels is not None
    phys = np.asarray(result.physical.states, dtype=float)
    assert phys.shape == (41, len(result.state_labels))
    assert np.all(np.isfinite(phys))
    assert isinstance(result.success_physics, bool)


def test_pendulum_swings_back_and_forth() -> None:
    """The torque limit is too low to go straight to the goal: the base joint must swing both ways."""
    result = solved("pendulum-swing")
    assert result.emulated is not None
    base = np.asarray(result.emulated.states, dtype=float)[:, 0]
    assert base.min() < -0.2 and base.max() > 0.9
    assert np.abs(np.asarray(result.controls, dtype=float)).max() <= 2.0 + 1e-9


@pytest.mark.parametrize("name", WITH_CRITERION)
def test_controller_drives_mujoco_after_physics_refinement(name: str) -> None:
    """The controller returned meets the criterion on MuJoCo; where the emulator-only controller did
    not (its drift), the refinement rounds say so and the first replay's outcome is kept."""
    result = solved(name)
    assert result.success_physics is True
    assert result.checks_physics and all(c.passed for c in result.checks_physics)
    phase, refinement = result.emulator_phase, result.refinement
    assert phase is not None and refinement is not None
    if phase.success_physics:
        assert refinement.rounds == []
    else:
        assert refinement.rounds[-1].success_physics is True
        assert result.final_error_physics is not None and phase.final_error_physics is not None
        assert result.final_error_physics < phase.final_error_physics
