"""Uploaded models: ``GET /models`` (the caller's, an operator's: all), ``POST /models/{name}/publish``
and ``DELETE /models/{name}``.

An uploaded model is its uploader's until an operator (a key of ``OPERATOR_KEYS``) publishes it; then
the emulator and controller services serve it to every key (``services.common.tenancy``). An operator
may delete any uploaded model, its uploader one not yet published. Models that were not uploaded (the
catalog's, or trained with ``neuro train`` on the server) are managed with files, not here. With API
keys off there are no owners: everybody is an operator.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from neuroanimator.artifacts import registry
from neuroanimator.contracts.emulator import ErrorBody
from neuroanimator.contracts.trainer import StoredModel, StoredModelList, Usage
from services.common import tenancy
from services.common.auth import CALLER, OPERATOR, OwnerDep
from services.common.errors import ApiError
from services.common.openapi import Responses
from services.trainer import models
from services.trainer.deps import SettingsDep, StoreDep
from services.trainer.settings import Settings
from services.trainer.store import TrainingStore

router = APIRouter(tags=["models"])
_ERRORS: Responses = {code: {"model": ErrorBody} for code in (403, 404, 409)}


def is_operator() -> bool:
    return CALLER.get() is None or OPERATOR.get()


def stored(root: Path, name: str) -> StoredModel:
    found = tenancy.read(root, name) or tenancy.Ownership(owner="")
    return StoredModel(
        model=name,
        owner=found.owner,
        published=found.published,
        uploaded=found.uploaded,
        versions=registry.versions(root, name),
        size_bytes=registry.model_size(root, name),
    )


def _list(store: TrainingStore, s: Settings, owner: str) -> StoredModelList:
    root = s.data_dir
    names = models.uploaded(root) if is_operator() else models.owned(root, owner)
    mine = models.owned(root, owner)
    usage = Usage(
        trainings=store.active(owner),
        max_trainings=s.max_trainings_per_key,
        models=len(mine),
        max_models=s.max_models_per_key,
        bytes=models.size(root, mine),
        max_bytes=s.max_bytes_per_key,
    )
    return StoredModelList(models=[stored(root, n) for n in names], usage=usage)


@router.get("/models", response_model=StoredModelList)
async def list_models(store: StoreDep, owner: OwnerDep, settings: SettingsDep) -> StoredModelList:
    """The caller's uploaded models (an operator's: every uploaded model), with their owners, versions
    and sizes, and the caller's use of its limits. Names being trained for the first time are listed
    with no versions."""
    return await run_in_threadpool(_list, store, settings, owner)


def uploaded(s: Settings, name: str, owner: str) -> StoredModel:
    """An uploaded model the caller sees; 404 if none (or another key's, unpublished), 409 if the model
    was not uploaded."""
    root = s.data_dir
    found = tenancy.read(root, name) if registry.is_name(name) else None
    if found is None:
        every = s.roots()
        if registry.is_name(name) and (every / name).is_dir() and tenancy.can_see(every, name):
            raise ApiError(
                409,
                "not_uploaded",
                f"model {name!r} was not uploaded (the catalog's, or trained on the server): it is managed "
                "with files, not through this service",
                field="name",
                got=name,
            )
        raise ApiError(404, "not_found", f"no uploaded model {name!r}", field="name", got=name)
    if not (is_operator() or found.owner == owner):
        raise ApiError(404, "not_found", f"no uploaded model {name!r}", field="name", got=name)
    return stored(root, name)


def _publish(s: Settings, name: str, owner: str) -> StoredModel:
    uploaded(s, name, owner)
    if not is_operator():
        raise ApiError(
            403, "forbidden", "only an operator's key (OPERATOR_KEYS) publishes models", field="name"
        )
    models.publish(s.data_dir, name)
    return stored(s.data_dir, name)


@router.post("/models/{name}/publish", response_model=StoredModel, responses=_ERRORS)
async def publish_model(name: str, owner: OwnerDep, settings: SettingsDep) -> StoredModel:
    """Make an uploaded model everybody's (operators only): every key then lists and drives it."""
    return await run_in_threadpool(_publish, settings, name, owner)


def _delete(s: Settings, name: str, owner: str) -> StoredModel:
    model = uploaded(s, name, owner)
    if model.published and not is_operator():
        raise ApiError(
            403, "forbidden", f"model {name!r} is published: only an operator's key deletes it", field="name"
        )
    models.delete(s.data_dir, name)
    return model


@router.delete("/models/{name}", response_model=StoredModel, responses=_ERRORS)
async def delete_model(name: str, owner: OwnerDep, settings: SettingsDep) -> StoredModel:
    """Delete an uploaded model and all its versions (an operator: any; its uploader: one not yet
    published). Sessions already running on it keep their emulator; it is listed no more."""
    return await run_in_threadpool(_delete, settings, name, owner)
