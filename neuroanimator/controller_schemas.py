"""The controller service's wire contract: pydantic v2 models of its requests, replies and events.

A job is a controller-synthesis problem (thesis ch. 5): a built-in ``task`` (``GET /tasks``) with
optional overrides, or a custom objective over a ``model``. The service checks the request's types
here (finite JSON numbers, positive sizes) and the job against the model and task with
``neuroanimator.control.validate_job``; both answer 422 naming the field.

Numbers that are not finite (an objective that diverged to NaN) travel as ``null``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from neuroanimator.schemas import Number, Vector

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
"""queued (waiting for a worker, also after a re-queue) → running → succeeded | failed | cancelled."""
FINAL_STATES: tuple[str, ...] = ("succeeded", "failed", "cancelled")
MaybeFloat = float | None
"""A number that is ``null`` where it was not finite (NaN, ±inf)."""


class _Wire(BaseModel):
    model_config = ConfigDict(extra="forbid")


# ---------------------------------------------------------------- requests
class OptimizerSpec(_Wire):
    """Gradient descent with momentum (thesis eq. 5.4): ``u ← u − η∇J + α·δu_prev``; it stops after
    ``max_iterations`` or when the objective improves by less than ``tolerance``."""

    learning_rate: Number | None = Field(None, gt=0, description="η")
    momentum: Number | None = Field(None, ge=0, lt=1, description="α")
    max_iterations: int | None = Field(None, ge=1, description="iteration cap")
    tolerance: Number | None = Field(None, ge=0, description="stop when the objective changes less")
    stop_on_success: bool | None = Field(None, description="stop once the success criterion holds")
    line_search: bool | None = Field(
        None, description="pick η and α afresh each iteration from a batch of candidates (off: fixed η, α)"
    )
    polish_iterations: int | None = Field(
        None, ge=0, le=10_000, description="updates after the success criterion first holds"
    )
    physics_rounds: int | None = Field(
        None, ge=0, le=20, description="rounds of re-optimising on an emulator corrected by the MuJoCo replay"
    )


class ObjectiveTerm(BaseModel):
    """One term of a custom objective: ``term`` names it, its other keys are the term's parameters."""

    model_config = ConfigDict(extra="allow")
    term: str = Field(min_length=1, max_length=64)


class JobCreate(_Wire):
    """A controller-synthesis job: a built-in ``task`` and/or a ``model`` with the objective's pieces;
    every field left out takes the task's (or the default) value."""

    task: str | None = Field(None, max_length=64, description="a built-in task of GET /tasks")
    model: str | None = Field(None, max_length=128, description="an emulator in the artifact registry")
    version: str | None = Field(None, max_length=128, description="an artifact version (default: latest)")
    substeps: int | None = Field(None, ge=1, description="the emulator's super timestep n")
    initial_state: Vector | None = None
    target_state: Vector | None = Field(None, description="s_d of the final-state term")
    state_weights: Vector | None = Field(None, description="weight of each state variable in that term")
    horizon: int | None = Field(None, ge=1, description="length of the controller, in super-steps")
    points_per_step: Number | None = Field(None, gt=0, description="control points per super-step")
    initial_controls: Vector | None = Field(None, description="the controls the optimisation starts from")
    mu_u: Number | None = Field(None, ge=0, description="μ_u, weight of the control effort")
    mu_s: Number | None = Field(None, ge=0, description="μ_s, weight of the final-state error")
    terms: list[ObjectiveTerm] | None = Field(None, max_length=32, description="a custom objective")
    success: list[dict[str, Any]] | None = Field(
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
        """The job's specification (what ``validate_job`` takes): the set fields, less the key."""
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


class JobResult(BaseModel):
    """What ``run_job`` returned (a job that crashed has only ``status``, ``reason`` and what was known):
    the controller (control points and the sampled ``controls`` at ``times``), the trajectory it gives
    on the emulator and on the physics (MuJoCo), and their errors against the target."""

    model_config = ConfigDict(extra="allow")
    id: str
    status: Literal["succeeded", "failed", "cancelled"]
    reason: str | None = None
    task: str | None = None
    model: str | None = None
    version: str | None = None
    substeps: int | None = None
    iterations: int | None = None
    iterations_to_success: int | None = None
    objective_history: list[MaybeFloat] = []
    control_points: list[Any] | None = None
    control_spacing_s: float | None = None
    times: list[float] | None = None
    controls: list[Any] | None = None
    emulated: Trajectory | None = None
    physical: Trajectory | None = None
    final_error_emulator: MaybeFloat = None
    final_error_physics: MaybeFloat = None
    success_emulator: bool | None = None
    success_physics: bool | None = None
    target_state: list[MaybeFloat] | None = None
    initial_state: list[MaybeFloat] | None = None
    wall_s: float | None = None
    state_labels: list[str] | None = None


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
