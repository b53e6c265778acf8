"""``GET /models``, ``GET /models/{model}``: the loaded emulators and their manifests; ``/geometry``,
``/poses`` and ``/assets/{asset}``: what a client needs to draw a model (bodies, geoms, world poses of
states, the mesh and texture files its MJCF names)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse

from neuroanimator.artifacts import registry
from neuroanimator.contracts.emulator import (
    ControlInfo,
    DriverInfo,
    ErrorBody,
    ForceInfo,
    ModelDetail,
    ModelGeometry,
    ModelList,
    ModelSummary,
    PosesRequest,
    PosesResponse,
)
from services.common.openapi import Responses
from services.emulator.deps import ServiceDep
from services.emulator.errors import UnknownModel
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
    ranges, training metrics, the envelope of its training states and, for a model of one's own, the
    operating point it was trained around (``operating``)."""
    reg = service.registry
    emu = reg.get(model, version)
    m = emu.manifest
    return ModelDetail(
        **summary(emu, reg.versions(model)).model_dump(),
        description=m.description,
        layout=m.layout,
        state_labels=m.state_labels,
        controls=[ControlInfo(**c.model_dump()) for c in m.controls],
        forces=[ForceInfo.of(f.name, f.body, f.component, f.low, f.high) for f in m.forces],
        metrics=m.metrics.model_dump(),
        envelope=m.envelope,
        driver=None if m.spec.driver is None else DriverInfo(**m.spec.driver.model_dump(exclude={"factory"})),
        operating=m.spec.operating,
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


MEDIA_TYPES = {
    ".stl": "model/stl",
    ".obj": "model/obj",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
}
"""The media type of an asset by its extension; any other file is ``application/octet-stream``."""
_ASSET_RESPONSES: Responses = {
    200: {
        "description": "the file, as the artifact stores it (its ETag is its SHA-256)",
        "content": {t: {} for t in (*dict.fromkeys(MEDIA_TYPES.values()), "application/octet-stream")},
    },
    404: {"model": ErrorBody},
}


@router.get("/models/{model}/assets/{asset}", response_class=FileResponse, responses=_ASSET_RESPONSES)
async def get_asset(model: str, asset: str, service: ServiceDep, version: str | None = None) -> FileResponse:
    """A file the model's MJCF names (a mesh, texture, height field or skin), by the name ``/geometry``
    gives it (``<sha256><extension>``: its content, so it never changes)."""
    emu = service.registry.get(model, version)
    found = next((a for a in emu.manifest.assets if a.name == asset), None)
    if found is None:
        names = [a.name for a in emu.manifest.assets]
        raise UnknownModel(
            f"model {emu.model!r} version {emu.version!r} has no asset {asset!r}; its assets are {names}",
            code="unknown_asset",
            field="asset",
            expected=names,
            got=asset,
        )
    file = registry.assets_dir(emu.path) / found.name
    if not file.is_file():
        raise UnknownModel(
            f"model {emu.model!r} version {emu.version!r}: its {found.kind} {found.source or asset} is "
            "missing from the artifact registry",
            code="missing_asset",
            field="asset",
            got=asset,
        )
    suffix = "." + asset.rsplit(".", 1)[-1].lower() if "." in asset else ""
    return FileResponse(
        file,
        media_type=MEDIA_TYPES.get(suffix, "application/octet-stream"),
        headers={"ETag": f'"{found.sha256}"', "Cache-Control": "private, max-age=31536000, immutable"},
    )
