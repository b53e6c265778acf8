"""The types of a control-synthesis job: ``JobSpec`` (validated, what a worker runs) and ``Task``.

A request (``controller_schemas.JobCreate``: a task and/or a model, every other field optional)
becomes a ``JobSpec`` through ``validation.validate_job``: the task's defaults filled in, the model's
artifact pinned (version and substeps), states checked against its layout, terms typed with their
variables as indices, the optimiser's every setting present. The JSON of a ``JobSpec`` is itself a
valid request that validates to the same spec, which is what a worker does with the spec it reads
from the queue (its artifacts may differ from the API's).

A ``Task`` is a named set of defaults for a job on one model; each is defined beside its physical
model (``physics/pendulum.py``, ``lander.py``, ``truck.py``) and collected by ``tasks.py``.
Torch-free and MuJoCo-free.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from neuroanimator.goals import criteria
from neuroanimator.goals.criteria import SuccessCheck
from neuroanimator.goals.terms import Finite, Term

MAX_HORIZON = 1000
MAX_ITERATIONS = 10_000
MAX_LEARNING_RATE = 100.0
MAX_PHYSICS_ROUNDS = 20
MAX_SUBSTEPS = 100_000
MAX_MU = 1e12
MAX_STARTS = 16
MAX_GLOBAL_GENERATIONS = 50
# Defaults of a job that names a model but no task.
DEFAULT_HORIZON = 40
DEFAULT_POINTS_PER_STEP = 1.0
DEFAULT_MU_U = 1e-4
DEFAULT_MU_S = 1.0
# Every built-in task is 20 s long: 40 super-steps of the n = 50 emulator (Δt = 0.5 s), with one
# control point every two super-steps, i.e. 20 points per control (thesis 6.2).
TASK_HORIZON = 40
TASK_SUBSTEPS = 50
TASK_POINTS_PER_STEP = 0.5


class OptimizerSettings(BaseModel):
    """Gradient descent with momentum (thesis eqs. 5.5-5.6), every setting given; the defaults are
    those of a job that names no task."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    learning_rate: float = Field(1.0, gt=0, le=MAX_LEARNING_RATE, description="η")
    momentum: float = Field(0.5, ge=0, lt=1, description="α")
    max_iterations: int = Field(100, ge=1, le=MAX_ITERATIONS)
    tolerance: float = Field(1e-6, ge=0, le=1)
    stop_on_success: bool = True
    line_search: bool = True
    polish_iterations: int = Field(3, ge=0, le=MAX_ITERATIONS)
    physics_rounds: int = Field(3, ge=0, le=MAX_PHYSICS_ROUNDS)
    starts: int = Field(4, ge=1, le=MAX_STARTS, description="controllers descended at once (search.py)")
    global_generations: int = Field(
        3, ge=0, le=MAX_GLOBAL_GENERATIONS, description="cross-entropy generations before descent"
    )
    gauss_newton_iterations: int = Field(
        20,
        ge=0,
        le=MAX_ITERATIONS,
        description="Levenberg-Marquardt updates after a descent that ends short of the criterion",
    )


class JobSpec(BaseModel):
    """A validated job: everything a worker needs, nothing left to a default.

    S is the model's state size and U its number of controls. ``initial_state``, ``target_state``
    and ``state_weights`` have S values (quaternions of unit length), ``initial_controls`` U values
    within the controls' limits; ``terms`` name state variables by index, ``success`` by label.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    task: str | None = Field(description="the built-in task whose defaults were taken, if any")
    model: str
    version: str = Field(description="the artifact version, pinned at submission")
    substeps: int = Field(ge=1, le=MAX_SUBSTEPS, description="the emulator's super timestep n")
    initial_state: list[Finite]
    target_state: list[Finite]
    state_weights: list[Finite]
    horizon: int = Field(ge=1, le=MAX_HORIZON, description="super-steps")
    points_per_step: float = Field(gt=0, le=1, description="control points per super-step")
    mu_u: Finite = Field(ge=0, le=MAX_MU)
    mu_s: Finite = Field(ge=0, le=MAX_MU)
    terms: list[Term]
    initial_controls: list[Finite]
    success: list[SuccessCheck]
    optimizer: OptimizerSettings


def num_points(horizon: int, points_per_step: float) -> int:
    """Control points per control for a horizon of super-steps: round(horizon · points_per_step), >= 1."""
    return max(1, round(horizon * points_per_step))


@dataclass(frozen=True)
class Task:
    """A control-synthesis problem: a model, where it starts, where it must end, and how to judge it.

    States are in the model's layout order; ``labels`` are that layout's labels
    (``StateLayout.labels()``), which ``success`` checks and label-named ``terms`` refer to.
    ``terms`` are written as a job writes them; ``optimizer`` overrides ``OptimizerSettings``.
    """

    name: str
    model: str
    summary: str
    labels: tuple[str, ...]
    initial_state: tuple[float, ...]
    target_state: tuple[float, ...]
    state_weights: tuple[float, ...]
    success: tuple[SuccessCheck, ...]
    initial_controls: tuple[float, ...]
    mu_u: float
    mu_s: float
    terms: tuple[Mapping[str, Any], ...] = ()
    optimizer: Mapping[str, float | int | bool] = field(default_factory=dict)
    horizon: int = TASK_HORIZON
    substeps: int = TASK_SUBSTEPS
    points_per_step: float = TASK_POINTS_PER_STEP

    def __post_init__(self) -> None:
        size = len(self.labels)
        for name in ("initial_state", "target_state", "state_weights"):
            if len(getattr(self, name)) != size:
                raise ValueError(
                    f"task {self.name}: {name} must have {size} values, got {getattr(self, name)}"
                )
        problems = criteria.validate_checks([c.model_dump() for c in self.success], self.labels)
        if problems:
            where, what = problems[0]
            raise ValueError(f"task {self.name}: success{where} {what}")
        unknown = sorted(set(self.optimizer) - set(OptimizerSettings.model_fields))
        if unknown:
            raise ValueError(f"task {self.name}: unknown optimizer settings {unknown}")

    @property
    def success_text(self) -> str:
        return criteria.describe(self.success, self.target_state, self.labels)

    @property
    def description(self) -> str:
        return f"{self.summary} Success {self.success_text}."

    def control_variables(self, num_controls: int) -> int:
        return num_points(self.horizon, self.points_per_step) * num_controls

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able data, for ``GET /tasks``."""
        return {
            "name": self.name,
            "model": self.model,
            "description": self.description,
            "success_criterion": self.success_text,
            "success": [c.model_dump() for c in self.success],
            "horizon": self.horizon,
            "substeps": self.substeps,
            "points_per_step": self.points_per_step,
            "state_labels": list(self.labels),
            "initial_state": list(self.initial_state),
            "target_state": list(self.target_state),
            "state_weights": list(self.state_weights),
            "initial_controls": list(self.initial_controls),
            "mu_u": self.mu_u,
            "mu_s": self.mu_s,
            "terms": [dict(t) for t in self.terms],
            "optimizer": dict(self.optimizer),
        }
