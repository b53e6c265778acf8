"""Trainings: ``POST /trainings`` (an upload), ``GET /trainings``, ``GET /trainings/{id}``,
``GET /trainings/{id}/events`` (server-sent events) and ``DELETE /trainings/{id}``.

``POST /trainings`` answers in this order, so that what can be refused early is refused before the
upload is read whole: the caller's concurrent trainings (429: a place taken atomically in Redis before
anything else, given back if the upload is refused), the content type (415), the body's size (413, by
``limits.BodyLimitMiddleware`` while it streams), the form's fields (422; an ``operating_spec`` that is
not JSON or not an operating spec too, naming the field inside it), the file's type (415), then the
model itself (``validation``, in a sandbox process, ``MAX_VALIDATIONS`` at once: 4xx naming the
problem, an operating spec that does not fit the model included), then under the caller's lock its name (409 when it is not available) and the caller's stored
models and bytes (429). Nothing is kept of a refused upload.

A training belongs to the API key that made it: any other key gets 404 for it, as if it did not exist.
"""

from __future__ import annotations

import contextlib
import logging
import re
import shutil
import threading
from pathlib import Path, PurePosixPath
from typing import Annotated, Any

import redis
import redis.asyncio as aioredis
from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.responses import StreamingResponse
from pydantic import ValidationError
from python_multipart.exceptions import MultipartParseError
from redis.exceptions import LockError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.formparsers import MultiPartException

from neuroanimator.contracts.emulator import ErrorBody
from neuroanimator.contracts.trainer import (
    LossPoint,
    TrainingAccepted,
    TrainingList,
    TrainingOptions,
    TrainingResult,
    TrainingStatus,
    TrainingSummary,
    TrainingUpload,
)
from neuroanimator.core.operating_spec import OperatingSpec
from services.common import job_events
from services.common.auth import CALLER, OwnerDep
from services.common.errors import ApiError, from_validation
from services.common.jobs import FINAL, JobRecord, QueueFull, new_id
from services.common.openapi import Responses
from services.common.queue_app import queue_full
from services.trainer import models
from services.trainer import operating as specs
from services.trainer.deps import SettingsDep, StoreDep
from services.trainer.metrics import Metrics
from services.trainer.settings import Settings
from services.trainer.spec import TrainingProgress, TrainingSpec
from services.trainer.store import TrainingStore
from services.trainer.validation import SPEC_ERROR, Checked, Refused, check_model

log = logging.getLogger(__name__)
router = APIRouter(tags=["trainings"])
UPLOAD_SUFFIXES = (".xml", ".zip", ".tar.gz", ".tgz")
_UPLOAD_ERRORS: Responses = {code: {"model": ErrorBody} for code in (409, 413, 415, 422, 429, 503)}
_ERRORS: Responses = {code: {"model": ErrorBody} for code in (404, 503)}
_CANCEL_ERRORS: Responses = {code: {"model": ErrorBody} for code in (404, 409, 503)}
_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {"multipart/form-data": {"schema": TrainingUpload.model_json_schema()}},
    }
}
_PHASE_OF = {"queued": "queued", "succeeded": "done", "failed": "failed", "cancelled": "cancelled"}


def training_status(rec: JobRecord, result: str | None) -> TrainingStatus:
    """The wire view of a record from ``TrainingStore.record`` (and, once it succeeded, its stored
    result, JSON)."""
    spec = TrainingSpec.model_validate_json(rec.spec)
    prog = TrainingProgress.model_validate(rec.progress)
    status = rec.status
    running = status == "running"
    done = None
    if status == "succeeded" and result is not None:
        done = TrainingResult.model_validate_json(result)  # the stored id, status and reason are left out
    return TrainingStatus(
        id=rec.id,
        status=status,
        phase=(prog.phase or "validating") if running else _PHASE_OF[status],
        model=spec.model,
        super_step=spec.super_step,
        examples=spec.examples,
        percent=100.0 if status == "succeeded" else min(100.0, prog.percent or 0.0),
        eta_s=prog.eta_s if running else None,
        elapsed_s=prog.elapsed_s,
        detail=prog.detail if running else None,
        loss_curve=[LossPoint(epoch=int(p[0]), loss=p[1]) for p in rec.history if isinstance(p, list)],
        created_at=rec.created_at,
        started_at=rec.started_at or None,
        ended_at=rec.ended_at or None,
        attempt=rec.attempt,
        failures=rec.failures,
        worker=rec.worker or None,
        error=rec.error or None,
        result=done,
    )


