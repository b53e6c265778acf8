"""The controller service's wire contract: pydantic v2 models of its requests, replies and events.

A job is a controller-synthesis problem (thesis ch. 5): a built-in ``task`` (``GET /tasks``) with
optional overrides, or a custom objective over a ``model``. The service checks the request's types
here (finite JSON numbers, positive sizes) and the job against the model and task with
``neuroanimator.control.validation.validate_job``; both answer 422 naming the field.

    JobCreate --validate_job--> JobSpec (neuroanimator.goals.spec) --run_job--> JobOutcome
    --stored with the job's id--> JobResult

A policy job trains a feedback policy for a built-in policy task (``GET /policy-tasks``) through the
task's emulator and stores it (``neuroanimator.control.policy_job``):

    PolicyJobCreate --checked at submission--> the job's spec --run_policy_job--> PolicyOutcome
    --stored with the job's id--> PolicyJobResult (the stored policy's PolicyManifest inside)

Numbers that are not finite (an objective that diverged to NaN) travel as ``null``.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidatorFunctionWrapHandler,
    WrapValidator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from neuroanimator.contracts.emulator import Flag, Integer, Number
from neuroanimator.core.policy_manifest import PolicyManifest
from neuroanimator.goals.criteria import CheckKind
from neuroanimator.goals.spec import (
    MAX_GLOBAL_GENERATIONS,
    MAX_HORIZON,
    MAX_ITERATIONS,
    MAX_LEARNING_RATE,
    MAX_MU,
    MAX_PHYSICS_ROUNDS,
    MAX_STARTS,
    MAX_SUBSTEPS,
    JobSpec,
)
from neuroanimator.goals.terms import MAX_VALUE, MAX_WEIGHT
from neuroanimator.goals.verdict import verdict as verdict_of

MAX_VECTOR = 1024
"""The longest state, weight or control vector a request may carry (the service then checks it
against the model's own size)."""
MAX_LABEL = 128
"""The longest state label, term name or model name."""
Vector = Annotated[list[Number], Field(max_length=MAX_VECTOR)]
"""A list of finite JSON numbers, at most ``MAX_VECTOR`` of them."""
Bounded = Annotated[Number, Field(ge=-MAX_VALUE, le=MAX_VALUE)]
"""A finite number of magnitude at most ``terms.MAX_VALUE`` (a state value, target or bound)."""
Label = Annotated[str, Field(min_length=1, max_length=MAX_LABEL)]

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
"""queued (waiting for a worker, also after a re-queue) → running → succeeded | failed | cancelled."""
FINAL_STATES: tuple[str, ...] = ("succeeded", "failed", "cancelled")
MaybeFloat = float | None
"""A number that is ``null`` where it was not finite (NaN, ±inf)."""


class _Wire(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _absent(value: object) -> bool:
    return value is None


# ---------------------------------------------------------------- requests
class OptimizerSpec(_Wire):
    """Gradient descent with momentum (thesis eq. 5.4): ``u ← u − η∇J + α·δu_prev``; it stops after
    ``max_iterations`` or when the objective improves by less than ``tolerance``."""

    learning_rate: Number | None = Field(None, gt=0, le=MAX_LEARNING_RATE, description="η")
    momentum: Number | None = Field(None, ge=0, lt=1, description="α")
    max_iterations: Integer | None = Field(
        None,
        ge=1,
        le=MAX_ITERATIONS,
        description="cap on the gradient-descent updates (the Levenberg-Marquardt ones after them have their own)",
    )
    tolerance: Number | None = Field(None, ge=0, le=1, description="stop when the objective changes less")
    stop_on_success: Flag | None = Field(None, description="stop once the success criterion holds")
    line_search: Flag | None = Field(
        None, description="pick η and α afresh each iteration from a batch of candidates (off: fixed η, α)"
    )
    polish_iterations: Integer | None = Field(
        None, ge=0, le=MAX_ITERATIONS, description="updates after the success criterion first holds"
    )
    physics_rounds: Integer | None = Field(
        None,
        ge=0,
        le=MAX_PHYSICS_ROUNDS,
        description="rounds of re-optimising on an emulator corrected by the MuJoCo replay",
    )
    starts: Integer | None = Field(
        None,
        ge=1,
        le=MAX_STARTS,
        description="controllers descended at once, from a global search's best and fixed starts",
    )
    global_generations: Integer | None = Field(
        None,
        ge=0,
        le=MAX_GLOBAL_GENERATIONS,
        description="generations of the cross-entropy search before gradient descent (0: none)",
    )
    gauss_newton_iterations: Integer | None = Field(
        None,
        ge=0,
        le=MAX_ITERATIONS,
        description=(
            "Levenberg-Marquardt updates when gradient descent ends without meeting the success "
            "criterion on the emulator (0: none)"
        ),
    )


class ObjectiveTerm(BaseModel):
    """One term of a custom objective: ``term`` names it, its other keys are the term's parameters
    (``GET /tasks`` and the README list them; the service checks each against the model, 422 naming it)."""

    model_config = ConfigDict(extra="allow")
    term: str = Field(min_length=1, max_length=64)


class SuccessCheckSpec(_Wire):
    """One check on the final state (``neuroanimator.goals.criteria``): ``variables`` are state labels
    of the model; ``target`` (one value per variable) overrides the job's target state; ``max`` bounds
    the measured value (``range``: ``min`` and/or ``max``)."""

    check: CheckKind
    variables: list[Label] = Field(min_length=1, max_length=MAX_VECTOR)
    max: Bounded | None = None
    min: Bounded | None = None
    target: Annotated[list[Bounded], Field(max_length=MAX_VECTOR)] | None = None


class JobCreate(_Wire):
    """A controller-synthesis job: a built-in ``task`` and/or a ``model`` with the objective's pieces;
    every field left out takes the task's (or the default) value."""

    task: str | None = Field(None, max_length=64, description="a built-in task of GET /tasks")
    model: str | None = Field(None, max_length=128, description="an emulator in the artifact registry")
    version: str | None = Field(None, max_length=128, description="an artifact version (default: latest)")
    substeps: Integer | None = Field(
        None, ge=1, le=MAX_SUBSTEPS, description="the emulator's super timestep n"
    )
    initial_state: Vector | None = None
    target_state: Vector | None = Field(None, description="s_d of the final-state term")
    state_weights: Vector | None = Field(None, description="weight of each state variable in that term")
    horizon: Integer | None = Field(
        None, ge=1, le=MAX_HORIZON, description="length of the controller, in super-steps"
    )
    points_per_step: Number | None = Field(None, gt=0, le=1, description="control points per super-step")
    initial_controls: Vector | None = Field(None, description="the controls the optimisation starts from")
    mu_u: Number | None = Field(None, ge=0, le=MAX_MU, description="μ_u, weight of the control effort")
    mu_s: Number | None = Field(None, ge=0, le=MAX_MU, description="μ_s, weight of the final-state error")
    terms: list[ObjectiveTerm] | None = Field(None, max_length=32, description="a custom objective")
    success: list[SuccessCheckSpec] | None = Field(
        None, max_length=32, description="checks on the final state that define success"
    )
    optimizer: OptimizerSpec | None = None
    idempotency_key: str | None = Field(
        None,
        min_length=1,
        max_length=128,
        pattern=r"^[\x21-\x7e]+$",
        description="the same key (and body) returns the same job instead of a new one",
    )

    def spec(self) -> dict[str, Any]:
        """The job's request as JSON (what ``validate_job`` checks): the set fields, less the key."""
        return self.model_dump(exclude_none=True, exclude={"idempotency_key"})


# ---------------------------------------------------------------- replies
class JobAccepted(BaseModel):
    """A job on the queue (or, for a repeated idempotency key, the job it already made)."""

    id: str
    status: JobState
    created: bool = Field(True, description="false when an idempotency key returned an existing job")


class BestSoFar(BaseModel):
    """The best controller found so far (lowest finite objective)."""

    model_config = ConfigDict(extra="allow")
    iteration: int | None = None
    objective: MaybeFloat = None


class JobStatus(BaseModel):
    """A job as it runs: the progress of its current attempt and, once it ended, how."""

    id: str
    status: JobState
    task: str | None = None
    model: str | None = None
    version: str | None = None
    created_at: float = Field(description="Unix time")
    started_at: float | None = None
    ended_at: float | None = None
    attempt: int = Field(0, description="runs started (a re-queued job starts again)")
    failures: int = Field(0, description="runs that crashed, raised or were abandoned by their worker")
    worker: str | None = None
    iteration: int = 0
    max_iterations: int | None = None
    objective: MaybeFloat = None
    best_objective: MaybeFloat = None
    success_emulator: bool | None = None
    elapsed_s: float | None = None
    objective_history: list[MaybeFloat] = []
    best: BestSoFar | None = Field(None, description="the best controller so far")
    error: str | None = Field(None, description="why it failed or was cancelled (or why it was re-queued)")
    result: str | None = Field(None, description="where the result is, once the job ended")


class JobSummary(BaseModel):
    """One line of GET /jobs."""

    id: str
    status: JobState
    task: str | None = None
    model: str | None = None
    created_at: float
    ended_at: float | None = None
    iteration: int = 0
    best_objective: MaybeFloat = None


class JobList(BaseModel):
    """The caller's jobs, newest first."""

    jobs: list[JobSummary]


class Trajectory(BaseModel):
    """States at ``times``: one row of S numbers per time."""

    model_config = ConfigDict(extra="allow")
    states: list[list[MaybeFloat]] = []


class CheckOutcome(BaseModel):
    """One success check on a final state: its text, whether it held, and the value measured."""

    check: str
    passed: bool
    value: MaybeFloat = None


class EmulatorPhase(BaseModel):
    """The controller found on the emulator alone, before any physics refinement, and its replay."""

    objective: MaybeFloat = None
    success_emulator: bool | None = None
    success_physics: bool | None = None
    final_error_emulator: MaybeFloat = None
    final_error_physics: MaybeFloat = None


class RefinementRound(BaseModel):
    """One round of re-optimising on the emulator corrected along the last MuJoCo replay."""

    round: int
    iterations: int
    stop: str
    # a diverged round has a reason; the others an objective and a success on MuJoCo
    reason: str | None = Field(None, description="why the round ended early", exclude_if=_absent)
    objective_physics: MaybeFloat = Field(None, exclude_if=_absent)
    success_physics: bool | None = Field(None, exclude_if=_absent)


class Refinement(BaseModel):
    """The physics-refinement rounds of a run (none when the first replay met the criterion)."""

    rounds: list[RefinementRound] = []
    iterations: int = 0
    physics_replays: int = Field(1, description="MuJoCo replays, the first one included")


class GaussNewtonInfo(BaseModel):
    """The Levenberg-Marquardt updates that followed gradient descent when it ended short of the
    criterion on the emulator (``neuroanimator.control.gauss_newton``), over the whole run."""

    runs: int = Field(0, description="times it ran: after the emulator descent and per refinement round")
    iterations: int = Field(0, description="updates made, all runs together")
    rollouts: int = Field(0, description="emulator trajectories it scored (Jacobians and damping candidates)")
    success: bool = Field(
        False, description="whether a run reached the criterion that the descent before it missed"
    )


class SearchInfo(BaseModel):
    """The search before single-start descent: a cross-entropy pass and several starts descended at
    once, all batched on the emulator (``neuroanimator.control.search``)."""

    starts: int = Field(1, description="controllers descended at once")
    global_rollouts: int = Field(0, description="controllers the global (cross-entropy) pass scored")
    start_iterations: int = Field(0, description="batched descent iterations over all starts")
    chosen: str = Field("initial controls", description="the start the returned controller came from")


class JobOutcome(BaseModel):
    """What ``run_job`` returns (a job that crashed has only ``status``, ``reason`` and what was known):
    the controller (control points and the sampled ``controls`` at ``times``), the trajectory it gives
    on the emulator and on the physics (MuJoCo), and their errors against the target.

    Shapes: M control points and K super-steps per controller, U controls, S state variables."""

    model_config = ConfigDict(extra="allow")
    status: Literal["succeeded", "failed", "cancelled"]
    verdict: str | None = Field(
        None,
        description=(
            "how the job ended, in words for a report (``status`` only says the run ended normally): "
            "succeeded (the controller meets the success criterion on MuJoCo) | done, no criterion | "
            "done, criterion met on the emulator only | done, criterion missed | failed | cancelled; "
            "worked out from the status and the success fields when not given"
        ),
    )
    reason: str | None = None
    stop: str | None = Field(
        None,
        description=(
            "success | converged | stalled | max_iterations | missed_on_physics (met on the emulator, "
            "neither on the returned controller's emulation nor on MuJoCo) | diverged | cancelled"
        ),
    )
    task: str | None = None
    model: str | None = None
    version: str | None = None
    substeps: int | None = None
    iterations: int | None = None
    iterations_to_success: int | None = None
    emulator_rollouts: int | None = None
    bptt_networks: Literal["all", "global"] | None = Field(
        None,
        description=(
            "the networks the gradients went through: all (the emulator's whole step) or global (a "
            "hierarchy's global network alone, as the objective depends only on the parts' frames)"
        ),
    )
    objective: MaybeFloat = None
    objective_physics: MaybeFloat = None
    objective_history: list[MaybeFloat] = []
    best_objective: MaybeFloat = Field(None, description="of a job that ended before it returned")
    control_names: list[str] | None = None
    control_points: list[list[MaybeFloat]] | None = Field(None, description="M × U, in the controls' units")
    control_spacing_s: float | None = None
    super_timestep: float | None = None
    times: list[float] | None = Field(None, description="the K super-steps' start times")
    controls: list[list[MaybeFloat]] | None = Field(None, description="K × U held values")
    emulated: Trajectory | None = None
    physical: Trajectory | None = None
    final_error_emulator: MaybeFloat = None
    final_error_physics: MaybeFloat = None
    final_errors_emulator: dict[str, MaybeFloat] | None = Field(
        None, description="|error| per weighted variable"
    )
    final_errors_physics: dict[str, MaybeFloat] | None = None
    transfer_error: MaybeFloat = Field(None, description="how far MuJoCo ends from the emulator's end")
    success_criterion: str | None = None
    success_emulator: bool | None = None
    success_physics: bool | None = None
    checks_emulator: list[CheckOutcome] | None = None
    checks_physics: list[CheckOutcome] | None = None
    reachable: bool | None = Field(
        None, description="whether a controller meets the criterion (null: the job has none)"
    )
    reachability: str | None = Field(None, description="why the goal counts as reached or unreachable")
    search: SearchInfo | None = None
    gauss_newton: GaussNewtonInfo | None = None
    emulator_phase: EmulatorPhase | None = None
    refinement: Refinement | None = None
    target_state: list[MaybeFloat] | None = None
    initial_state: list[MaybeFloat] | None = None
    state_labels: list[str] | None = None
    spec: JobSpec | None = Field(None, description="the validated job that ran")
    wall_s: float | None = None

    @model_validator(mode="after")
    def _verdict(self) -> JobOutcome:
        # every outcome says it, stored results from before the field too: they are read through here
        if self.verdict is None:
            self.verdict = verdict_of(
                self.status, self.success_criterion, self.success_emulator, self.success_physics
            )
        return self


class JobResult(JobOutcome):
    """A job's result (``GET /jobs/{id}/result``): what its run returned, and the job's id."""

    id: str


class TaskInfo(BaseModel):
    """A built-in task: its model and default parameters (whatever the task defines)."""

    model_config = ConfigDict(extra="allow")
    name: str


class TaskList(BaseModel):
    tasks: list[TaskInfo]


# ---------------------------------------------------------------- events (SSE and websocket)
class ProgressEvent(BaseModel):
    """``event: progress``: one optimisation iteration of the current attempt."""

    model_config = ConfigDict(extra="allow")
    iteration: int
    objective: MaybeFloat = None
    best_objective: MaybeFloat = None
    success_emulator: bool | None = None
    elapsed_s: float | None = None
    attempt: int | None = None


class StatusEvent(BaseModel):
    """``event: status``: the job was queued, started, or re-queued (with why)."""

    status: JobState
    attempt: int | None = None
    reason: str | None = None


class EndEvent(BaseModel):
    """``event: end``: the last event of a job's stream."""

    status: Literal["succeeded", "failed", "cancelled", "expired"]
    reason: str | None = None
    iterations: int | None = None
    best_objective: MaybeFloat = None


class WsEvent(BaseModel):
    """A websocket message of ``/ws/jobs/{id}``: the SSE event's name and its data."""

    event: Literal["progress", "status", "end"]
    data: dict[str, Any]


# ---------------------------------------------------------------- policy jobs
MIN_POLICY_SECONDS = 5.0
"""The shortest training budget a policy job may ask for (the longest is the service's
``POLICY_MAX_SECONDS``)."""
MAX_POLICY_BATCH = 4096
MAX_POLICY_SEEDS = 8  # a reward policy's seeds trained side by side (a process and a core each)
MAX_POLICY_WIDTH = 1024
MAX_POLICY_LAYERS = 8
HISTORY_POINTS = 100
"""The most points of a policy job's loss history (``HistoryPoint``s, each the mean over its stretch)."""
PolicyWidth = Annotated[int, Field(strict=True, ge=1, le=MAX_POLICY_WIDTH)]


MAX_POLICY_EPISODE_S = 600.0
"""The longest run a user's policy task may ask for (the service also caps it at ``MAX_HORIZON``
super-steps of its emulator)."""
MAX_POLICY_CHECKS = 32
PolicyTaskName = Annotated[str, Field(min_length=1, max_length=64)]
Weight = Annotated[Number, Field(ge=0, le=MAX_WEIGHT)]
"""A state variable's weight: finite, not negative, at most ``terms.MAX_WEIGHT``."""
Seconds = Annotated[Number, Field(gt=0, le=MAX_POLICY_EPISODE_S)]


class PolicyStartsSpec(_Wire):
    """Where a user's policy task's runs start: every state variable uniform in [low, high] (S values
    each, in the model's state order); a model with an orientation quaternion turned by a random yaw
    (``random_yaw``) and tilted by at most ``max_tilt`` radians from upright."""

    low: Annotated[list[Bounded], Field(min_length=1, max_length=MAX_VECTOR)]
    high: Annotated[list[Bounded], Field(min_length=1, max_length=MAX_VECTOR)]
    random_yaw: Flag = Field(False, description="any heading (a model with a quaternion only)")
    max_tilt: Number = Field(
        0.0, ge=0, le=math.pi, description="radians from upright (a model with a quaternion only)"
    )


class PolicyGoalSpec(_Wire):
    """A user's policy task's goals: values of ``variables`` (state labels) that MuJoCo's runs of the
    model's typical motion from the starts reach, within [low, high] per variable (G values each)."""

    variables: Annotated[list[Label], Field(min_length=1, max_length=MAX_VECTOR)]
    low: Annotated[list[Bounded], Field(min_length=1, max_length=MAX_VECTOR)]
    high: Annotated[list[Bounded], Field(min_length=1, max_length=MAX_VECTOR)]
    at_rest: Flag = Field(False, description="only poses passed through at rest (every speed small)")
    rest_speed: Number = Field(0.3, gt=0, le=MAX_VALUE, description="what counts as at rest")
    holdable: Flag = Field(False, description="only poses the model's controls can hold still")
    max_move: Number | None = Field(
        None,
        gt=0,
        le=MAX_VALUE,
        description="a moving goal's next value within this distance of its last (null: anywhere)",
    )


class _OwnTask(_Wire):
    """What every task of a user's own names: its model and emulator, its name, its runs' length."""

    model: str = Field(min_length=1, max_length=MAX_LABEL, description="a model in the artifact registry")
    substeps: Integer | None = Field(
        None,
        ge=1,
        le=MAX_SUBSTEPS,
        description="the emulator's super-step n, the policy's control period (default: the model's latest)",
    )
    name: str | None = Field(
        None,
        max_length=64,
        pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$",
        description="the stored policy's name, a plain name (default: custom-<model>)",
    )
    summary: str = Field("", max_length=1000, description="what the task asks, in words")
    episode_s: Seconds = Field(description="a run's length in seconds")


class PolicyTaskSpec(_OwnTask):
    """A user's own policy task (what ``GET /policy-tasks`` lists of a built-in one): a model, where its
    runs start, which goals it is asked to reach and how success is judged. States are S values in the
    model's state order (its emulator's ``state_labels``); the target state has the goal written into
    its goal variables; ``success`` checks are those of a control job (``POST /jobs``)."""

    starts: PolicyStartsSpec
    goal: PolicyGoalSpec
    target_state: Annotated[list[Bounded], Field(min_length=1, max_length=MAX_VECTOR)] = Field(
        description="the state to reach, S values (the goal's values replace its goal variables)"
    )
    state_weights: Annotated[list[Weight], Field(min_length=1, max_length=MAX_VECTOR)] = Field(
        description="each state variable's weight in the distance to the target, S values"
    )
    success: list[SuccessCheckSpec] = Field(
        min_length=1, max_length=MAX_POLICY_CHECKS, description="checks that define a run's success"
    )
    goal_period_s: Seconds | None = Field(
        None, description="a new goal every so many seconds (null: one goal per run)"
    )
    check_after_s: Number | None = Field(
        None,
        ge=0,
        le=MAX_POLICY_EPISODE_S,
        description="the checks hold this long after each goal is set (default: at its period's end)",
    )
    settle_s: Number = Field(
        0.0,
        ge=0,
        le=MAX_POLICY_EPISODE_S,
        description="seconds after a goal is set from which the distance to it fully counts",
    )
    timed: Flag = Field(False, description="the policy is told how long is left until the check")


MAX_REWARD_TERMS = 16
RewardTermKind = Literal["height", "upright", "speed", "still", "small_control"]


class RewardTermSpec(_Wire):
    """One term of a user's reward task, worth 0 to 1 at every super-step (the suite's
    ``rewards.tolerance``: 1 within the bound, falling off over ``margin`` outside it):

    - ``height``: the body's origin at least ``at_least`` metres above the world's z = 0 (margin
      default half of it, Gaussian);
    - ``upright``: the body's z axis at least ``at_least`` (a cosine, default 0.9) along the world's
      z (linear to 0 over the margin, default ``1 + at_least``: nothing when upside down);
    - ``speed``: the centre of mass of the body's subtree moving along ``axis`` at ``at_least`` m/s or
      faster (a negative speed: as fast backwards; linear from 0 at standstill, or over ``margin``);
    - ``still``: that centre of mass's horizontal speed near 0 (Gaussian over ``margin``, default 2
      m/s: the mean over x and y);
    - ``small_control``: the controls small, each as a share of its half range (``(4 + q) / 5``, q the
      mean of a quadratic falling to 0 at the range's ends: as the suite pays it).

    ``body`` (default: the model's root body, the first below the world) names a body of the MJCF."""

    kind: RewardTermKind
    body: Label | None = Field(None, description="a body of the model (default: its root body)")
    at_least: Bounded | None = Field(
        None, description="height: metres (required); upright: a cosine (default 0.9); speed: m/s (required)"
    )
    axis: Literal["x", "y"] = Field("x", description="speed: the world axis it is measured along")
    margin: Number | None = Field(
        None, gt=0, le=MAX_VALUE, description="how far outside the bound it still pays"
    )

    @model_validator(mode="after")
    def _needs_a_bound(self) -> RewardTermSpec:
        if self.kind in ("height", "speed") and self.at_least is None:
            raise ValueError(
                f"a {self.kind} term needs at_least ({'metres' if self.kind == 'height' else 'm/s'})"
            )
        if self.kind == "speed" and self.at_least == 0:
            raise ValueError("a speed term's at_least must not be 0 (a still body: use a still term)")
        if self.kind == "upright" and self.at_least is not None and not -1 <= self.at_least < 1:
            raise ValueError(f"an upright term's at_least is a cosine in [-1, 1), got {self.at_least:g}")
        return self


class RewardTaskSpec(_OwnTask):
    """A user's own reward task (``kind: "reward"``): a model (any MJCF brought in, the ground touched
    or not), runs of ``episode_s`` seconds from random joints (the suite's draw, again while the body
    touches anything) or from rest (its first keyframe, else ``qpos0``, a little perturbed), and a
    reward at every super-step: the product of its ``terms`` (``combine: "mean"``: their mean). The
    policy is learned for the return through the emulator and judged by it on MuJoCo; nothing sets a
    target: the return is reported."""

    kind: Literal["reward"]
    starts: Literal["random", "rest"] = Field("random", description="random joints, or the model at rest")
    terms: Annotated[list[RewardTermSpec], Field(min_length=1, max_length=MAX_REWARD_TERMS)]
    combine: Literal["product", "mean"] = Field("product", description="how the terms make the reward")


_TASK_NAME: TypeAdapter[str] = TypeAdapter(PolicyTaskName)


def _task_or_definition(
    value: Any, handler: ValidatorFunctionWrapHandler
) -> str | PolicyTaskSpec | RewardTaskSpec:
    """A built-in task's name or a user's task (a reward task has ``kind: "reward"``); a user's task's
    errors name its own fields (``task.goal.low[1]``), not the branch of the union they came from."""
    if isinstance(value, RewardTaskSpec) or (isinstance(value, dict) and "kind" in value):
        return RewardTaskSpec.model_validate(value)
    if isinstance(value, (dict, PolicyTaskSpec)):
        return PolicyTaskSpec.model_validate(value)
    if not isinstance(value, str):
        raise PydanticCustomError(
            "policy_task_type", "Input should be a built-in policy task's name or a policy task (an object)"
        )
    return _TASK_NAME.validate_python(value)


class PolicyJobCreate(_Wire):
    """A feedback policy ``π(state, goal) → controls`` to train through the emulator for a policy task
    (a built-in one of ``GET /policy-tasks`` by name, or a user's own ``PolicyTaskSpec``) and store;
    every field left out takes the task's (or the trainer's) default."""

    task: Annotated[PolicyTaskName | PolicyTaskSpec | RewardTaskSpec, WrapValidator(_task_or_definition)] = (
        Field(
            description="a built-in policy task of GET /policy-tasks, or a task of your own: goals to reach "
            "(PolicyTaskSpec) or a reward to earn (RewardTaskSpec, kind: reward)"
        )
    )
    seconds: Number | None = Field(
        None,
        ge=MIN_POLICY_SECONDS,
        description="the training budget in seconds (default: the task's; at most POLICY_MAX_SECONDS)",
    )
    refine: Flag = Field(
        True, description="fine-tune the emulator on the policy's own MuJoCo runs as it trains"
    )
    seed: Integer | None = Field(None, ge=0, le=2**31 - 1, description="the random seed (default 0)")
    batch: Integer | None = Field(
        None, ge=1, le=MAX_POLICY_BATCH, description="starts × goals rolled out per update (default 256)"
    )
    hidden: list[PolicyWidth] | None = Field(
        None,
        min_length=1,
        max_length=MAX_POLICY_LAYERS,
        description="the policy network's hidden layer widths (default: the task's)",
    )
    seeds: Integer | None = Field(
        None,
        ge=1,
        le=MAX_POLICY_SEEDS,
        description="a reward task: policies trained from this many seeds side by side, a process and a "
        "core each, the best on MuJoCo kept (default: the task's, 2 for a body on the ground; at most the "
        "worker's cores)",
    )
    idempotency_key: str | None = Field(
        None,
        min_length=1,
        max_length=128,
        pattern=r"^[\x21-\x7e]+$",
        description="the same key (and body) returns the same job instead of a new one",
    )


class HistoryPoint(BaseModel):
    """One point of a curve: the value at (or, thinned, averaged up to) an iteration."""

    iteration: int
    value: MaybeFloat = None


class PolicyJobStatus(BaseModel):
    """A policy job as it trains: the progress of its current attempt and, once it ended, how."""

    id: str
    status: JobState
    task: str
    model: str
    emulator_version: str = Field(
        description="the emulator at the task's super-step when the job was queued (the run trains "
        "through the latest at its start: the stored policy names the one it used)"
    )
    seconds: float = Field(description="the training budget")
    refine: bool
    created_at: float = Field(description="Unix time")
    started_at: float | None = None
    ended_at: float | None = None
    attempt: int = Field(0, description="runs started (a re-queued job starts again)")
    failures: int = Field(0, description="runs that crashed, raised or were abandoned by their worker")
    worker: str | None = None
    iteration: int = 0
    loss: MaybeFloat = Field(None, description="the last batch's loss")
    success_physics: float | None = Field(
        None, description="the share of the last check's MuJoCo runs that met the task (null before one)"
    )
    return_physics: float | None = Field(
        None, description="a suite task's: the last check's mean return on MuJoCo (null before one)"
    )
    mujoco_steps: int = Field(0, description="MuJoCo steps used so far (goals, checks, refinement)")
    elapsed_s: float | None = None
    loss_history: list[HistoryPoint] = Field(
        [], description=f"the loss per iteration, thinned to at most {HISTORY_POINTS} points"
    )
    error: str | None = Field(None, description="why it failed or was cancelled (or why it was re-queued)")
    result: str | None = Field(None, description="where the result is, once the job ended")


class PolicyJobSummary(BaseModel):
    """One line of GET /policy-jobs."""

    id: str
    status: JobState
    task: str
    model: str
    created_at: float
    ended_at: float | None = None
    iteration: int = 0
    success_physics: float | None = None


class PolicyJobList(BaseModel):
    """The caller's policy jobs, newest first."""

    jobs: list[PolicyJobSummary]


class PolicyOutcome(BaseModel):
    """How a policy job's run ended: the policy it stored (after a cancel or past the time limit, the
    best one so far: ``policy.metrics.stop`` says ``cancelled``), its loss and success histories."""

    status: Literal["succeeded", "failed", "cancelled"]
    reason: str | None = None
    policy: PolicyManifest | None = Field(
        None, description="the stored policy (GET /policies/{model}/{name}); null: none was stored"
    )
    iterations: int = 0
    loss_history: list[HistoryPoint] = Field(
        [], description=f"the batch loss per iteration, thinned to at most {HISTORY_POINTS} points"
    )
    success_history: list[HistoryPoint] = Field(
        [], description="the share of each check's MuJoCo runs that met the task, at its iteration"
    )
    return_history: list[HistoryPoint] = Field(
        [], description="a suite task's: the mean return of each check's MuJoCo episodes, at its iteration"
    )


class PolicyJobResult(PolicyOutcome):
    """A policy job's result (``GET /policy-jobs/{id}/result``): its run's outcome and the job's id."""

    id: str
    task: str | None = None
    model: str | None = None
    emulator_version: str | None = Field(None, description="the emulator when the job was queued")


class PolicyTaskInfo(BaseModel):
    """A built-in policy task: its model, goals and success criterion (whatever the task defines)."""

    model_config = ConfigDict(extra="allow")
    name: str
    model: str


class PolicyTaskList(BaseModel):
    tasks: list[PolicyTaskInfo]


class PolicyList(BaseModel):
    """Stored policies: the latest version of each, by model and name."""

    policies: list[PolicyManifest]


class PolicyProgressEvent(BaseModel):
    """``event: progress`` of a policy job: one training iteration of the current attempt."""

    iteration: int
    loss: MaybeFloat = None
    success_physics: float | None = None
    return_physics: float | None = Field(None, description="a suite task's: the last check's mean return")
    mujoco_steps: int = 0
    elapsed_s: float | None = None
    attempt: int | None = None
