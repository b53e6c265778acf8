"""The controller's jobs in Redis (``services.common.jobs.JobStore``): a delivery runs
``services.controller.execution.perform``; a job's spec is a validated ``JobSpec``, its history the
objective per iteration, and its result names the task, model and version.

What is stored, and how every change of a job's state is one transaction, is told in
``services.common.jobs``; this module adds what is the controller's own.
"""

from __future__ import annotations

import json
from typing import Any

from redis.client import Pipeline

from neuroanimator.contracts.controller import JobOutcome
from neuroanimator.goals.spec import JobSpec
from services.common.jobs import DURATION_BUCKETS, IdempotencyConflict, Keys, QueueFull, clean, observe, rq_id
from services.common.jobs import JobStore as BaseStore

__all__ = [
    "DURATION_BUCKETS",
    "ITERATION_BUCKETS",
    "PERFORM",
    "IdempotencyConflict",
    "JobStore",
    "Keys",
    "QueueFull",
    "clean",
    "rq_id",
]

PERFORM = "services.controller.execution.perform"
ITERATION_BUCKETS = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 5000.0)


class JobStore(BaseStore):
    """The controller's jobs (one prefix and one RQ queue), for the API and for workers."""

    perform = PERFORM
    noun = "job"

    def summary(self, spec: dict[str, Any]) -> dict[str, Any]:
        return {"task": spec.get("task"), "model": spec.get("model"), "version": spec.get("version")}

    def end_event(self, body: dict[str, Any]) -> dict[str, Any]:
        best = body.get("best_objective")
        if best is None and body.get("objective_history"):
            finite = [v for v in clean(body["objective_history"]) if v is not None]
            best = min(finite) if finite else None
        return {
            "status": body["status"],
            "reason": body["reason"],
            "iterations": body.get("iterations"),
            "best_objective": best,
        }

    def observe_end(self, pipe: Pipeline, body: dict[str, Any]) -> None:
        if isinstance(body.get("iterations"), int):
            observe(pipe, self.keys.stats, "iterations", float(body["iterations"]), ITERATION_BUCKETS)

    def partial(self, progress: dict[str, str], history: list[Any]) -> dict[str, Any]:
        return {
            "iterations": json.loads(progress.get("iteration", "0")),
            "objective_history": history,
            "best_objective": json.loads(progress.get("best_objective", "null")),
        }

    def submit(self, spec: JobSpec, owner: str, idempotency_key: str | None = None) -> tuple[str, str, bool]:
        """Queue a validated job; returns (id, status, created). A repeated idempotency key returns its
        job; raises ``QueueFull`` or ``IdempotencyConflict``."""
        spec_json = json.dumps(spec.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        return self.submit_spec(spec_json, owner, idempotency_key, log_extra={"task": spec.task})

    def progress(self, job_id: str, attempt: int, p: dict[str, Any]) -> None:
        """Record one iteration: the progress hash, the objective history and a ``progress`` event."""
        self.record_progress(job_id, attempt, p, [p.get("objective")])

    def finish(self, job_id: str, delivery: int, result: JobOutcome) -> bool:
        """End the job with ``run_job``'s outcome; False if it had already ended or was superseded."""
        return self.end(job_id, delivery, result.status, result.reason, result.model_dump())