def owned(store: TrainingStore, job_id: str, owner: str) -> JobRecord:
    """The caller's training, else 404 (also for another key's)."""
    rec = store.record(job_id, owner)
    if rec is None:
        raise ApiError(
            404, "not_found", f"no training {job_id!r} (it may have expired)", field="id", got=job_id
        )
    return rec


def _status(store: TrainingStore, job_id: str, owner: str) -> TrainingStatus:
    rec = owned(store, job_id, owner)
    return training_status(rec, store.result(job_id) if rec.status == "succeeded" else None)


def limit_error(name: str, what: str, limit: int, got: int) -> ApiError:
    return ApiError(
        429,
        "limit_exceeded",
        f"{what}: the limit is {limit:,} ({name}={limit})",
        field=name,
        expected=f"<= {limit}",
        got=got,
    )


def _reserve(store: TrainingStore, owner: str, s: Settings, job_id: str) -> None:
    """Take one of the caller's places for trainings (atomic in Redis), else 429."""
    taken, held = store.reserve(owner, job_id, s.max_trainings_per_key)
    if not taken:
        who = "this API key has" if CALLER.get() else "there are"
        raise limit_error(
            "MAX_TRAININGS_PER_KEY",
            f"{who} {held} trainings queued, running or being uploaded; wait for one to end (or cancel one)",
            s.max_trainings_per_key,
            held,
        )


def release(store: TrainingStore, s: Settings, name: str, owner: str, job_id: str) -> None:
    """Give the name back if nothing was exported under it and no other training of the owner's holds it."""
    if not store.active(owner, name, but=job_id):
        models.release(s.data_dir, name, owner)


def _storage(s: Settings, owner: str, name: str, upload_bytes: int) -> None:
    """429 when a new model or the upload would pass the caller's stored models or bytes (keys on)."""
    if CALLER.get() is None:
        return
    mine = models.owned(s.data_dir, owner)
    if name not in mine and len(mine) >= s.max_models_per_key:
        raise limit_error(
            "MAX_MODELS_PER_KEY",
            f"this API key has {len(mine)} models stored; delete one (DELETE /models/{{name}}) to add another",
            s.max_models_per_key,
            len(mine),
        )
    used = models.size(s.data_dir, mine)
    if used + upload_bytes > s.max_bytes_per_key:
        raise limit_error(
            "MAX_BYTES_PER_KEY",
            f"this API key's models take {used:,} bytes and the upload {upload_bytes:,} more; delete a model "
            "or an old version's model to make room",
            s.max_bytes_per_key,
            used + upload_bytes,
        )


def upload_name(filename: str | None) -> str:
    """The upload's file name, made safe (its type kept); 415 when it is not an MJCF or an archive."""
    name = PurePosixPath((filename or "").replace("\\", "/")).name
    lower = name.lower()
    suffix = next((x for x in UPLOAD_SUFFIXES if lower.endswith(x)), None)
    if suffix is None:
        raise ApiError(
            415,
            "unsupported_file",
            f"the file must be an MJCF (.xml) or a .zip / .tar.gz / .tgz of a model folder; got {name!r}",
            field="file",
            expected=list(UPLOAD_SUFFIXES),
            got=name,
        )
    stem = re.sub(r"[^A-Za-z0-9_-]+", "-", name[: len(name) - len(suffix)]).strip("-") or "model"
    return stem[:64] + suffix


def operating_spec(opts: TrainingOptions) -> OperatingSpec | None:
    """The form's operating spec, read (None when there is none); 422 naming the field inside it when
    it is not JSON or not an operating spec."""
    if opts.operating_spec is None or not opts.operating_spec.strip():
        return None
    try:
        return specs.parse(opts.operating_spec)
    except specs.SpecProblem as exc:
        raise ApiError(
            422,
            SPEC_ERROR,
            str(exc),
            field=exc.field,
            expected="an operating spec, JSON (docs/operating-spec.md)",
        ) from exc


