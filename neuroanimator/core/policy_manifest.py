"""``PolicyManifest``: what a stored policy is, for whoever serves or lists it (torch-free).

A policy version folder holds ``policy.onnx`` (``π(state (B,S), goal (B,G), time_left (B,1)) →
controls (B,U)``; ``time_left`` only for a timed task), ``policy.pt`` (the torch network's weights and
shape) and ``policy.json`` (this manifest). The policy was trained through one emulator version
(``emulator_version``, at ``substeps``): a session drives that emulator with it, and a session of
another version is refused.

The goal envelope (``goal_low``/``goal_high``) is the range of the goals it was trained for: a goal
outside it is accepted but flagged, as a state outside the emulator's training range is.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

POLICY_FORMAT = 1


class PolicyFall(BaseModel):
    """A fall in one of the final episodes on MuJoCo: which episode, when, and the state it lay in."""

    model_config = ConfigDict(extra="forbid")

    episode: int
    time_s: float = Field(description="seconds into the episode")
    state: list[float] = Field(description="the emulator state (S,) it fell into")
    up_again_s: float | None = Field(
        None,
        description="seconds into the episode from which it was up again for good after the fall "
        "(never down again); null: it lay at the end",
    )


class PolicyMetrics(BaseModel):
    """How the policy did on held-out starts and goals when it was trained."""

    model_config = ConfigDict(extra="forbid")

    success_physics: float | None = Field(
        None, description="share of held-out runs meeting the task on MuJoCo"
    )
    success_emulator: float | None = Field(None, description="the same runs on the emulator")
    return_physics: float | None = None
    return_emulator: float | None = None
    evaluate_runs: int = 0
    mujoco_steps: int = Field(0, description="MuJoCo steps the training used: goals, checks, refinement")
    iterations: int = 0
    refinements: int = Field(0, description="fine-tunings of its emulator copy on the policy's MuJoCo runs")
    wall_s: float = 0.0
    stop: str = "budget"
    outside_envelope: float | None = Field(
        None, description="share of emulated states outside the emulator's training envelope (reward tasks)"
    )
    root_drift_m: float | None = Field(
        None,
        description="metres between the root body on the emulator and on MuJoCo 1 s into the final "
        "episodes, each under the policy (reward tasks)",
    )
    falls: list[PolicyFall] = Field(
        default_factory=list, description="the final episodes on MuJoCo that fell (a task with a fall)"
    )
    seed_returns: list[float] = Field(
        default_factory=list,
        description="each seed's return on the same final MuJoCo episodes, when several were trained "
        "side by side and the best kept (reward tasks)",
    )


class PolicyManifest(BaseModel):
    """A stored policy (module doc). Shapes: S state, G goal variables, U controls."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: int = POLICY_FORMAT
    name: str = Field(description="the policy's name: its task's")
    version: str
    created: str
    model: str
    emulator_version: str = Field(description="the emulator version it was trained through and drives")
    substeps: int = Field(ge=1)
    super_timestep: float = Field(gt=0)
    state_size: int
    state_labels: list[str]
    control_names: list[str]
    goal_variables: list[str]
    goal_low: list[float]
    goal_high: list[float]
    goal_default: list[float]
    timed: bool = False
    goal_period_steps: int = Field(ge=1, description="super-steps a goal is held in training")
    check_steps: int = Field(ge=1, description="super-steps after a goal is set at which it is judged")
    description: str = ""
    task: dict[str, Any] = Field(default_factory=dict)
    metrics: PolicyMetrics = Field(default_factory=PolicyMetrics)
    starts: list[list[float]] = Field(
        default_factory=list,
        description="(K, S) states its task's runs start from (the runner's: a running stride); a "
        "session driven by it without a state given starts at one of them, drawn by the seed (none: "
        "the model's typical starts)",
    )

    @model_validator(mode="after")
    def _starts_are_states(self) -> PolicyManifest:
        bad = [i for i, s in enumerate(self.starts) if len(s) != self.state_size]
        if bad:
            raise ValueError(f"starts {bad} do not have the state's {self.state_size} values")
        return self

    @property
    def goal_size(self) -> int:
        return len(self.goal_variables)
