"""Policy jobs of the controller, torch-free: their spec, how a request becomes one (checked against the
built-in policy tasks, or a user's task by ``custom_policy``, and the artifact registry at
submission), and their curves thinned for the wire.

    PolicyJobCreate --policy_spec--> PolicyJobSpec (the queued job's spec, ``"kind": "policy"``)
    --policy_execution.perform_policy, in the worker's job process--> PolicyOutcome

A job's spec (JSON) says its kind: a policy job's has ``"kind": "policy"``, a control job's is a
``JobSpec`` (which has no ``kind``). Both kinds share the controller's queue, workers and records.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from neuroanimator.artifacts import registry
from neuroanimator.catalog.suite import SUITE_TASK_INFO, SuiteTaskInfo
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.contracts.controller import (
    HISTORY_POINTS,
    HistoryPoint,
    PolicyJobCreate,
    PolicyTaskSpec,
    RewardTaskSpec,
)
from neuroanimator.goals.policy_task import PolicyTask
from services.common import tenancy
from services.controller.custom_policy import TaskDefinitionError, checked_reward_task, checked_task

POLICY: Literal["policy"] = "policy"
REWARD_HIDDEN = (64, 64)  # a suite task's policy network (``reward_policy.RewardSettings.hidden``)
CUSTOM_REWARD_SECONDS = 1500.0  # a user's reward task's default budget (a suite task's default)
JobKind = Literal["control", "policy"]


class PolicyJobSpec(BaseModel):
    """A checked policy job: the task, the emulator it resolved to when queued, and the training
    settings (None: the trainer's default, ``neuroanimator.control.policy.PolicySettings``).

    ``task`` is the task's name; a user's own task travels whole in ``definition`` (its name and
    super-step filled in) with its model's state ``labels``, so that a worker builds the same
    ``PolicyTask`` (``custom_policy.build_task``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["policy"] = POLICY
    task: str
    definition: PolicyTaskSpec | RewardTaskSpec | None = None
    labels: list[str] | None = None
    model: str
    emulator_version: str
    substeps: int = Field(ge=1)
    seconds: float = Field(gt=0)
    refine: bool
    seed: int | None = None
    batch: int | None = None
    hidden: list[int]
    seeds: int | None = None  # a reward task's seeds side by side (None: the task's)


class PolicySpecError(ValueError):
    """A policy job that cannot be queued: the request's ``field``, what was expected and what was got."""

    def __init__(self, field: str, message: str, expected: Any = None, got: Any = None) -> None:
        super().__init__(message)
        self.field, self.expected, self.got = field, expected, got


def job_kind(spec: str) -> JobKind:
    """A job's kind from its spec (JSON)."""
    try:
        data = json.loads(spec)
    except ValueError:
        return "control"
    return POLICY if isinstance(data, dict) and data.get("kind") == POLICY else "control"


def policy_spec(req: PolicyJobCreate, root: registry.Root, max_seconds: float) -> PolicyJobSpec:
    """The job of a request, or ``PolicySpecError``: an unknown task (naming the built-in ones), a budget
    over ``max_seconds``, a task whose model has no emulator (that the caller sees) at its super-step,
    or a user's task that does not fit its model (``custom_policy.checked_task``: the field is
    ``task.<its field>``)."""
    if isinstance(req.task, PolicyTaskSpec):
        return _custom_spec(req, req.task, root, max_seconds)
    if isinstance(req.task, RewardTaskSpec):
        return _reward_spec(req, req.task, root, max_seconds)
    task: PolicyTask | SuiteTaskInfo | None = POLICY_TASKS.get(req.task) or SUITE_TASK_INFO.get(req.task)
    if task is None:
        known = sorted([*POLICY_TASKS, *SUITE_TASK_INFO])
        raise PolicySpecError(
            "task", f"unknown policy task {req.task!r}; built-in: {', '.join(known)}", known, req.task
        )
    seconds = _budget(req, task.train_seconds, max_seconds)
    need = f"an emulator of {task.model!r} at n = {task.substeps}"
    if isinstance(task, SuiteTaskInfo):
        need += f" ({task.train_command})"
    seen = tenancy.can_see(root, task.model)  # another key's unpublished upload: as if there were none
    try:
        if not seen:
            raise registry.ArtifactError("model", f"unknown model {task.model!r}")
        path = registry.resolve(root, task.model, None, task.substeps)
    except registry.ArtifactError as exc:
        have = registry.available_substeps(root, task.model) if seen else []
        raise PolicySpecError(
            "task",
            f"policy task {task.name!r} needs {need}: {exc}",
            need,
            {"model": task.model, "substeps": have},
        ) from exc
    return PolicyJobSpec(
        task=task.name,
        model=task.model,
        emulator_version=path.name,
        substeps=task.substeps,
        seconds=seconds,
        refine=req.refine,
        seed=req.seed,
        batch=req.batch,
        hidden=list(req.hidden or (REWARD_HIDDEN if isinstance(task, SuiteTaskInfo) else task.hidden)),
        seeds=_seeds(req, isinstance(task, SuiteTaskInfo)),
    )


def _custom_spec(
    req: PolicyJobCreate, given: PolicyTaskSpec, root: registry.Root, max_seconds: float
) -> PolicyJobSpec:
    """The job of a request with a user's own task, checked against its model's emulator."""
    try:
        checked = checked_task(given, root)
    except TaskDefinitionError as exc:
        field, message = (f"task.{exc.field}", f"task.{exc}") if exc.field else ("task", f"task: {exc}")
        raise PolicySpecError(field, message, exc.expected, exc.got) from exc
    task = checked.task
    return PolicyJobSpec(
        task=task.name,
        definition=checked.definition,
        labels=list(task.labels),
        model=task.model,
        emulator_version=checked.emulator.name,
        substeps=task.substeps,
        seconds=_budget(req, task.train_seconds, max_seconds),
        refine=req.refine,
        seed=req.seed,
        batch=req.batch,
        hidden=list(req.hidden or task.hidden),
        seeds=_seeds(req, False),
    )


def _reward_spec(
    req: PolicyJobCreate, given: RewardTaskSpec, root: registry.Root, max_seconds: float
) -> PolicyJobSpec:
    """The job of a request with a user's own reward task, checked against its model's emulator."""
    try:
        definition, emulator = checked_reward_task(given, root)
    except TaskDefinitionError as exc:
        field, message = (f"task.{exc.field}", f"task.{exc}") if exc.field else ("task", f"task: {exc}")
        raise PolicySpecError(field, message, exc.expected, exc.got) from exc
    assert definition.name is not None and definition.substeps is not None  # (filled in by the check)
    return PolicyJobSpec(
        task=definition.name,
        definition=definition,
        model=definition.model,
        emulator_version=emulator.name,
        substeps=definition.substeps,
        seconds=_budget(req, CUSTOM_REWARD_SECONDS, max_seconds),
        refine=req.refine,
        seed=req.seed,
        batch=req.batch,
        hidden=list(req.hidden or REWARD_HIDDEN),
        seeds=_seeds(req, True),
    )


def _seeds(req: PolicyJobCreate, reward: bool) -> int | None:
    """The request's seeds side by side: any number for a reward task; a goal-reaching task trains one."""
    if req.seeds is not None and req.seeds > 1 and not reward:
        raise PolicySpecError(
            "seeds",
            f"seeds: a goal-reaching task trains from one seed; several side by side are for a reward "
            f"task; got {req.seeds}",
            1,
            req.seeds,
        )
    return req.seeds if reward else None


def _budget(req: PolicyJobCreate, task_seconds: float, max_seconds: float) -> float:
    """The training budget: the request's, else the task's (at most ``max_seconds``)."""
    seconds = float(req.seconds) if req.seconds is not None else min(task_seconds, max_seconds)
    if seconds > max_seconds:
        raise PolicySpecError(
            "seconds",
            f"seconds: a policy job trains at most {max_seconds:g} s (POLICY_MAX_SECONDS); got {seconds:g}",
            f"<= {max_seconds:g}",
            req.seconds,
        )
    return seconds


def thin(values: Sequence[float | None], most: int = HISTORY_POINTS) -> list[HistoryPoint]:
    """A curve of one value per iteration (the first is iteration 1) as at most ``most`` points: each
    the mean of the finite values of a stretch of iterations, at the stretch's last iteration."""
    n = len(values)
    size = max(1, math.ceil(n / most))
    out = []
    for start in range(0, n, size):
        part = [v for v in values[start : start + size] if v is not None and math.isfinite(v)]
        out.append(
            HistoryPoint(iteration=min(n, start + size), value=sum(part) / len(part) if part else None)
        )
    return out
