"""A user's own policy task (``PolicyTaskSpec``, the ``task`` object of ``POST /policies``), torch-free:
checked at submission against the emulator it will be trained through, and built into the
``PolicyTask`` the trainer takes.

    PolicyTaskSpec --checked_task(spec, root)--> CheckedTask (name and super-step filled in, its
    PolicyTask, the emulator) --queued in PolicyJobSpec--> build_task --> PolicyTask

The checks read only the emulator's manifest (``registry.read_manifest``): S is its state size, its
``state_labels`` name the variables of the goal and of the success checks. ``TaskDefinitionError``
names the field inside the task (``goal.variables[1]``), the expected and the got.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neuroanimator.artifacts import registry
from neuroanimator.catalog.suite import SUITE_TASK_INFO
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.contracts.controller import PolicyTaskSpec, RewardTaskSpec
from neuroanimator.core.manifest import Manifest
from neuroanimator.goals import criteria
from neuroanimator.goals.criteria import SuccessCheck
from neuroanimator.goals.policy_task import GoalSpec, PolicyTask, StartBox
from neuroanimator.goals.spec import MAX_HORIZON
from services.common import tenancy

DEFAULT_PREFIX = "custom-"
"""A user's task without a name is named ``custom-<model>``."""


class TaskDefinitionError(ValueError):
    """A user's policy task that cannot be trained: the ``field`` inside the task, what was expected
    and what was got."""

    def __init__(self, field: str, message: str, expected: Any = None, got: Any = None) -> None:
        super().__init__(f"{field}: {message}" if field else message)
        self.field, self.expected, self.got = field, expected, got


@dataclass(frozen=True)
class CheckedTask:
    """A user's task as it is queued (its definition with ``name`` and ``substeps`` filled in), the
    ``PolicyTask`` it builds on its model's state labels, and the emulator it resolved to."""

    definition: PolicyTaskSpec
    task: PolicyTask
    emulator: Path


def checked_task(spec: PolicyTaskSpec, root: registry.Root) -> CheckedTask:
    """The task if it can be trained through an emulator the caller sees, else ``TaskDefinitionError``:
    an unknown (or unseen) model, no emulator at ``substeps``, a vector that is not S values (or G for
    the goal's bounds), an unknown label, a low above its high, bad success checks, times that do not
    fit the emulator's super-step or each other, a built-in task's name."""
    manifest, emulator = _emulator(spec, root)
    labels = list(manifest.state_labels)
    name = _own_name(spec)
    _check_states(spec, labels)
    _check_starts(spec, manifest)
    _check_goal(spec, labels)
    _check_success(spec, labels)
    _check_times(spec, manifest.super_timestep, manifest.substeps)
    definition = spec.model_copy(update={"name": name, "substeps": manifest.substeps})
    try:  # the checks above cover the constructor's; this keeps the two from drifting apart
        task = build_task(definition, labels)
    except ValueError as exc:
        raise TaskDefinitionError("", str(exc), got=name) from exc
    return CheckedTask(definition, task, emulator)


def build_task(definition: PolicyTaskSpec, labels: Sequence[str]) -> PolicyTask:
    """The ``PolicyTask`` of a checked definition (``name`` and ``substeps`` set) on a model whose state
    labels are ``labels`` (S); ``ValueError`` from ``PolicyTask`` where they do not fit."""
    if definition.name is None or definition.substeps is None:
        raise ValueError("a user's policy task is built once checked: its name and substeps are set")
    starts, goal = definition.starts, definition.goal
    return PolicyTask(
        name=definition.name,
        model=definition.model,
        summary=definition.summary or f"a policy task of {definition.model}",
        labels=tuple(labels),
        substeps=definition.substeps,
        episode_s=definition.episode_s,
        starts=StartBox(
            low=tuple(starts.low),
            high=tuple(starts.high),
            random_yaw=starts.random_yaw,
            max_tilt=starts.max_tilt,
        ),
        goal=GoalSpec(
            variables=tuple(goal.variables),
            low=tuple(goal.low),
            high=tuple(goal.high),
            at_rest=goal.at_rest,
            rest_speed=goal.rest_speed,
            holdable=goal.holdable,
            max_move=goal.max_move,
        ),
        target_state=tuple(definition.target_state),
        state_weights=tuple(definition.state_weights),
        success=tuple(
            SuccessCheck.model_validate(c.model_dump(exclude_none=True)) for c in definition.success
        ),
        goal_period_s=definition.goal_period_s,
        check_after_s=definition.check_after_s,
        settle_s=definition.settle_s,
        timed=definition.timed,
    )


