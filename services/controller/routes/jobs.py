"""Jobs: ``POST /jobs``, ``GET /jobs``, ``GET /jobs/{id}``, ``GET /jobs/{id}/result``, ``DELETE /jobs/{id}``.

A job belongs to the API key that made it: any other key gets 404 for it, as if it did not exist.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response

from neuroanimator.artifacts import registry
from neuroanimator.catalog.tasks import TASKS
from neuroanimator.contracts.controller import (
    FINAL_STATES,
    BestSoFar,
    JobAccepted,
    JobCreate,
    JobList,
    JobResult,
    JobStatus,
    JobSummary,
)
from neuroanimator.contracts.emulator import ErrorBody
from neuroanimator.control.validation import validate_job
from neuroanimator.goals.errors import JobSpecError
from neuroanimator.goals.spec import JobSpec
from services.common import tenancy
from services.common.auth import CALLER, OwnerDep
from services.common.errors import ApiError
from services.common.jobs import JobRecord
from services.common.openapi import Responses
from services.common.queue_app import queue_full
from services.controller.deps import SettingsDep, StoreDep
from services.controller.metrics import Metrics
from services.controller.policies import POLICY, JobKind, job_kind
from services.controller.store import IdempotencyConflict, JobStore, QueueFull

router = APIRouter(tags=["jobs"])
_ERRORS: Responses = {
    404: {"model": ErrorBody},
    409: {"model": ErrorBody},
    422: {"model": ErrorBody},
    503: {"model": ErrorBody},
}
# progress keys that are not part of "the best controller so far"
_PROGRESS_KEYS = {
    "iteration",
    "objective",
    "best_objective",
    "best_iteration",
    "success_emulator",
    "elapsed_s",
    "attempt",
    "phase",
}


def _lookup(spec: Mapping[str, object], field: str) -> Any:
    """The value at a dotted field path (``optimizer.learning_rate``, ``terms[1].variable``), or None."""
    value: Any = spec
    for name, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", field):
        try:
            value = value[int(index)] if index else value[name]
        except (KeyError, IndexError, TypeError):
            return None
    return value


def number(value: Any) -> float | None:
    """A progress value as a float; None for anything that is not a number (a missing loss, a flag)."""
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _best_so_far(prog: Mapping[str, Any]) -> BestSoFar | None:
    """The best controller so far from the progress of ``run_job`` (its extra keys describe it)."""
    extra = {k: v for k, v in prog.items() if k not in _PROGRESS_KEYS}
    if prog.get("best_objective") is None and not extra:
        return None
    return BestSoFar(
        iteration=prog.get("best_iteration"), objective=number(prog.get("best_objective")), **extra
    )


def job_status(rec: JobRecord) -> JobStatus:
    """The wire view of a record from ``JobStore.record``."""
    spec = JobSpec.model_validate_json(rec.spec)
    prog = rec.progress
    return JobStatus(
        id=rec.id,
        status=rec.status,
        task=spec.task,
        model=spec.model,
        version=spec.version,
        created_at=rec.created_at,
        started_at=rec.started_at or None,
        ended_at=rec.ended_at or None,
        attempt=rec.attempt,
        failures=rec.failures,
        worker=rec.worker or None,
        iteration=int(prog.get("iteration") or 0),
        max_iterations=spec.optimizer.max_iterations,
        objective=number(prog.get("objective")),
        best_objective=number(prog.get("best_objective")),
        success_emulator=prog.get("success_emulator"),
        elapsed_s=number(prog.get("elapsed_s")),
        objective_history=[number(v) for v in rec.history],
        best=_best_so_far(prog),
        error=rec.error or None,
        result=f"/jobs/{rec.id}/result" if rec.status in FINAL_STATES else None,
    )


def _summary(rec: JobRecord) -> JobSummary:
    s = job_status(rec)
    return JobSummary(
        id=s.id,
        status=s.status,
        task=s.task,
        model=s.model,
        created_at=s.created_at,
        ended_at=s.ended_at,
        iteration=s.iteration,
        best_objective=s.best_objective,
    )


def hidden(req: JobCreate, root: registry.Root) -> None:
    """A ``JobSpecError`` on ``model`` when the job names a model the caller does not see (another key's
    upload, not published): as for a model that does not exist, listing only the models it sees."""
    model = req.model or (TASKS[req.task].model if req.task in TASKS else None)
    if model is None or CALLER.get() is None:  # keys off: every model is everybody's
        return
    seen = tenancy.visible_models(root)
    if model not in seen:
        raise JobSpecError("model", f"unknown model {model!r}; trained models are {seen}", seen)


def owned(store: JobStore, job_id: str, owner: str, kind: JobKind = "control") -> JobRecord:
    """The caller's job of this kind, else 404 (also for another key's job); a job of the other kind
    is 404 naming where it is."""
    rec = store.record(job_id, owner)
    if rec is None:
        raise ApiError(404, "not_found", f"no job {job_id!r} (it may have expired)", field="id", got=job_id)
    found = job_kind(rec.spec)
    if found != kind:
        where = f"/policy-jobs/{job_id}" if found == POLICY else f"/jobs/{job_id}"
        raise ApiError(
            404, "not_found", f"job {job_id} is a {found} job: see {where}", field="id", got=job_id
        )
    return rec


def jobs_of_kind(store: JobStore, owner: str, kind: JobKind, limit: int, most: int) -> list[JobRecord]:
    """The owner's newest ``limit`` jobs of a kind, among their newest ``most`` of both kinds."""
    return [r for r in store.jobs_of(owner, most) if job_kind(r.spec) == kind][:limit]


