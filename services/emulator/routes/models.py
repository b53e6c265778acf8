"""``GET /models`` and ``GET /models/{model}``: the loaded emulators and their manifests."""

from __future__ import annotations

from fastapi import APIRouter

from neuroanimator.schemas import ErrorBody, ModelDetail, ModelList, ModelSummary
from services.emulator.deps import EngineDep
from services.emulator.registry import Loaded

router = APIRouter(tags=["models"])


def summary(emu: Loaded, versions: list[str]) -> ModelSummary:
    m = emu.manifest
    return ModelSummary(
        model=emu.model,
        version=emu.version,
        substeps=int(m["substeps"]),
        timestep=float(m["timestep"]),
        super_timestep=emu.super_timestep,
        state_size=emu.state_size,
        num_controls=emu.num_controls,
        num_forces=emu.num_forces,
        versions=versions,
    )


@router.get("/models", response_model=ModelList)
def list_models(engine: EngineDep) -> ModelList:
    reg = engine.registry
    return ModelList(models=[summary(reg.get(name), reg.versions(name)) for name in reg.models()])


@router.get("/models/{model}", response_model=ModelDetail, responses={404: {"model": ErrorBody}})
def get_model(model: str, engine: EngineDep, version: str | None = None) -> ModelDetail:
    reg = engine.registry
    emu = reg.get(model, version)
    m = emu.manifest
    return ModelDetail(
        **summary(emu, reg.versions(model)).model_dump(),
        description=str(m.get("description", "")),
        layout=m["layout"],
        state_labels=m["state_labels"],
        controls=m["controls"],
        forces=m["forces"],
        metrics=m.get("metrics", {}),
    )