def _emulator(spec: PolicyTaskSpec | RewardTaskSpec, root: registry.Root) -> tuple[Manifest, Path]:
    """The manifest and folder of the emulator the task trains through: the model's latest at
    ``substeps``, else its latest. A model the caller does not see (another key's upload) is unknown."""
    model = spec.model
    seen = tenancy.visible_models(root)
    if model not in seen:
        raise TaskDefinitionError("model", f"unknown model {model!r}; trained models are {seen}", seen, model)
    try:
        substeps = spec.substeps or registry.read_manifest(registry.resolve(root, model)).substeps
        path = registry.resolve(root, model, None, substeps)
        manifest = registry.read_manifest(path)
    except registry.ArtifactError as exc:
        have = registry.available_substeps(root, model)
        field = "substeps" if spec.substeps is not None else "model"
        raise TaskDefinitionError(field, str(exc), have, spec.substeps or model) from exc
    if not manifest.controls:
        raise TaskDefinitionError(
            "model",
            f"model {model!r} has no controls: there is nothing to control",
            "a model with controls",
            model,
        )
    return manifest, path


def _size(field: str, values: Sequence[float], size: int, what: str) -> None:
    if len(values) != size:
        raise TaskDefinitionError(
            field, f"must be {size} values ({what}), got {len(values)}", f"{size} values", len(values)
        )


def _ordered(field: str, low: Sequence[float], high: Sequence[float], names: Sequence[str]) -> None:
    """Every low at most its high (``field`` names the low list)."""
    for i, (lo, hi) in enumerate(zip(low, high, strict=True)):
        if lo > hi:
            raise TaskDefinitionError(
                f"{field}[{i}]", f"{names[i]}: low {lo:g} is above high {hi:g}", f"<= {hi:g}", lo
            )


def _check_states(spec: PolicyTaskSpec, labels: list[str]) -> None:
    what = f"one per state variable: {', '.join(labels)}"
    _size("target_state", spec.target_state, len(labels), what)
    _size("state_weights", spec.state_weights, len(labels), what)


def _check_starts(spec: PolicyTaskSpec, manifest: Manifest) -> None:
    labels = list(manifest.state_labels)
    what = f"one per state variable: {', '.join(labels)}"
    _size("starts.low", spec.starts.low, len(labels), what)
    _size("starts.high", spec.starts.high, len(labels), what)
    _ordered("starts.low", spec.starts.low, spec.starts.high, labels)
    # only a quaternion is turned and tilted: on another model they would be silently ignored
    if manifest.state_layout().find("quaternion") is None:
        for field, value, off in (
            ("random_yaw", spec.starts.random_yaw, False),
            ("max_tilt", spec.starts.max_tilt, 0.0),
        ):
            if value != off:
                raise TaskDefinitionError(
                    f"starts.{field}",
                    f"model {manifest.model!r} has no orientation quaternion to turn or tilt; its start "
                    "angles are in starts.low and starts.high",
                    off,
                    value,
                )


def _check_goal(spec: PolicyTaskSpec, labels: list[str]) -> None:
    goal = spec.goal
    for i, name in enumerate(goal.variables):
        if name not in labels:
            raise TaskDefinitionError(
                f"goal.variables[{i}]", f"unknown state label {name!r}; labels are {labels}", labels, name
            )
        if name in goal.variables[:i]:
            raise TaskDefinitionError(
                f"goal.variables[{i}]", f"{name!r} is named twice", "distinct labels", name
            )
    what = f"one per goal variable: {', '.join(goal.variables)}"
    _size("goal.low", goal.low, len(goal.variables), what)
    _size("goal.high", goal.high, len(goal.variables), what)
    _ordered("goal.low", goal.low, goal.high, goal.variables)
    # the policy learns the goal only through the weighted distance to it
    weights = [spec.state_weights[labels.index(v)] for v in goal.variables]
    if not any(w > 0 for w in weights):
        raise TaskDefinitionError(
            "state_weights",
            f"the goal variables {list(goal.variables)} all weigh 0: the distance to the goal would not count",
            "a positive weight on a goal variable",
            weights,
        )


