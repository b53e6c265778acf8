"""FastAPI dependencies: the app's ``EmulatorService``."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from services.emulator.service import EmulatorService


async def get_service(request: Request) -> EmulatorService:
    # async: FastAPI runs a plain ``def`` dependency in a worker thread, a thread hop per request
    service: EmulatorService = request.app.state.service
    return service


ServiceDep = Annotated[EmulatorService, Depends(get_service)]