async def read_form(request: Request) -> tuple[UploadFile, TrainingOptions, OperatingSpec | None, Any]:
    """The upload, its options and its operating spec from the multipart form (the form, to close when
    done)."""
    ctype = request.headers.get("content-type", "")
    if not ctype.lower().startswith("multipart/form-data"):
        raise ApiError(
            415,
            "unsupported_media_type",
            "send the model as multipart/form-data: the file as field 'file', the options as fields",
            field="body",
            expected="multipart/form-data",
            got=ctype.split(";")[0] or None,
        )
    try:
        form = await request.form(max_files=1, max_fields=16, max_part_size=16_384)
    except (MultiPartException, MultipartParseError) as exc:
        raise ApiError(400, "bad_request", f"the multipart form cannot be read: {exc}", field="body") from exc
    file = form.get("file")
    if not isinstance(file, UploadFile):
        await form.close()
        raise ApiError(
            422, "invalid_request", "the form has no file: send the model as field 'file'", field="file"
        )
    fields = {k: v for k, v in form.multi_items() if k != "file"}
    try:
        if any(isinstance(v, UploadFile) for v in fields.values()):
            raise ApiError(422, "invalid_request", "send one file, as field 'file'", field="file")
        opts = TrainingOptions.model_validate(fields)
        spec = operating_spec(opts)
    except ValidationError as exc:
        await form.close()
        raise from_validation([dict(e) for e in exc.errors()]) from exc
    except ApiError:
        await form.close()
        raise
    return file, opts, spec, form


def _check(
    s: Settings,
    path: Path,
    opts: TrainingOptions,
    spec: OperatingSpec | None,
    checks: threading.BoundedSemaphore,
) -> Checked:
    """The model checked in the sandbox, around its operating point, at most ``MAX_VALIDATIONS`` at once
    (503 when none frees up within ``VALIDATION_WAIT_S``)."""
    if not checks.acquire(timeout=s.validation_wait_s):
        raise ApiError(
            503,
            "busy",
            f"the service is checking {s.max_validations} other uploads (MAX_VALIDATIONS); try again shortly",
        )
    try:
        return check_model(
            path, opts.entry, opts.name, s.limits(), s.require_landlock, spec=spec, keyframe=opts.keyframe
        )
    except Refused as exc:
        raise ApiError(exc.status, exc.error, str(exc), field=exc.field) from exc
    finally:
        checks.release()


def _accept(
    store: TrainingStore,
    s: Settings,
    owner: str,
    job_id: str,
    path: Path,
    opts: TrainingOptions,
    spec: OperatingSpec | None,
    checks: threading.BoundedSemaphore,
) -> TrainingAccepted:
    """Check the stored upload and queue its training (in a worker thread: the check runs in a sandbox
    process, then the owner's models and bytes are counted and the name claimed under the owner's lock)."""
    checked = _check(s, path, opts, spec, checks)
    name = checked.model
    lock = store.owner_lock(owner)
    if not lock.acquire():
        raise ApiError(503, "busy", "another upload of this API key is being queued; try again shortly")
    try:
        _storage(s, owner, name, path.stat().st_size)
        try:
            new = models.claim(s.roots(), name, owner)
        except models.NameTaken as exc:
            raise ApiError(409, "name_taken", str(exc), field="name", got=name) from exc
        queued = TrainingSpec(
            model=name,
            source=path.relative_to(s.uploads()).as_posix(),
            entry=opts.entry,
            super_step=opts.super_step,
            examples=opts.examples or s.default_examples,
            epochs=opts.epochs,
            hidden=opts.hidden,
            rollout_steps=opts.rollout_steps,
            force=opts.force,
            operating_spec=checked.spec,
            keyframe=opts.keyframe,
        )
        try:
            store.submit_spec(queued.to_json(), owner, job_id=job_id, log_extra={"model": name})
        except BaseException:
            release(store, s, name, owner, job_id)
            raise
    finally:
        with contextlib.suppress(redis.RedisError, LockError):
            lock.release()
    what = "a new model" if new else f"a new version of your model {name!r}"
    dofs = f"{checked.dofs} degrees of freedom, {len(checked.controls)} controls"
    point = "" if checked.operating is None else f"; {checked.operating.describe()}"
    given = f", with the operating spec of {checked.spec_from}" if checked.spec_from else ""
    return TrainingAccepted(
        id=job_id,
        status="queued",
        phase="queued",
        model=name,
        new_version=not new,
        message=f"{name}: {dofs}{point}{given}; queued to train {what}",
    )


