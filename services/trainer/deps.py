"""FastAPI dependencies: the app's settings and training store (the caller: ``services.common.auth.OwnerDep``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from services.trainer.settings import Settings
from services.trainer.store import TrainingStore


# async: FastAPI runs a plain ``def`` dependency in a worker thread, a thread hop per request.
async def get_store(request: Request) -> TrainingStore:
    store: TrainingStore = request.app.state.store
    return store


async def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


StoreDep = Annotated[TrainingStore, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
