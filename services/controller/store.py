"""The controller's jobs in Redis (``services.common.jobs.JobStore``): a delivery runs
``services.controller.execution.perform``. A control job's spec is a validated ``JobSpec``, its history
the objective per iteration, and its result names the task, model and version; a policy job's spec is
a ``PolicyJobSpec`` (``services.controller.policies``), its history the loss per iteration, and its
result names the task, model and emulator version. Both kinds share the queue, records and owners'
lists.

What is stored, and how every change of a job's state is one transaction, is told in
``services.common.jobs``; this module adds what is the controller's own.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import redis
from pydantic import BaseModel
from redis.client import Pipeline

from neuroanimator.contracts.controller import (
    EndEvent,
    HistoryPoint,
    JobOutcome,
    MaybeFloat,
    PolicyOutcome,
)
from neuroanimator.goals.spec import JobSpec
from services.common.jobs import (
    DURATION_BUCKETS,
    IdempotencyConflict,
    JobRecord,
    Keys,
    QueueFull,
    clean,
    observe,
    rq_id,
)
from services.common.jobs import JobStore as BaseStore
from services.controller.policies import POLICY, PolicyJobSpec, job_kind, thin
from services.controller.settings import Settings

__all__ = [
    "DURATION_BUCKETS",
    "ITERATION_BUCKETS",
    "PERFORM",
    "IdempotencyConflict",
    "JobStore",
    "Keys",
    "PartialRun",
    "PolicyPartial",
    "QueueFull",
    "clean",
    "rq_id",
]

PERFORM = "services.controller.execution.perform"
ITERATION_BUCKETS = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 5000.0)


class PartialRun(BaseModel):
    """The result of a job given up or cancelled while it ran (or before): what its progress knew."""

    iterations: int
    objective_history: list[MaybeFloat]
    best_objective: MaybeFloat


class PolicyPartial(BaseModel):
    """The result of a policy job given up or cancelled while it ran: what its progress knew (no
    policy was stored by this service for it)."""

    policy: None = None
    iterations: int
    loss_history: list[HistoryPoint]
    success_history: list[HistoryPoint] = []


def _best(result: JobOutcome | PartialRun) -> float | None:
    """The best objective of a run: as it said, else the least finite one of its history."""
    if result.best_objective is None and result.objective_history:
        finite = [v for v in clean(result.objective_history) if v is not None]
        return min(finite) if finite else None
    return result.best_objective


class JobStore(BaseStore):
    """The controller's jobs (one prefix and one RQ queue), for the API and for workers."""

    perform = PERFORM
    noun = "job"

    def __init__(self, conn: redis.Redis, settings: Settings) -> None:
        super().__init__(conn, settings)
        # a policy job's own limit: its budget (at most POLICY_MAX_SECONDS) plus the overhead
        self.policy_limit_s = settings.policy_max_seconds + settings.policy_overhead_s

    def time_limit_s(self) -> float:
        return max(self.settings.job_timeout_s, self.policy_limit_s)

    def summary(self, spec: str) -> dict[str, str | None]:
        if job_kind(spec) == POLICY:
            pol = PolicyJobSpec.model_validate_json(spec)
            return {"task": pol.task, "model": pol.model, "emulator_version": pol.emulator_version}
        job = JobSpec.model_validate_json(spec)
        return {"task": job.task, "model": job.model, "version": job.version}

    def end_event(
        self, rec: JobRecord, status: str, reason: str | None, result: BaseModel | None
    ) -> EndEvent:
        run = result if isinstance(result, (JobOutcome, PartialRun)) else None
        policy = result if isinstance(result, (PolicyOutcome, PolicyPartial)) else None
        iterations = run.iterations if run is not None else policy.iterations if policy is not None else None
        return EndEvent.model_validate(
            {
                "status": status,
                "reason": reason,
                "iterations": iterations,
                "best_objective": None if run is None else _best(run),
            }
        )

    def observe_end(self, pipe: Pipeline, result: BaseModel | None) -> None:
        iterations = getattr(result, "iterations", None)
        if isinstance(iterations, int):
            observe(pipe, self.keys.stats, "iterations", float(iterations), ITERATION_BUCKETS)

    def partial(self, progress: dict[str, str], history: list[Any]) -> PartialRun | PolicyPartial:
        iterations = json.loads(progress.get("iteration", "0"))
        if "mujoco_steps" in progress:  # a policy job's progress (a control job's has an objective)
            return PolicyPartial(iterations=iterations, loss_history=thin(history))
        return PartialRun(
            iterations=iterations,
            objective_history=history,
            best_objective=json.loads(progress.get("best_objective", "null")),
        )

    def submit(self, spec: JobSpec, owner: str, idempotency_key: str | None = None) -> tuple[str, str, bool]:
        """Queue a validated job; returns (id, status, created). A repeated idempotency key returns its
        job; raises ``QueueFull`` or ``IdempotencyConflict``."""
        spec_json = json.dumps(spec.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        return self.submit_spec(spec_json, owner, idempotency_key, log_extra={"task": spec.task})

    def submit_policy(
        self, spec: PolicyJobSpec, owner: str, idempotency_key: str | None = None
    ) -> tuple[str, str, bool]:
        """Queue a checked policy job, as ``submit`` does a control job."""
        spec_json = json.dumps(spec.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        return self.submit_spec(spec_json, owner, idempotency_key, log_extra={"policy_task": spec.task})

    def progress(self, job_id: str, attempt: int, p: Mapping[str, object]) -> None:
        """Record one iteration (``run_job``'s report, a JSON object of its own): the progress hash, the
        objective history and a ``progress`` event."""
        self.record_progress(job_id, attempt, p, [p.get("objective")])

    def policy_progress(self, job_id: str, attempt: int, p: Mapping[str, object]) -> None:
        """Record one iteration of a policy's training (its ``PolicyProgress``): the progress hash, the
        loss history and a ``progress`` event."""
        self.record_progress(job_id, attempt, p, [p.get("loss")])

    def finish(self, job_id: str, delivery: int, result: JobOutcome | PolicyOutcome) -> bool:
        """End the job with its run's outcome; False if it had already ended or was superseded."""
        return self.end(job_id, delivery, result.status, result.reason, result)