def _check_success(spec: PolicyTaskSpec, labels: list[str]) -> None:
    checks = [c.model_dump(exclude_none=True) for c in spec.success]
    problems = criteria.validate_checks(checks, labels)
    if problems:
        where, what = problems[0]
        raise TaskDefinitionError(f"success{where}", what, what, _at(checks, where))


def _at(data: Any, path: str) -> Any:
    """The value at a path such as ``[0].target[1]`` inside ``data`` (None where there is none)."""
    for key in re.findall(r"\[(\d+)\]|\.?([A-Za-z_]\w*)", path):
        index, name = key
        try:
            data = data[int(index)] if index else data.get(name)
        except (IndexError, KeyError, TypeError, AttributeError):
            return None
    return data


def _check_times(spec: PolicyTaskSpec, super_dt: float, substeps: int) -> None:
    """Every time at least one super-step of the emulator (``super_dt`` seconds), a run at most
    ``MAX_HORIZON`` of them, a goal's period within the run and the check and settling within it."""
    step = _check_episode(spec.episode_s, super_dt, substeps)
    period = spec.episode_s
    if spec.goal_period_s is not None:
        period = spec.goal_period_s
        if not super_dt <= period <= spec.episode_s:
            raise TaskDefinitionError(
                "goal_period_s",
                f"must be between {super_dt:g} s ({step}) and the run's {spec.episode_s:g} s, got {period:g}",
                f"[{super_dt:g}, {spec.episode_s:g}]",
                period,
            )
    if spec.check_after_s is not None and not super_dt <= spec.check_after_s <= period:
        raise TaskDefinitionError(
            "check_after_s",
            f"must be between {super_dt:g} s ({step}) and a goal's period ({period:g} s), "
            f"got {spec.check_after_s:g}",
            f"[{super_dt:g}, {period:g}]",
            spec.check_after_s,
        )
    if spec.settle_s > period:
        raise TaskDefinitionError(
            "settle_s",
            f"must be at most a goal's period ({period:g} s), got {spec.settle_s:g}",
            f"<= {period:g}",
            spec.settle_s,
        )


def _check_episode(episode_s: float, super_dt: float, substeps: int) -> str:
    """A run of at least one super-step (``super_dt`` seconds) and at most ``MAX_HORIZON``; returns how
    a super-step is named in messages."""
    step = f"one super-step of the n = {substeps} emulator"
    longest = MAX_HORIZON * super_dt
    if episode_s < super_dt or episode_s > longest + 1e-9:
        raise TaskDefinitionError(
            "episode_s",
            f"must be between {super_dt:g} s ({step}) and {longest:g} s ({MAX_HORIZON} super-steps), "
            f"got {episode_s:g}",
            f"[{super_dt:g}, {longest:g}]",
            episode_s,
        )
    return step


def checked_reward_task(spec: RewardTaskSpec, root: registry.Root) -> tuple[RewardTaskSpec, Path]:
    """A user's reward task as it is queued (``name`` and ``substeps`` filled in) and the emulator it
    trains through, else ``TaskDefinitionError``: an unknown (or unseen) model, no emulator at
    ``substeps``, a model without controls, a run shorter than a super-step or longer than
    ``MAX_HORIZON`` of them, a built-in task's name. Its bodies are the MJCF's, which this process
    does not load: a term naming a body the model lacks fails the job, saying which bodies it has."""
    manifest, emulator = _emulator(spec, root)
    name = _own_name(spec)
    _check_episode(spec.episode_s, manifest.super_timestep, manifest.substeps)
    return spec.model_copy(update={"name": name, "substeps": manifest.substeps}), emulator


def _own_name(spec: PolicyTaskSpec | RewardTaskSpec) -> str:
    """The task's name (default ``custom-<model>``), unless it is a built-in task's."""
    name = spec.name or f"{DEFAULT_PREFIX}{spec.model}"
    if name in POLICY_TASKS or name in SUITE_TASK_INFO:
        raise TaskDefinitionError(
            "name", f"{name!r} is a built-in policy task's name; choose another", "a name of your own", name
        )
    return name
