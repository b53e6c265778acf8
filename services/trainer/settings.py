"""Trainer settings, read from the environment (``REDIS_URL=... MAX_UPLOAD_BYTES=...``); the API and
its training workers read the same variables, so one environment file configures both."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, field_validator

from neuroanimator.sim.bundle import Limits
from services.common.jobs import QueueSettings
from services.common.settings import Port

_MiB = 1 << 20


class Settings(QueueSettings):
    """Every knob of the trainer API and its workers (beside host, port, log level, API keys, CORS
    origins and the queue's: ``QueueSettings``); environment variables have the upper-case names."""

    redis_prefix: str = Field(
        "neuroanimator:trainer", min_length=1, description="prefix of the service's own Redis keys"
    )
    queue_name: str = Field(
        "neuroanimator-trainer",
        pattern=r"^[A-Za-z0-9_.:-]+$",
        description="the RQ queue (RQ's keys are rq:queue:<name>, rq:wip:<name>, ...)",
    )
    work_dir: Path | None = Field(
        None,
        description="uploads waiting for a worker, and trainings being made (default: DATA_DIR/.trainer); "
        "the API and the workers must share it",
    )
    max_body_bytes: int = Field(
        65_536, ge=1024, description="the largest request body but an upload: 413 beyond, before it is read"
    )
    max_upload_bytes: int = Field(
        32 * _MiB,
        ge=1024,
        description="the largest upload (POST /trainings): 413 beyond, refused before it is read whole",
    )
    max_extracted_bytes: int = Field(
        256 * _MiB, ge=1024, description="an archive's files, once extracted (counted while extracting)"
    )
    max_archive_files: int = Field(5000, ge=1, description="files in an archive")
    max_archive_ratio: float = Field(
        100.0, gt=1.0, description="extracted bytes per archive byte (past the first 4 MiB): beyond, a bomb"
    )
    max_file_bytes: int = Field(64 * _MiB, ge=1024, description="one XML or asset file of a model")
    max_mesh_vertices: int = Field(200_000, ge=3, description="vertices of one mesh")
    max_xml_bytes: int = Field(8 * _MiB, ge=1024, description="one .xml file of a model")
    min_timestep: float = Field(
        1e-4, gt=0.0, description="the smallest <option timestep> accepted, in seconds"
    )
    compile_seconds: float = Field(
        10.0,
        gt=0.0,
        description="CPU seconds to read and compile a model in the sandbox (and three times that of wall-clock time): refused beyond",
    )
    compile_memory_mb: int = Field(
        2048, ge=256, description="address space of the sandbox that compiles a model, in MiB: refused beyond"
    )
    max_validations: int = Field(
        2, ge=1, description="uploads checked at once by one API process (each in a sandbox process)"
    )
    validation_wait_s: float = Field(
        20.0, gt=0.0, description="how long an upload waits for a free check before a 503"
    )
    require_landlock: bool = Field(
        True,
        description="compile models only where MuJoCo is confined by Linux Landlock (5.13+); false lets "
        "a server without it accept uploads, with MuJoCo able to read the server's files",
    )
    max_queue: int = Field(20, ge=1, description="queued trainings; beyond, POST /trainings is 503")
    job_timeout_s: float = Field(
        1800.0,
        gt=0.0,
        description="time limit of one training: it is then stopped and fails, naming its phase",
    )
    job_retries: int = Field(
        1, ge=0, le=20, description="re-runs of a training whose process crashed or was abandoned"
    )
    default_examples: int = Field(
        20_000, ge=100, description="the sample budget of a training that names none (training examples)"
    )
    eval_trials: int = Field(
        8, ge=1, le=100, description="rollouts against MuJoCo of a trained emulator's evaluation"
    )
    eval_seconds: float = Field(
        10.0, gt=0.0, le=60.0, description="simulated seconds of each of those rollouts"
    )
    # tenancy
    max_trainings_per_key: int = Field(2, ge=1, description="queued and running trainings of one API key")
    max_models_per_key: int = Field(10, ge=1, description="uploaded models one API key may have stored")
    max_bytes_per_key: int = Field(
        1024 * _MiB, ge=1024, description="bytes of the models one API key has stored (versions and assets)"
    )
    # workers
    worker_nice: int = Field(
        10, ge=0, le=19, description="how much lower a training worker's CPU priority is than the services'"
    )
    worker_idle: bool = Field(
        True,
        description="training workers in Linux's idle scheduling class (SCHED_IDLE): they run on the CPU "
        "the services leave, so a training does not lengthen their latency",
    )
    port: Port = 8002

    @field_validator("work_dir")
    @classmethod
    def _absolute(cls, path: Path | None) -> Path | None:
        """Made absolute where the settings are read: a training runs in a folder of its own, where a
        relative path would name another place."""
        return None if path is None else path.expanduser().absolute()

    def work(self) -> Path:
        return self.work_dir if self.work_dir is not None else self.data_dir / ".trainer"

    def uploads(self) -> Path:
        """Uploads waiting for a worker: ``<work>/uploads/<training id>/<file>``."""
        return self.work() / "uploads"

    def staging(self) -> Path:
        """Trainings being made: ``<work>/staging/<training id>/`` (an artifact registry of one model)."""
        return self.work() / "staging"

    def limits(self) -> Limits:
        """The caps on a model's files (``bundle.Limits``)."""
        return Limits(
            max_bytes=self.max_extracted_bytes,
            max_files=self.max_archive_files,
            max_ratio=self.max_archive_ratio,
            max_file_bytes=self.max_file_bytes,
            max_mesh_vertices=self.max_mesh_vertices,
            max_xml_bytes=self.max_xml_bytes,
            min_timestep=self.min_timestep,
            compile_seconds=self.compile_seconds,
            compile_memory_bytes=self.compile_memory_mb * _MiB,
        )
