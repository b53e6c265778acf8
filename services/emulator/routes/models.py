"""``GET /models``, ``GET /models/{model}``: the loaded emulators and their manifests; ``/geometry`` and
``/poses``: what a client needs to draw a model (bodies, geoms, world poses of states)."""

from __future__ import annotations

from fastapi import APIRouter

from neuroanimator.emulator_schemas import (
    ControlInfo,
    ErrorBody,
    ForceInfo,
    ModelDetail,
    ModelGeometry,
    ModelList,
    ModelSummary,
    PosesRequest,
    PosesResponse,
)
from services.emulator.deps import ServiceDep
from services.emulator.registry import LoadedEmulator
from services.emulator.scene import check_states, geometry

router = APIRouter(tags=["models"])


def summary(emu: LoadedEmulator, versions: list[str]) -> ModelSummary:
    m = emu.manifest
    return ModelSummary(
        model=emu.model,
        version=emu.version,
        substeps=m.substeps,
        timestep=m.timestep,
        super_timestep=emu.super_timestep,
        state_size=emu.state_size,
        num_controls=emu.num_controls,
        num_forces=emu.num_forces,
        versions=versions,
    )


@router.get("/models", response_model=ModelList)
async def list_models(service: ServiceDep) -> ModelList:
    """The models served: each one's latest version, time steps, sizes and the versions loaded beside it
    (``GET /models/{model}`` has the whole manifest)."""
    reg = service.registry
    return ModelList(models=[summary(reg.get(name), reg.versions(name)) for name in reg.models()])


@router.get("/models/{model}", response_model=ModelDetail, responses={404: {"model": ErrorBody}})
async def get_model(model: str, service: ServiceDep, version: str | None = None) -> ModelDetail:
    """A model version's manifest: state layout and labels, controls and forces with their trained
    ranges, training metrics."""
    reg = service.registry
    emu = reg.get(model, version)
    m = emu.manifest
    return ModelDetail(
        **summary(emu, reg.versions(model)).model_dump(),
        description=m.description,
        layout=m.layout,
        state_labels=m.state_labels,
        controls=[ControlInfo(**c.model_dump()) for c in m.controls],
        forces=[ForceInfo(**f.model_dump()) for f in m.forces],
        metrics=m.metrics.model_dump(),
        envelope=m.envelope,
    )


@router.get("/models/{model}/geometry", response_model=ModelGeometry, responses={404: {"model": ErrorBody}})
async def get_geometry(model: str, service: ServiceDep, version: str | None = None) -> ModelGeometry:
    """The model's bodies and geoms (from its MJCF) and their rest poses, for drawing it."""
    emu = service.registry.get(model, version)
    return geometry(emu.model, emu.version, emu.kinematics)


@router.post(
    "/models/{model}/poses",
    response_model=PosesResponse,
    responses={404: {"model": ErrorBody}, 422: {"model": ErrorBody}},
)
def post_poses(model: str, req: PosesRequest, service: ServiceDep) -> PosesResponse:
    """Every body's world pose in each of the given states (forward kinematics in MuJoCo)."""
    emu = service.registry.get(model, req.version)
    states = check_states(
        req.states, emu.state_size, f"model {emu.model!r}", service.settings.max_frames_per_request
    )
    kin = emu.kinematics
    return PosesResponse(
        model=emu.model,
        version=emu.version,
        bodies=kin.body_names,
        poses=kin.poses(states).round(6).tolist(),
    )
