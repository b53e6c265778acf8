"""FastAPI dependencies: the app's settings and job store, and who is calling."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from services.controller.settings import Settings
from services.controller.store import JobStore
from services.emulator.auth import CALLER

PUBLIC = "public"
"""The owner of jobs made while API keys are off."""


# async: FastAPI runs a plain ``def`` dependency in a worker thread, a thread hop per request.
async def get_store(request: Request) -> JobStore:
    store: JobStore = request.app.state.store
    return store


async def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


async def get_owner() -> str:
    """The caller's key id (set by the API-key middleware), or ``public`` when keys are off."""
    return CALLER.get() or PUBLIC


StoreDep = Annotated[JobStore, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
OwnerDep = Annotated[str, Depends(get_owner)]
