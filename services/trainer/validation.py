"""Checking an uploaded model before it is queued: what ``POST /trainings`` answers at once.

The model is read as ``neuro train --mjcf`` reads it (``mjcf.load_mjcf``: the includes and assets of an
MJCF file, or a .zip / .tar.gz of a model folder, under the service's caps, compiled in the sandbox
where MuJoCo can read nothing but the upload: ``neuroanimator.sim.sandbox``), so every refusal of
``neuroanimator.sim.bundle`` comes back as a 4xx naming the problem (``STATUS`` maps each kind),
and so does a model the trainer could not make an emulator of: no degrees of freedom, no actuators,
or actuators without a ``ctrlrange`` (the emulator is trained over the range of each control; the
command line would guess one, a service asks). Nothing is written: the caller removes the upload.

The model is loaded around its operating point as the training will load it: with the operating spec
of the form (``operating_spec``, ``keyframe``), else the ``operating.json`` of the archive
(``services.trainer.operating``), so that a spec that does not fit the model (an actuator, joint or
keyframe it does not have, a control range outside its ``ctrlrange``) is refused now, naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco

from neuroanimator.core.operating_spec import OperatingRecord, OperatingSpec
from neuroanimator.sim import operating
from neuroanimator.sim.bundle import Limits, SourceError, SourceProblem
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import ModelError, PhysicalModel
from neuroanimator.sim.sandbox import Unconfined
from services.trainer import operating as specs

STATUS: dict[SourceProblem, int] = {
    "not_found": 422,
    "not_xml": 422,
    "compile_error": 422,
    "missing_file": 422,
    "outside_model": 422,
    "unsafe_archive": 422,
    "archive_too_large": 413,
    "file_too_large": 413,
    "mesh_too_large": 422,
    "plugin_refused": 422,
    "entry": 422,
    "bad_timestep": 422,
    "too_costly": 422,
}
"""The HTTP status of each kind of refusal of a model's files: 413 for what is too large, else 422."""


class Refused(Exception):
    """A model that cannot be trained: the HTTP status, an error code and the message naming why."""

    def __init__(self, status: int, error: str, message: str, field: str = "file") -> None:
        super().__init__(message)
        self.status, self.error, self.field = status, error, field


SPEC_ERROR = "invalid_operating_spec"
"""The error code of an operating spec that is not one, or does not fit the model."""


@dataclass(frozen=True)
class Checked:
    """What the check found: the model's name (from the MJCF unless given), its size, the operating
    point it will be trained around (``operating``) and the spec the training is to use (``spec``:
    canonical JSON, the form's or the archive's; ``spec_from`` says which)."""

    model: str
    dofs: int
    controls: list[str]
    assets: int
    operating: OperatingRecord | None = None
    spec: str | None = None
    spec_from: str | None = None


def check_trainable(model: PhysicalModel) -> None:
    """``Refused`` for a model with no degrees of freedom, no actuators, or actuators without a
    ``ctrlrange``, naming them."""
    m = model.mj_model
    if m.nv == 0:
        raise Refused(
            422, "no_joints", f"model {model.name} has no degrees of freedom: nothing moves to emulate"
        )
    if model.num_controls == 0:
        raise Refused(
            422,
            "no_actuators",
            f"model {model.name} has no actuators: an emulator maps a state and controls to the next state; "
            'add an <actuator> (e.g. <motor joint=... ctrlrange="-1 1"/>)',
        )
    unlimited = [
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, int(i)) or f"actuator {int(i)}"
        for i in model.control_ids
        if not m.actuator_ctrllimited[int(i)]
    ]
    if unlimited:
        names = ", ".join(repr(n) for n in unlimited)
        raise Refused(
            422,
            "no_ctrlrange",
            f"model {model.name}: actuator{'s' if len(unlimited) > 1 else ''} {names} "
            f"{'have' if len(unlimited) > 1 else 'has'} no ctrlrange: the emulator is trained over each "
            'control\'s range; give each one, e.g. ctrlrange="-1 1" (and ctrllimited="true" where the '
            "compiler's autolimits is off)",
        )


def spec_field(field: str, spec: OperatingSpec | None, keyframe: str | None) -> str:
    """The form field an ``OperatingSpecError``'s field is in: ``keyframe`` when the form's keyframe
    field named it (and the spec names none), else under ``operating_spec``."""
    if field == "keyframe" and keyframe is not None and (spec is None or spec.keyframe is None):
        return "keyframe"
    return f"{specs.FORM_FIELD}.{field}"


def _archive_spec(
    model: PhysicalModel, path: Path, entry: str | None, keyframe: str | None
) -> tuple[OperatingRecord | None, str | None, str | None]:
    """The archive's ``operating.json``, checked against the model: (the record, the spec's canonical
    JSON, where it was); ``Refused`` naming the file and the field when it is not a spec or does not fit."""
    try:
        found = specs.in_archive(path, entry)
    except specs.SpecProblem as exc:
        raise Refused(422, SPEC_ERROR, str(exc), "file") from exc
    if found is None:
        return model.spec.operating, None, None
    where = f"{found.path} in {path.name}"
    try:
        spec = specs.parse(found.text, found.path)
        record = operating.typical_motion(model, spec, keyframe).operating
    except specs.SpecProblem as exc:
        raise Refused(422, SPEC_ERROR, f"{path.name}: {exc}", "file") from exc
    except operating.OperatingSpecError as exc:
        raise Refused(422, SPEC_ERROR, f"{where}: {exc}", "file") from exc
    return record, specs.canonical(spec), where


def check_model(
    path: Path,
    entry: str | None,
    name: str | None,
    limits: Limits,
    require_landlock: bool = True,
    spec: OperatingSpec | None = None,
    keyframe: str | None = None,
) -> Checked:
    """Read and check an uploaded model, around its operating point (``spec``: the form's operating
    spec; without one, the archive's ``operating.json``; see the module's text); ``Refused`` with the
    status."""
    try:
        model = load_mjcf(
            path,
            entry=entry,
            name=name,
            limits=limits,
            stabilise=False,
            require_landlock=require_landlock,
            operating_spec=spec,
            keyframe=keyframe,
        )
    except Unconfined as exc:
        raise Refused(503, "sandbox_unavailable", str(exc)) from exc
    except SourceError as exc:
        raise Refused(
            STATUS[exc.kind], exc.kind, str(exc), "entry" if exc.kind == "entry" else "file"
        ) from exc
    except operating.OperatingSpecError as exc:  # the spec does not fit the model: an actuator it lacks, ...
        field = spec_field(exc.field, spec, keyframe)
        raise Refused(422, SPEC_ERROR, f"{field}: {exc.reason}", field) from exc
    except ModelError as exc:  # e.g. no joints: no state to emulate
        error = "no_joints" if "no joints" in str(exc) else "invalid_model"
        raise Refused(422, error, str(exc)) from exc
    check_trainable(model)
    record, text, where = (
        (model.spec.operating, specs.canonical(spec), f"the form field {specs.FORM_FIELD}")
        if spec is not None
        else _archive_spec(model, path, entry, keyframe)
    )
    return Checked(
        model.name,
        int(model.mj_model.nv),
        list(model.control_names),
        len(model.assets),
        operating=record,
        spec=text,
        spec_from=where,
    )
