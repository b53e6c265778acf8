"""``run_policy_job``: a policy task from its name (or its definition) to a stored policy.

What the CLI (``neuro policy``) and the controller's workers call: the task's emulator is the model's
latest version at the task's super-step (``registry.resolve``), the policy is trained through it
(``policy.train_policy``) and stored beside it (``policy_store.save_policy``) with how it did.

A suite task (``suite_tasks.SUITE_TASKS``: ``cartpole-swingup``, ``reacher-hard``, ...) takes the same
path with its reward: the emulator of the model named as its domain, the policy trained by
``seed_race.train_reward_policy`` (``reward_policy``, from the task's seeds side by side) and stored by ``policy_store.save_reward_policy``.
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
from neuroanimator.control.policy_store import save_policy, save_reward_policy
from neuroanimator.control.reward_policy import (
    OUTSIDE,
    RewardProgress,
    RewardResult,
    RewardSettings,
)
from neuroanimator.control.seed_race import train_reward_policy
from neuroanimator.control.suite_tasks import SUITE_TASKS, SuiteTask
from neuroanimator.goals.policy_task import PolicyTask

log = logging.getLogger(__name__)


class PolicyJobError(ValueError):
    """A policy job that cannot run: an unknown task, or no emulator at the super-step it needs."""


def policy_task(name: str) -> PolicyTask | SuiteTask:
    """A built-in policy task (a goal-reaching one, or a suite task's reward) by name;
    ``PolicyJobError`` listing the known ones."""
    task = POLICY_TASKS.get(name) or SUITE_TASKS.get(name)
    if task is None:
        known = ", ".join([*POLICY_TASKS, *SUITE_TASKS])
        raise PolicyJobError(f"unknown policy task {name!r}; built-in: {known}")
    return task


def emulator_for(root: registry.Root, task: PolicyTask | SuiteTask, version: str | None = None) -> Path:
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

    result: PolicyResult | RewardResult
    folder: Path | None
    stored_reason: str = ""


def worth_storing(result: PolicyResult | RewardResult) -> tuple[bool, str]:
    """Whether a policy is worth storing: one stopped before it was ever run on MuJoCo is untrained."""
    checked = result.success_history if isinstance(result, PolicyResult) else result.return_history
    if result.stop == "cancelled" and not checked:
        return False, f"cancelled after {result.iterations} iterations, before its first check on MuJoCo"
    return True, "stored"


def run_policy_job(
    task: PolicyTask | SuiteTask | str,
    root: registry.Root,
    settings: PolicySettings | RewardSettings | None = None,
    on_progress: Callable[[PolicyProgress], None] | Callable[[RewardProgress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    emulator_version: str | None = None,
    should_store: Callable[[PolicyResult | RewardResult], tuple[bool, str]] = worth_storing,
) -> PolicyJobOutcome:
    """Train the task's policy through its emulator (``emulator_version``, else the latest at the task's
    super-step) and store it under ``root``'s data directory, unless ``should_store`` says not to (a
    worker shutting down, a policy cancelled before it was ever checked). A suite task's ``settings``
    are ``RewardSettings`` (None: its defaults, its ``train_seconds``)."""
    task = policy_task(task) if isinstance(task, str) else task
    path = emulator_for(root, task, emulator_version)
    if isinstance(task, SuiteTask):
        if settings is not None and not isinstance(settings, RewardSettings):
            raise PolicyJobError(f"{task.name} is a reward task: its settings are RewardSettings")
        return _run_reward_job(task, root, path, settings, on_progress, should_stop, should_store)  # type: ignore[arg-type]
    if isinstance(settings, RewardSettings):
        raise PolicyJobError(f"{task.name} is a goal-reaching task: its settings are PolicySettings")
    result = train_policy(task, path, settings, on_progress, should_stop)  # type: ignore[arg-type]
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


def _run_reward_job(
    task: SuiteTask,
    root: registry.Root,
    path: Path,
    settings: RewardSettings | None,
    on_progress: Callable[[RewardProgress], None] | None,
    should_stop: Callable[[], bool] | None,
    should_store: Callable[[PolicyResult | RewardResult], tuple[bool, str]],
) -> PolicyJobOutcome:
    """A suite task's policy trained for its reward through the emulator at ``path`` and stored."""
    try:
        result = train_reward_policy(task, path, settings, on_progress, should_stop)
    except ValueError as e:  # an emulator that does not fit the task (its super-step, its kind)
        raise PolicyJobError(str(e)) from e
    if result.stop == OUTSIDE:
        raise PolicyJobError(
            f"{task.name}: the emulator's states under the policy were outside its training envelope "
            f"{100 * result.outside_share:.0f} % of the time after {result.wall_s:.0f} s (at most "
            f"{100 * (settings or RewardSettings()).max_outside:.0f} % is trusted): the emulator has not "
            "seen where the policy goes; train it on more of the model's motion"
        )
    store, why = should_store(result)
    if not store:
        log.info("policy %s not stored: %s", task.name, why)
        return PolicyJobOutcome(result, None, why)
    folder = save_reward_policy(root, result, path)
    log.info(
        "policy %s: return on MuJoCo %.1f, on the emulator %.1f (%d episodes), %d MuJoCo steps, %.0f s; "
        "stored in %s",
        task.name,
        result.return_physics,
        result.return_emulator,
        result.evaluate_runs,
        result.mujoco_steps,
        result.wall_s,
        folder,
    )
    return PolicyJobOutcome(result, folder, "stored")
