"""FastAPI dependencies: the app's ``Engine``."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from services.emulator.engine import Engine


async def get_engine(request: Request) -> Engine:
    # async: FastAPI runs a plain ``def`` dependency in a worker thread, a thread hop per request
    engine: Engine = request.app.state.engine
    return engine


EngineDep = Annotated[Engine, Depends(get_engine)]
