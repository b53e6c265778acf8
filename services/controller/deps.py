"""FastAPI dependencies: the app's settings and job store (the caller: ``services.common.auth.OwnerDep``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from services.controller.settings import Settings
from services.controller.store import JobStore


# async: FastAPI runs a plain ``def`` dependency in a worker thread, a thread hop per request.
async def get_store(request: Request) -> JobStore:
    store: JobStore = request.app.state.store
    return store


async def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


StoreDep = Annotated[JobStore, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
