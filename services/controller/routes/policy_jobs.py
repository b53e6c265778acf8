"""Policy jobs: ``GET /policy-jobs``, ``GET /policy-jobs/{id}``, ``GET /policy-jobs/{id}/events`` (SSE),
``GET /policy-jobs/{id}/result``, ``DELETE /policy-jobs/{id}`` (``POST /policies`` queues one).

They share the controller's queue, workers and records with control jobs and behave as they do (see
``jobs`` and ``events``): a job belongs to the API key that made it, its events are ``status``,
``progress`` (one per training iteration: ``PolicyProgressEvent``) and one last ``end``, and its result
is there once it ends. A control job's id here (or a policy job's under ``/jobs``) is 404 naming where
it is.
"""

from __future__ import annotations

from typing import Annotated

import redis.asyncio as aioredis
from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from neuroanimator.contracts.controller import (
    FINAL_STATES,
    PolicyJobList,
    PolicyJobResult,
    PolicyJobStatus,
    PolicyJobSummary,
)
from neuroanimator.contracts.emulator import ErrorBody
from services.common import job_events as sse
from services.common.auth import OwnerDep
from services.common.errors import ApiError
from services.common.job_events import SSE_RESPONSES
from services.common.jobs import JobRecord
from services.common.openapi import Responses
from services.controller.deps import SettingsDep, StoreDep
from services.controller.policies import POLICY, PolicyJobSpec, thin
from services.controller.routes.jobs import jobs_of_kind, number, owned
from services.controller.store import JobStore

router = APIRouter(tags=["policy jobs"])
_ERRORS: Responses = {404: {"model": ErrorBody}, 409: {"model": ErrorBody}, 503: {"model": ErrorBody}}


def policy_job_status(rec: JobRecord) -> PolicyJobStatus:
    """The wire view of a policy job's record."""
    spec = PolicyJobSpec.model_validate_json(rec.spec)
    prog = rec.progress
    return PolicyJobStatus(
        id=rec.id,
        status=rec.status,
        task=spec.task,
        model=spec.model,
        emulator_version=spec.emulator_version,
        seconds=spec.seconds,
        refine=spec.refine,
        created_at=rec.created_at,
        started_at=rec.started_at or None,
        ended_at=rec.ended_at or None,
        attempt=rec.attempt,
        failures=rec.failures,
        worker=rec.worker or None,
        iteration=int(prog.get("iteration") or 0),
        loss=number(prog.get("loss")),
        success_physics=number(prog.get("success_physics")),
        return_physics=number(prog.get("return_physics")),
        mujoco_steps=int(prog.get("mujoco_steps") or 0),
        elapsed_s=number(prog.get("elapsed_s")),
        loss_history=thin([number(v) for v in rec.history]),
        error=rec.error or None,
        result=f"/policy-jobs/{rec.id}/result" if rec.status in FINAL_STATES else None,
    )


def _owned(store: JobStore, job_id: str, owner: str) -> JobRecord:
    return owned(store, job_id, owner, POLICY)


@router.get("/policy-jobs", response_model=PolicyJobList, responses=_ERRORS)
def list_policy_jobs(
    store: StoreDep,
    owner: OwnerDep,
    settings: SettingsDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="most jobs to list")] = 50,
) -> PolicyJobList:
    """The caller's recent policy jobs, newest first."""
    recs = jobs_of_kind(store, owner, POLICY, min(limit, settings.max_list), settings.max_list)
    jobs = []
    for rec in recs:
        s = policy_job_status(rec)
        jobs.append(
            PolicyJobSummary(
                id=s.id,
                status=s.status,
                task=s.task,
                model=s.model,
                created_at=s.created_at,
                ended_at=s.ended_at,
                iteration=s.iteration,
                success_physics=s.success_physics,
            )
        )
    return PolicyJobList(jobs=jobs)


@router.get("/policy-jobs/{job_id}", response_model=PolicyJobStatus, responses=_ERRORS)
def get_policy_job(job_id: str, store: StoreDep, owner: OwnerDep) -> PolicyJobStatus:
    """A policy job's status and progress: iteration, loss, the last success on MuJoCo, MuJoCo steps."""
    return policy_job_status(_owned(store, job_id, owner))


@router.get(
    "/policy-jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={**SSE_RESPONSES, 404: {"model": ErrorBody}},
)
async def policy_job_events(
    job_id: str,
    request: Request,
    store: StoreDep,
    owner: OwnerDep,
    last_event_id: Annotated[str | None, Header(description="resume after this event id")] = None,
) -> StreamingResponse:
    """Server-sent events of a policy job: ``status``, ``progress`` per iteration, then one ``end``."""
    await run_in_threadpool(_owned, store, job_id, owner)
    aredis: aioredis.Redis = request.app.state.aredis
    keepalive = request.app.state.settings.sse_keepalive_s
    return sse.job_events(aredis, store, job_id, last_event_id, keepalive)


@router.get("/policy-jobs/{job_id}/result", response_model=PolicyJobResult, responses=_ERRORS)
def get_policy_result(job_id: str, store: StoreDep, owner: OwnerDep) -> PolicyJobResult:
    """The finished policy job's result: the stored policy's manifest (null when none was stored), the
    loss and success histories (409 until it ends)."""
    rec = _owned(store, job_id, owner)
    if rec.status not in FINAL_STATES:
        raise ApiError(
            409,
            "not_finished",
            f"job {job_id} is {rec.status}; its result is here once it ends "
            f"(watch /policy-jobs/{job_id}/events)",
            field="status",
            expected=list(FINAL_STATES),
            got=rec.status,
        )
    result = store.result(job_id)
    if result is None:
        raise ApiError(404, "not_found", f"the result of job {job_id!r} has expired", field="id", got=job_id)
    return PolicyJobResult.model_validate_json(result)


@router.delete("/policy-jobs/{job_id}", response_model=PolicyJobStatus, status_code=202, responses=_ERRORS)
def cancel_policy_job(job_id: str, store: StoreDep, owner: OwnerDep) -> PolicyJobStatus:
    """Cancel a queued policy job (it ends now, storing nothing) or a running one (it stops at its next
    iteration and stores the best policy so far)."""
    rec = _owned(store, job_id, owner)
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
    return policy_job_status(_owned(store, job_id, owner))