@router.post("/jobs", response_model=JobAccepted, status_code=202, responses=_ERRORS)
def create_job(
    req: JobCreate,
    request: Request,
    response: Response,
    store: StoreDep,
    owner: OwnerDep,
    settings: SettingsDep,
) -> JobAccepted:
    """Queue a controller-synthesis job; the same ``idempotency_key`` returns the same job."""
    metrics: Metrics = request.app.state.metrics
    try:
        hidden(req, settings.roots())
        spec = validate_job(req, settings.roots())
    except JobSpecError as exc:
        metrics.rejected.labels("invalid").inc()
        got = _lookup(req.spec(), exc.field)
        expected = exc.expected if exc.expected is not None else exc.message
        raise ApiError(422, "invalid_job", str(exc), field=exc.field, expected=expected, got=got) from exc
    try:
        job_id, status, created = store.submit(spec, owner, req.idempotency_key)
    except QueueFull as exc:
        metrics.rejected.labels("queue_full").inc()
        raise queue_full(exc) from exc
    except IdempotencyConflict as exc:
        metrics.rejected.labels("conflict").inc()
        raise ApiError(409, "idempotency_conflict", str(exc), field="idempotency_key") from exc
    if created:
        metrics.submitted.inc()
    response.headers["Location"] = f"/jobs/{job_id}"
    return JobAccepted(id=job_id, status=status, created=created)


@router.get("/jobs", response_model=JobList, responses=_ERRORS)
def list_jobs(
    store: StoreDep,
    owner: OwnerDep,
    settings: SettingsDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="most jobs to list")] = 50,
) -> JobList:
    """The caller's recent control jobs, newest first (policy jobs: ``GET /policy-jobs``)."""
    recs = jobs_of_kind(store, owner, "control", min(limit, settings.max_list), settings.max_list)
    return JobList(jobs=[_summary(r) for r in recs])


@router.get("/jobs/{job_id}", response_model=JobStatus, responses=_ERRORS)
def get_job(job_id: str, store: StoreDep, owner: OwnerDep) -> JobStatus:
    """A job's status, progress (objective history, best controller so far) and error."""
    return job_status(owned(store, job_id, owner))


@router.get("/jobs/{job_id}/result", response_model=JobResult, responses=_ERRORS)
def get_result(job_id: str, store: StoreDep, owner: OwnerDep) -> JobResult:
    """The finished job's result: the controller, its trajectories and errors (409 until it ends)."""
    rec = owned(store, job_id, owner)
    if rec.status not in FINAL_STATES:
        raise ApiError(
            409,
            "not_finished",
            f"job {job_id} is {rec.status}; its result is here once it ends (watch /jobs/{job_id}/events)",
            field="status",
            expected=list(FINAL_STATES),
            got=rec.status,
        )
    result = store.result(job_id)
    if result is None:
        raise ApiError(404, "not_found", f"the result of job {job_id!r} has expired", field="id", got=job_id)
    return JobResult.model_validate_json(result)


@router.delete("/jobs/{job_id}", response_model=JobStatus, status_code=202, responses=_ERRORS)
def cancel_job(job_id: str, store: StoreDep, owner: OwnerDep) -> JobStatus:
    """Cancel a queued job (it ends now) or a running one (it stops at its next iteration)."""
    rec = owned(store, job_id, owner)
    if rec.status in FINAL_STATES:
        raise ApiError(
            409,
            "already_ended",
            f"job {job_id} already ended: {rec.status}",
            field="status",
            expected=["queued", "running"],
            got=rec.status,
        )
    store.cancel(job_id)
    return job_status(owned(store, job_id, owner))
