"""Policies: ``POST /policies`` (queue a policy job), ``GET /policies`` and ``GET /policies/{model}/{name}``
(stored policies), ``GET /policy-tasks`` (the built-in policy tasks).

A policy job trains a feedback policy for a policy task (a built-in one by name, or a user's own
``PolicyTaskSpec``, checked against its model's emulator) through the task's emulator and stores it,
under the task's name, beside the emulator (``GET /policy-jobs/{id}`` follows it). Stored policies
are read from the service's registries, the data directory's over the committed defaults; a policy
of a model the caller does not see (another key's upload) is not listed, and is 404.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from neuroanimator.artifacts.policies import PolicyError, list_policies, read_policy, resolve_policy
from neuroanimator.artifacts.registry import is_name
from neuroanimator.catalog.suite import SUITE_TASK_INFO
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.contracts.controller import (
    JobAccepted,
    PolicyJobCreate,
    PolicyList,
    PolicyTaskInfo,
    PolicyTaskList,
)
from neuroanimator.contracts.emulator import ErrorBody
from neuroanimator.core.policy_manifest import PolicyManifest
from services.common import tenancy
from services.common.auth import OwnerDep
from services.common.errors import ApiError
from services.common.openapi import Responses
from services.common.queue_app import queue_full
from services.controller.deps import SettingsDep, StoreDep
from services.controller.metrics import Metrics
from services.controller.policies import PolicySpecError, policy_spec
from services.controller.store import IdempotencyConflict, QueueFull, clean

router = APIRouter(tags=["policies"])
_ERRORS: Responses = {
    404: {"model": ErrorBody},
    409: {"model": ErrorBody},
    422: {"model": ErrorBody},
    503: {"model": ErrorBody},
}
Name = Annotated[str, Query(max_length=128)]


@router.post("/policies", response_model=JobAccepted, status_code=202, responses=_ERRORS)
def create_policy_job(
    req: PolicyJobCreate,
    request: Request,
    response: Response,
    store: StoreDep,
    owner: OwnerDep,
    settings: SettingsDep,
) -> JobAccepted:
    """Queue a policy job: train a policy for a built-in policy task (``GET /policy-tasks``) or a task
    of your own (an object: model, starts, goal, target, weights, success checks) and store it under
    the task's name; follow it at ``/policy-jobs/{id}`` (the ``Location``). The same ``idempotency_key`` returns the
    same job."""
    metrics: Metrics = request.app.state.metrics
    try:
        spec = policy_spec(req, settings.roots(), settings.policy_max_seconds)
    except PolicySpecError as exc:
        metrics.rejected.labels("invalid").inc()
        raise ApiError(
            422, "invalid_job", str(exc), field=exc.field, expected=exc.expected, got=exc.got
        ) from exc
    try:
        job_id, status, created = store.submit_policy(spec, owner, req.idempotency_key)
    except QueueFull as exc:
        metrics.rejected.labels("queue_full").inc()
        raise queue_full(exc) from exc
    except IdempotencyConflict as exc:
        metrics.rejected.labels("conflict").inc()
        raise ApiError(409, "idempotency_conflict", str(exc), field="idempotency_key") from exc
    if created:
        metrics.submitted.inc()
    response.headers["Location"] = f"/policy-jobs/{job_id}"
    return JobAccepted(id=job_id, status=status, created=created)


@router.get("/policy-tasks", response_model=PolicyTaskList)
def list_policy_tasks() -> PolicyTaskList:
    """The built-in policy tasks: model, super-step, goals, success criterion and state layout; then
    dm_control's suite tasks (``kind`` ``reward``: judged by the suite's reward on MuJoCo, their model
    the suite's MJCF trained under the domain's name)."""
    tasks = [PolicyTaskInfo(**clean(t.to_dict())) for t in POLICY_TASKS.values()]
    suite = [PolicyTaskInfo(**t.to_dict()) for t in SUITE_TASK_INFO.values()]
    return PolicyTaskList(tasks=tasks + suite)


@router.get("/policies", response_model=PolicyList)
def get_policies(settings: SettingsDep, model: Name | None = None) -> PolicyList:
    """The stored policies (the latest version of each), of every model the caller sees or of ``model``."""
    root = settings.roots()
    found = list_policies(root, model)
    return PolicyList(policies=[p for p in found if tenancy.can_see(root, p.model)])


@router.get("/policies/{model}/{name}", response_model=PolicyManifest, responses={404: {"model": ErrorBody}})
def get_policy(model: str, name: str, settings: SettingsDep, version: Name | None = None) -> PolicyManifest:
    """A stored policy's manifest: its emulator, goals, state layout and how it did (``metrics``); the
    latest version unless ``version`` is given."""
    root = settings.roots()
    try:
        # a name that is no plain name is no model (and never reaches the file system)
        if not (is_name(model) and tenancy.can_see(root, model)):
            raise PolicyError(f"policy {name!r} for model {model!r} not found")
        return read_policy(resolve_policy(root, model, name, version))
    except PolicyError as exc:
        field = "version" if version is not None else "name"
        raise ApiError(404, "not_found", str(exc), field=field, got=version or name) from exc
