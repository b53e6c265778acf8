"""The trainer service's wire contract: pydantic v2 models of its requests, replies and events.

A training turns an uploaded MuJoCo model (an MJCF file, or a .zip / .tar.gz of a model folder) into
an emulator in the artifact registry: ``POST /trainings`` takes the file and ``TrainingOptions`` as a
multipart form, validates the model at once (a 4xx naming the problem) and queues the training; a
worker then goes through the phases

    queued → validating → sampling → training → evaluating → exporting → done
                                                     (or failed, cancelled, at any point)

reporting its percent, an estimate of the time left and the validation loss of each epoch (the loss
curve). ``TrainingResult`` is what a finished training made: the artifact's model and version, its
one-step error against the linear baseline and its rollout errors in physical units.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from neuroanimator.core.results import PhysicalErrors

MAX_EXAMPLES = 1_000_000
"""The largest sample budget (training examples) one training may ask for."""
MAX_EPOCHS = 5000
MAX_SUPER_STEP = 1000
MAX_WIDTH = 1024
"""The widest hidden layer one may ask for (at most four layers)."""
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]*$"

TrainingState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
"""The job's state: queued (waiting for a worker, also after a re-queue) → running → succeeded | failed
| cancelled."""
TrainingPhase = Literal[
    "queued", "validating", "sampling", "training", "evaluating", "exporting", "done", "failed", "cancelled"
]
"""Where a training is: its state while queued or ended, else the running phase."""
PHASES: tuple[str, ...] = ("validating", "sampling", "training", "evaluating", "exporting")
"""The running phases, in order."""
SuperStep = int | Literal["auto"]


class _Wire(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TrainingOptions(_Wire):
    """The form fields of ``POST /trainings`` beside the uploaded ``file``; every one may be left out."""

    name: str | None = Field(
        None,
        max_length=64,
        pattern=NAME_PATTERN,
        description="the model's name in the registry (default: the MJCF's model attribute); a name the "
        "caller already uses adds a version, another's is refused",
    )
    entry: str | None = Field(
        None,
        min_length=1,
        max_length=256,
        description="in an archive: the MJCF file to train (default: the only one)",
    )
    super_step: SuperStep = Field(
        "auto",
        description="physical steps per emulator step (n), or auto: 50 for a smooth model, shorter when "
        "contacts or limits need it",
    )
    examples: int | None = Field(
        None,
        ge=100,
        le=MAX_EXAMPLES,
        description="the sample budget: training examples (default: the service's)",
    )
    epochs: int | None = Field(None, ge=1, le=MAX_EPOCHS, description="most epochs of the one-step phase")
    hidden: str | None = Field(
        None,
        pattern=r"^\d{1,4}(,\d{1,4}){0,3}$",
        description="hidden layer widths, e.g. 64,64 (default: the trainer's)",
    )
    rollout_steps: int | None = Field(
        None, ge=0, le=64, description="super-steps of the rollout phase (0: off; default: the trainer's)"
    )
    force: bool = Field(False, description="keep the emulator even when it misses the acceptance bar")
    operating_spec: str | None = Field(
        None,
        max_length=16_000,
        description="the model's typical motion, an operating spec as JSON text (docs/operating-spec.md: the "
        "keyframe, the controls' centres and spreads, how runs start); default: an operating.json at the "
        "top of an uploaded archive, else the operating point found in the model (its keyframes, else the "
        "controls that hold it still)",
    )
    keyframe: str | None = Field(
        None,
        min_length=1,
        max_length=256,
        description="train around this keyframe of the model only (default: every keyframe it has)",
    )

    @field_validator("super_step", mode="before")
    @classmethod
    def _super_step(cls, value: object) -> object:
        if isinstance(value, str) and value.strip().isdigit():
            return int(value)
        return value

    @field_validator("super_step")
    @classmethod
    def _super_step_range(cls, value: SuperStep) -> SuperStep:
        if isinstance(value, int) and not 1 <= value <= MAX_SUPER_STEP:
            raise ValueError(f"a super-step is an integer in [1, {MAX_SUPER_STEP}] or auto")
        return value

    @field_validator("hidden")
    @classmethod
    def _widths(cls, value: str | None) -> str | None:
        if value is not None and not all(1 <= int(w) <= MAX_WIDTH for w in value.split(",")):
            raise ValueError(f"each width is an integer in [1, {MAX_WIDTH}]")
        return value


class TrainingUpload(TrainingOptions):
    """The multipart form of ``POST /trainings`` (documentation: ``file`` is the upload)."""

    file: bytes = Field(
        json_schema_extra={"format": "binary"},
        description="the model: an MJCF .xml file, or a .zip / .tar.gz / .tgz of its folder",
    )


class TrainingAccepted(BaseModel):
    """A training on the queue, its model checked."""

    id: str
    status: TrainingState
    phase: TrainingPhase
    model: str = Field(description="the name the emulator will have in the registry")
    new_version: bool = Field(description="true when the caller's model of that name gets a new version")
    message: str


class TrainingResult(BaseModel):
    """What a finished training made."""

    model: str
    version: str
    artifact: str = Field(description="<model>/<version> in the artifact registry")
    substeps: int = Field(description="the super-step n the emulator was trained at")
    one_step_rel_error: float | None = Field(description="held-out one-step error (1 − R²)")
    linear_baseline_rel_error: float | None = Field(description="the same of a least-squares linear map")
    physical_errors: PhysicalErrors | None = Field(
        None, description="rollout errors against MuJoCo in metres, degrees and radians"
    )
    weights: int | None = None
    examples: int | None = None
    phase_seconds: dict[str, float] = Field(default_factory=dict, description="seconds spent in each phase")
    notes: list[str] = Field(
        default_factory=list, description="what the trainer did other than asked, and why"
    )


class LossPoint(BaseModel):
    """The validation loss (mean squared error of normalised outputs) after one epoch."""

    epoch: int
    loss: float | None


class TrainingStatus(BaseModel):
    """A training as it runs: its phase, progress and loss curve, and once ended, how."""

    id: str
    status: TrainingState
    phase: TrainingPhase
    model: str
    super_step: SuperStep
    examples: int
    percent: float = Field(ge=0.0, le=100.0, description="an estimate, over the whole training")
    eta_s: float | None = Field(None, description="an estimate of the seconds left")
    elapsed_s: float | None = Field(None, description="seconds since the current attempt started")
    detail: str | None = Field(None, description="what the phase is doing, in words")
    loss_curve: list[LossPoint] = Field(default_factory=list)
    created_at: float
    started_at: float | None = None
    ended_at: float | None = None
    attempt: int = 0
    failures: int = 0
    worker: str | None = None
    error: str | None = None
    result: TrainingResult | None = None


class TrainingSummary(BaseModel):
    id: str
    status: TrainingState
    phase: TrainingPhase
    model: str
    percent: float
    created_at: float
    ended_at: float | None = None


class TrainingList(BaseModel):
    trainings: list[TrainingSummary]


class StoredModel(BaseModel):
    """An uploaded model in the registry."""

    model: str
    owner: str = Field(description="the key id that uploaded it (public: uploaded while keys were off)")
    published: bool = Field(description="true once an operator made it everybody's")
    uploaded: str = Field(description="when its first version was exported (UTC)")
    versions: list[str]
    size_bytes: int = Field(description="every version and its assets, as stored")


class Usage(BaseModel):
    """What a key uses against its limits (MAX_TRAININGS_PER_KEY, MAX_MODELS_PER_KEY, MAX_BYTES_PER_KEY)."""

    trainings: int
    max_trainings: int
    models: int
    max_models: int
    bytes: int
    max_bytes: int


class StoredModelList(BaseModel):
    models: list[StoredModel]
    usage: Annotated[Usage, Field(description="the caller's own use of its limits")]
