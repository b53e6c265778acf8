"""Session lifecycle and REST stepping: ``/sessions``, ``/sessions/{id}``, ``/sessions/{id}/step``."""

from __future__ import annotations

from fastapi import APIRouter, Response

from neuroanimator.emulator_schemas import ErrorBody, SessionCreate, SessionInfo, StepRequest, StepResponse
from services.emulator.deps import EngineDep

router = APIRouter(tags=["sessions"])
_ERRORS: dict[int | str, dict[str, object]] = {
    404: {"model": ErrorBody},
    409: {"model": ErrorBody},
    422: {"model": ErrorBody},
    429: {"model": ErrorBody},
}


@router.post("/sessions", response_model=SessionInfo, status_code=201, responses=_ERRORS)
async def create_session(req: SessionCreate, engine: EngineDep) -> SessionInfo:
    return engine.info(engine.create_session(req))


@router.get("/sessions/{sid}", response_model=SessionInfo, responses=_ERRORS)
async def get_session(sid: str, engine: EngineDep) -> SessionInfo:
    return engine.info(engine.store.get(sid))


@router.delete("/sessions/{sid}", status_code=204, responses=_ERRORS)
async def delete_session(sid: str, engine: EngineDep) -> Response:
    engine.delete(sid)
    return Response(status_code=204)


@router.post("/sessions/{sid}/step", response_model=StepResponse, responses=_ERRORS)
async def step_session(sid: str, req: StepRequest, engine: EngineDep) -> StepResponse:
    sess = engine.store.get(sid)
    return await engine.step(sess, req.controls, req.forces, req.steps, req.frames_per_step)