@router.post(
    "/trainings",
    response_model=TrainingAccepted,
    status_code=202,
    responses=_UPLOAD_ERRORS,
    openapi_extra=_UPLOAD_BODY,
)
async def create_training(
    request: Request, response: Response, store: StoreDep, owner: OwnerDep, settings: SettingsDep
) -> TrainingAccepted:
    """Upload a MuJoCo model (an MJCF file, or a .zip / .tar.gz of its folder) and queue its training.

    The model is checked before this answers: a 4xx names what is wrong with it (which file is missing,
    MuJoCo's compile error with the file and line, which actuator has no ``ctrlrange``, ...), and so
    does one for an operating spec (``operating_spec``, or the archive's ``operating.json``) that is not
    one or does not fit the model (``operating_spec.controls.thrust9``: an actuator it does not have).
    The answer's message says which operating point the training will use and why."""
    metrics: Metrics = request.app.state.metrics
    checks: threading.BoundedSemaphore = request.app.state.checks
    job_id = new_id()
    try:
        await run_in_threadpool(_reserve, store, owner, settings, job_id)
        try:
            file, opts, spec, form = await read_form(request)
            folder = settings.uploads() / job_id
            try:
                path = folder / upload_name(file.filename)
                folder.mkdir(parents=True)
                with path.open("wb") as out:
                    await run_in_threadpool(shutil.copyfileobj, file.file, out, 1 << 20)
                await form.close()
                accepted = await run_in_threadpool(
                    _accept, store, settings, owner, job_id, path, opts, spec, checks
                )
            except BaseException:
                await form.close()
                shutil.rmtree(folder, ignore_errors=True)
                raise
        except BaseException:
            with contextlib.suppress(redis.RedisError):
                await run_in_threadpool(store.unreserve, owner, job_id)
            raise
    except QueueFull as exc:
        metrics.rejected.labels("queue_full").inc()
        raise queue_full(exc) from exc
    except ApiError as exc:
        metrics.rejected.labels(exc.body.error).inc()
        raise
    metrics.submitted.inc()
    response.headers["Location"] = f"/trainings/{job_id}"
    log.info("training accepted", extra={"job": job_id, "model": accepted.model, "owner": owner})
    return accepted


@router.get("/trainings", response_model=TrainingList, responses=_ERRORS)
def list_trainings(
    store: StoreDep,
    owner: OwnerDep,
    settings: SettingsDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="most trainings to list")] = 50,
) -> TrainingList:
    """The caller's recent trainings, newest first."""
    out = []
    for rec in store.jobs_of(owner, min(limit, settings.max_list)):
        s = training_status(rec, None)
        out.append(
            TrainingSummary(
                id=s.id,
                status=s.status,
                phase=s.phase,
                model=s.model,
                percent=s.percent,
                created_at=s.created_at,
                ended_at=s.ended_at,
            )
        )
    return TrainingList(trainings=out)


@router.get("/trainings/{training_id}", response_model=TrainingStatus, responses=_ERRORS)
def get_training(training_id: str, store: StoreDep, owner: OwnerDep) -> TrainingStatus:
    """A training's phase, percent, time left and loss curve; once done, its result (the artifact's
    model and version, its one-step error against the linear baseline, its errors in physical units)."""
    return _status(store, training_id, owner)


@router.get(
    "/trainings/{training_id}/events",
    response_class=StreamingResponse,
    responses={**job_events.SSE_RESPONSES, 404: {"model": ErrorBody}},
    tags=["events"],
)
async def training_events(
    training_id: str,
    request: Request,
    store: StoreDep,
    owner: OwnerDep,
    last_event_id: Annotated[str | None, Header(description="resume after this event id")] = None,
) -> StreamingResponse:
    """Server-sent events of a training: ``status`` (queued, running), ``progress`` (phase, percent,
    detail, time left, and ``losses``: the loss curve's new ``[epoch, loss]`` points), then one ``end``
    (the result when it succeeded). With API keys on, ``?api_key=`` works too (EventSource)."""
    await run_in_threadpool(owned, store, training_id, owner)
    aredis: aioredis.Redis = request.app.state.aredis
    keepalive = request.app.state.settings.sse_keepalive_s
    return job_events.job_events(aredis, store, training_id, last_event_id, keepalive)


def _cancel(store: TrainingStore, s: Settings, job_id: str, owner: str) -> TrainingStatus:
    rec = owned(store, job_id, owner)
    if rec.status in FINAL:
        raise ApiError(
            409,
            "already_ended",
            f"training {job_id} already ended: {rec.status}",
            field="status",
            expected=["queued", "running"],
            got=rec.status,
        )
    if store.cancel(job_id) == "cancelled":  # it had not started: nothing else will clean up after it
        shutil.rmtree(s.uploads() / job_id, ignore_errors=True)
        release(store, s, TrainingSpec.model_validate_json(rec.spec).model, owner, job_id)
    return _status(store, job_id, owner)


@router.delete(
    "/trainings/{training_id}", response_model=TrainingStatus, status_code=202, responses=_CANCEL_ERRORS
)
def cancel_training(
    training_id: str, store: StoreDep, owner: OwnerDep, settings: SettingsDep
) -> TrainingStatus:
    """Cancel a queued training (it ends now) or a running one (its process is stopped within seconds);
    nothing is exported."""
    return _cancel(store, settings, training_id, owner)
