"""What a training is made of on its way through the queue: its spec as queued (``TrainingSpec``), what
its process is handed (``ChildSpec``) and reports (``TrainingProgress``, ``TrainedEmulator``), and the
``end`` event of its stream (``TrainingEnd``). The stored result is the contract's ``TrainingResult``.

Only pydantic and the contracts here: the training's process (``services.trainer.run``) imports this
before anything of ``neuroanimator`` that would load its progress bars.
"""

from __future__ import annotations

import json

from pydantic import BaseModel, Field, field_serializer

from neuroanimator.contracts.trainer import SuperStep, TrainingPhase, TrainingResult
from neuroanimator.core.results import PhysicalErrors


class TrainingSpec(BaseModel):
    """A queued training (the ``spec`` of its record, JSON with sorted keys): the checked upload's name
    and where it is (``source``, under the uploads folder), and the options, the sample budget filled in,
    the operating spec found (the form's, else the archive's ``operating.json``) and the keyframe."""

    model: str
    source: str
    entry: str | None = None
    super_step: SuperStep = "auto"
    examples: int
    epochs: int | None = None
    hidden: str | None = None
    rollout_steps: int | None = None
    force: bool = False
    operating_spec: str | None = Field(
        None, description="the operating spec to train with (canonical JSON: the form's or the archive's)"
    )
    keyframe: str | None = None

    def to_json(self) -> str:
        """The spec as the record keeps it."""
        return json.dumps(self.model_dump(), sort_keys=True)


class ChildSpec(TrainingSpec):
    """What the training's process reads on stdin: the spec (``source`` an absolute path), where to
    write the emulator (``staging``) and the service's caps and evaluation settings."""

    staging: str
    limits: dict[str, int | float] = Field(description="``neuroanimator.sim.bundle.Limits``'s fields")
    time_limit_s: float
    eval_trials: int
    eval_seconds: float


class TrainingProgress(BaseModel):
    """A training's last report (the progress hash; its ``progress`` events also carry ``losses``)."""

    phase: TrainingPhase = "validating"
    percent: float = 0.0
    detail: str | None = None
    elapsed_s: float | None = None
    eta_s: float | None = None


class TrainedEmulator(BaseModel):
    """What the training's process made, in its staging registry: a ``TrainingResult`` before it is
    exported (the version is the staging one, and there is no artifact yet)."""

    model: str
    version: str
    substeps: int
    one_step_rel_error: float | None
    linear_baseline_rel_error: float | None
    physical_errors: PhysicalErrors | None = None
    weights: int | None = None
    examples: int | None = None
    phase_seconds: dict[str, float] = Field(default_factory=dict)
    notes: list[str] = Field(default_factory=list)


def stored_order(result: TrainingResult) -> dict[str, object]:
    """The result's fields in the order results are stored and sent in: the artifact last, after what
    the training's process reported."""
    fields = result.model_dump()
    artifact = fields.pop("artifact")
    return {**fields, "artifact": artifact}


def _absent(value: object) -> bool:
    return value is None


class TrainingEnd(BaseModel):
    """The data of a training's ``end`` event: how it ended and, when it succeeded, what it made."""

    status: str
    phase: str
    reason: str | None
    model: str | None
    result: TrainingResult | None = Field(None, exclude_if=_absent)

    @field_serializer("result")
    def _result(self, result: TrainingResult | None) -> dict[str, object] | None:
        return None if result is None else stored_order(result)


LossPair = list[float | None]
"""A point of the loss curve: [epoch, validation loss]."""


class ChildMessage(BaseModel):
    """One line the training's process writes: progress (``phase``, ``percent``, ``detail`` and the
    loss curve's new points), else its ``result``, else the ``error`` that ended it."""

    phase: TrainingPhase | None = None
    percent: float = 0.0
    detail: str = ""
    losses: list[LossPair] = Field(default_factory=list)
    result: TrainedEmulator | None = None
    error: str | None = None
