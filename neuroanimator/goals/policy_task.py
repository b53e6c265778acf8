"""Policy tasks: what a feedback controller learned through the emulator is asked to do, for any start
and any goal (thesis 7.2.3).

A control-synthesis job (``spec.Task``) asks for one controller, for one start and one goal, replayed
open loop. A ``PolicyTask`` asks for a policy ``π(state, goal) → controls`` that reads the state every
super-step: its starts are drawn from a box (``StartBox``), its goals from the states MuJoCo itself
reaches (``GoalSpec``: the goal variables of states of the model's typical motion that fall inside a
box), so that every goal is reachable, and its success is the same checks as a job's
(``criteria.SuccessCheck``), evaluated with the goal written into the task's target state. A goal
may move (``goal_period_s``: a new one every so many seconds, as a game's target does); the checks
then hold ``check_after_s`` after every move.

The policy is trained to bring the goal variables to the goal and keep them there: the loss of a
rollout is the weighted distance of every state to the target (``state_weights``), counted from the
time it can be expected to hold (``settle_s`` after a goal is set) and lightly before. A ``timed``
task also tells the policy how long is left until the check (a lander that must touch down as the
run ends; a pendulum that must arrive at a pose at rest at a given time, at the top of a swing);
without ``settle_s`` only arriving on time counts. At the state the checks judge, the loss also counts
how far each check is from being met with room to spare (``check_weight``): the distance trades
its variables against each other, a check does not.

Torch-free and MuJoCo-free; the catalog defines its tasks beside its models (``POLICY_TASKS``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from neuroanimator.goals import criteria
from neuroanimator.goals.criteria import SuccessCheck


@dataclass(frozen=True)
class StartBox:
    """Where a policy's runs start: every state variable uniform in [low, high] (S values each); a
    quaternion group (if the model has one) turned by a random yaw (``random_yaw``) and tilted by at
    most ``max_tilt`` radians about a random horizontal axis from upright."""

    low: tuple[float, ...]
    high: tuple[float, ...]
    random_yaw: bool = False
    max_tilt: float = 0.0


@dataclass(frozen=True)
class GoalSpec:
    """A policy's goals: values of ``variables`` (state labels) taken from states MuJoCo reaches in the
        model's typical motion from the task's starts, within [low, high] per variable. ``at_rest`` keeps
        only states whose speeds (every ``qvel`` variable) are below ``rest_speed``: poses the model passes
        through at rest, the turning points of a swing; ``holdable`` only those its controls can then hold
    still, within their ranges (a pose to go to and stay at). A goal that moves (``PolicyTask.goal_period_s``)
        moves at most ``max_move`` (the Euclidean distance over its variables) each time."""

    variables: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    at_rest: bool = False
    rest_speed: float = 0.3
    max_move: float | None = None  # a moving goal's next value within this distance of its last
    holdable: bool = False  # only poses the model's controls can hold still (within their ranges)

    def __post_init__(self) -> None:
        if not (len(self.variables) == len(self.low) == len(self.high)) or not self.variables:
            raise ValueError("a goal needs one low and one high per variable, and at least one variable")


@dataclass(frozen=True)
class PolicyTask:
    """A feedback-control problem on one model: its starts, its goals, how success is judged, and the
    control period it needs (``substeps``: the emulator's super-step; a balancing pole needs feedback
    well within its fall time).

    ``episode_s`` is a run's length; with ``goal_period_s`` the goal moves that often (else once per
    run) and the success checks hold ``check_after_s`` after every move (else at the end of each goal's
    period). States are in the model's layout order, ``labels`` its labels."""

    name: str
    model: str
    summary: str
    labels: tuple[str, ...]
    substeps: int
    episode_s: float
    starts: StartBox
    goal: GoalSpec
    target_state: tuple[float, ...]
    state_weights: tuple[float, ...]
    success: tuple[SuccessCheck, ...]
    goal_period_s: float | None = None
    check_after_s: float | None = None
    settle_s: float = 0.0
    timed: bool = False
    control_weight: float = 1e-3
    check_weight: float = 1.0  # the success checks' own margin at the state they judge, beside the distance
    hidden: tuple[int, ...] = (64, 64)  # small: it runs beside the emulator every served super-step
    train_seconds: float = 600.0
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        size = len(self.labels)
        for name in ("target_state", "state_weights"):
            if len(getattr(self, name)) != size:
                raise ValueError(f"policy task {self.name}: {name} must have {size} values")
        for name in ("low", "high"):
            if len(getattr(self.starts, name)) != size:
                raise ValueError(f"policy task {self.name}: starts.{name} must have {size} values")
        unknown = [v for v in self.goal.variables if v not in self.labels]
        if unknown:
            raise ValueError(f"policy task {self.name}: goal variables {unknown} are not state labels")
        problems = criteria.validate_checks([c.model_dump() for c in self.success], self.labels)
        if problems:
            where, what = problems[0]
            raise ValueError(f"policy task {self.name}: success{where} {what}")
        if self.check_after_s is not None and self.check_after_s > self.period_s:
            raise ValueError(f"policy task {self.name}: check_after_s is longer than a goal's period")

    @property
    def period_s(self) -> float:
        """Seconds each goal is held: ``goal_period_s``, or the whole run."""
        return self.episode_s if self.goal_period_s is None else self.goal_period_s

    @property
    def goals_per_run(self) -> int:
        return max(1, round(self.episode_s / self.period_s))

    @property
    def check_s(self) -> float:
        """Seconds after a goal is set at which the success checks hold."""
        return self.period_s if self.check_after_s is None else self.check_after_s

    @property
    def goal_columns(self) -> list[int]:
        return [self.labels.index(v) for v in self.goal.variables]

    def target_with(self, goal: tuple[float, ...] | list[float]) -> list[float]:
        """The target state (S,) with the goal's values (G,) written into its goal variables."""
        out = list(self.target_state)
        for col, value in zip(self.goal_columns, goal, strict=True):
            out[col] = float(value)
        return out

    @property
    def success_text(self) -> str:
        when = (
            f"{self.check_s:g} s after each goal is set"
            if self.goal_period_s is not None
            else f"at the end of the {self.episode_s:g} s run"
        )
        return f"{criteria.describe(self.success, self.target_state, self.labels)}, {when}"

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able data, for ``GET /policy-tasks``."""
        return {
            "name": self.name,
            "model": self.model,
            "description": self.summary,
            "substeps": self.substeps,
            "episode_s": self.episode_s,
            "goal_period_s": self.goal_period_s,
            "check_after_s": self.check_s,
            "goal_variables": list(self.goal.variables),
            "goal_low": list(self.goal.low),
            "goal_high": list(self.goal.high),
            "success_criterion": self.success_text,
            "success": [c.model_dump() for c in self.success],
            "state_labels": list(self.labels),
            "target_state": list(self.target_state),
            "timed": self.timed,
        }


def steps_of(seconds: float, super_dt: float) -> int:
    """Super-steps of ``super_dt`` seconds in ``seconds``, at least 1."""
    return max(1, round(seconds / super_dt))


def goal_schedule(task: PolicyTask, super_dt: float) -> tuple[int, int, int]:
    """(steps per run, steps per goal, step within a goal's period at which the checks hold)."""
    per_goal = steps_of(task.period_s, super_dt)
    return per_goal * task.goals_per_run, per_goal, min(per_goal, steps_of(task.check_s, super_dt))
