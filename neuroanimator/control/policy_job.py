"""``run_policy_job``: a policy task from its name (or its definition) to a stored policy.

What the CLI (``neuro policy``) and the controller's workers call: the task's emulator is the model's
latest version at the task's super-step (``registry.resolve``), the policy is trained through it
(``policy.train_policy``) and stored beside it (``policy_store.save_policy``) with how it did.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neuroanimator.artifacts import registry
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.control.policy import PolicyProgress, PolicyResult, PolicySettings, train_policy
from neuroanimator.control.policy_store import save_policy
from neuroanimator.goals.policy_task import PolicyTask

log = logging.getLogger(__name__)


class PolicyJobError(ValueError):
    """A policy job that cannot run: an unknown task, or no emulator at the super-step it needs."""


def policy_task(name: str) -> PolicyTask:
    """A built-in policy task by name; ``PolicyJobError`` listing the known ones."""
    task = POLICY_TASKS.get(name)
    if task is None:
        raise PolicyJobError(f"unknown policy task {name!r}; built-in: {', '.join(POLICY_TASKS)}")
    return task


def emulator_for(root: registry.Root, task: PolicyTask, version: str | None = None) -> Path:
    """The emulator a task's policy is trained through: ``version`` of its model (pinned when a job is
    submitted), else its model's latest at the task's super-step."""
    try:
        return registry.resolve(root, task.model, version, None if version else task.substeps)
    except registry.ArtifactError as e:
        raise PolicyJobError(
            f"policy task {task.name!r} needs an emulator of {task.model!r} at n = {task.substeps}: {e}"
        ) from e


@dataclass
class PolicyJobOutcome:
    """The trained policy and where it was stored (None: not stored, ``stored_reason`` says why)."""

    result: PolicyResult
    folder: Path | None
    stored_reason: str = ""


def worth_storing(result: PolicyResult) -> tuple[bool, str]:
    """Whether a policy is worth storing: one stopped before it was ever run on MuJoCo is untrained."""
    if result.stop == "cancelled" and not result.success_history:
        return False, f"cancelled after {result.iterations} iterations, before its first check on MuJoCo"
    return True, "stored"


def run_policy_job(
    task: PolicyTask | str,
    root: registry.Root,
    settings: PolicySettings | None = None,
    on_progress: Callable[[PolicyProgress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    emulator_version: str | None = None,
    should_store: Callable[[PolicyResult], tuple[bool, str]] = worth_storing,
) -> PolicyJobOutcome:
    """Train the task's policy through its emulator (``emulator_version``, else the latest at the task's
    super-step) and store it under ``root``'s data directory, unless ``should_store`` says not to (a
    worker shutting down, a policy cancelled before it was ever checked)."""
    task = policy_task(task) if isinstance(task, str) else task
    path = emulator_for(root, task, emulator_version)
    result = train_policy(task, path, settings, on_progress, should_stop)
    store, why = should_store(result)
    if not store:
        log.info("policy %s not stored: %s", task.name, why)
        return PolicyJobOutcome(result, None, why)
    goals = result.goals if result.goals is not None else np.zeros((1, len(task.goal.variables)))
    folder = save_policy(root, result, goals)
    log.info(
        "policy %s: success on MuJoCo %.2f, on the emulator %.2f (%d held-out runs), %d MuJoCo steps, "
        "%.0f s; stored in %s",
        task.name,
        result.success_physics,
        result.success_emulator,
        result.evaluate_runs,
        result.mujoco_steps,
        result.wall_s,
        folder,
    )
    return PolicyJobOutcome(result, folder, "stored")
