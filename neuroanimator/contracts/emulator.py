"""The emulator service's wire contract: pydantic v2 models shared by the server and its clients.

Shapes use the artifact's manifest: S = state size, U = controls, F = external forces. Every vector
travels as a JSON list of numbers; a number must be a finite JSON number (strings, booleans, NaN and
Infinity are rejected with 422 naming the field). Lengths are checked against the model by the
service, which answers 422 with the field, the expected and the got length.

Controls and forces outside the manifest's range (``low``..``high`` of each control and force: the
range the emulator was trained over) are clipped to it; a step's response lists the clipped indices
in ``clipped_controls`` / ``clipped_forces`` and sets ``clipped: true``.

A new state outside the envelope of the states the emulator was trained on (the manifest's
``envelope``: per state group, the range of the training data) is still returned, but the step's
response says so: ``outside_envelope: true`` and the groups that are out in ``outside_groups``.

A session may be driven by a trained feedback policy (``SessionCreate.policy``): every super-step the
policy reads the session's state and goal (G values) and sets its controls; the client sends goals
and forces, never controls. A goal outside the range the policy was trained for is accepted and
flagged in every reply (``goal_outside`` names its variables), as a state outside the training
envelope is.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from neuroanimator.core.manifest import EnvelopeGroup
from neuroanimator.core.model_spec import DriverParam
from neuroanimator.core.operating_spec import OperatingRecord
from neuroanimator.core.state import LayoutGroup

WIRE_MODELS_FROM_ELSEWHERE = (LayoutGroup, EnvelopeGroup, DriverParam, OperatingRecord)
"""Wire models owned by another module (the state layout's), exported to proto/ with these."""

Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""A finite JSON number (int or float; no strings, booleans, NaN or Infinity)."""
Vector = list[Number]
DriverParams = dict[str, Number]
"""A driver's parameters by name (``ModelDetail.driver.params``), e.g. ``{"speed": 2.2}``."""
Integer = Annotated[int, Field(strict=True)]
"""A JSON integer (no strings, booleans or fractions)."""
Flag = Annotated[bool, Field(strict=True)]
"""JSON ``true`` or ``false`` (no strings or numbers)."""


class _Wire(BaseModel):
    model_config = ConfigDict(extra="forbid")


# ---------------------------------------------------------------- catalog
class ControlInfo(BaseModel):
    """One control input: ``low``..``high`` is the trained range (inputs are clipped to it). A value
    ``u`` applies ``gain · u`` of ``unit`` (N, N·m; a servo's target in rad or m); ``sign`` says what a
    positive value does. Emulators trained before these were recorded leave them null."""

    name: str
    low: float
    high: float
    limit_low: float | None = None
    limit_high: float | None = None
    label: str | None = Field(None, description="a short name in words, e.g. 'main jet'")
    unit: str | None = Field(None, description="unit of what the control applies: N, N·m, rad, m, rad/s, m/s")
    gain: float | None = Field(None, description="what a control value of 1 applies, in unit")
    sign: str | None = Field(None, description="what a positive value does (the sign convention)")


class ForceInfo(BaseModel):
    """One external-force input (a body's force or torque component) and its trained range, with what
    it is in words and its unit."""

    model_config = ConfigDict(extra="allow")
    name: str
    low: float
    high: float
    body: str | None = Field(None, description="the body it is applied to (at its centre of mass)")
    component: int | None = Field(None, description="0-2: force along world x, y, z; 3-5: torque about them")
    unit: str | None = Field(None, description="N for a force, N·m for a torque")
    description: str | None = Field(None, description="what it applies, in words")

    @classmethod
    def of(cls, name: str, body: str, component: int, low: float, high: float) -> ForceInfo:
        """The wire form of a manifest's force input, its unit and words derived from its component."""
        axis = "xyz"[component % 3]
        what = (
            f"a push along the world {axis} axis"
            if component < 3
            else f"a torque about the world {axis} axis"
        )
        unit = "N" if component < 3 else "N·m"
        return cls(
            name=name,
            low=low,
            high=high,
            body=body,
            component=component,
            unit=unit,
            description=f"{what} on {body} at its centre of mass, in {unit}",
        )


class ModelSummary(BaseModel):
    """A loaded emulator: its current (latest) version and the versions loaded beside it."""

    model: str
    version: str
    substeps: int
    timestep: float
    super_timestep: float
    state_size: int
    num_controls: int
    num_forces: int
    versions: list[str]


class DriverInfo(BaseModel):
    """A model's driver: its name, what it does, and the parameters a client may set."""

    name: str
    description: str = ""
    params: list[DriverParam]


class ModelDetail(ModelSummary):
    """The manifest's description of the latest (or the named) version."""

    description: str = ""
    layout: list[LayoutGroup]
    state_labels: list[str]
    controls: list[ControlInfo]
    forces: list[ForceInfo]
    metrics: dict[str, Any] = {}
    envelope: list[EnvelopeGroup] | None = Field(
        None, description="per state group, the range of the training states (absent for older artifacts)"
    )
    driver: DriverInfo | None = Field(
        None,
        description="the model's own controller, which a session may ask for (SessionCreate.driver): it sets "
        "every control each super-step, and the client sets its params and the forces",
    )
    operating: OperatingRecord | None = Field(
        None,
        description="the operating point a model of one's own was trained around (its keyframes, the controls "
        "that hold it still, or the operating spec given), why, and the controls' centres and spread: the "
        "motion the emulator knows best (absent for catalog models and older artifacts)",
    )


class ModelList(BaseModel):
    models: list[ModelSummary]


# ---------------------------------------------------------------- scene (what a client draws)
class MaterialInfo(BaseModel):
    """A geom's MJCF material. MuJoCo draws a geom in its material's ``rgba`` unless the geom has an
    ``rgba`` of its own (one other than the default ``0.5 0.5 0.5 1``); ``emission``, ``specular``,
    ``shininess`` and ``reflectance`` are MuJoCo's lighting coefficients in 0..1."""

    name: str
    rgba: list[float]
    emission: float = 0.0
    specular: float = 0.5
    shininess: float = 0.5
    reflectance: float = 0.0


class MeshInfo(BaseModel):
    """The file a mesh geom is drawn from, and where its vertices go. ``asset`` is the artifact's file
    (``GET /models/{model}/assets/{asset}``: STL, OBJ or MuJoCo's MSH), null for a mesh whose vertices
    are written in the MJCF. MuJoCo scales a mesh, then moves it so that its centre of mass and axes of
    inertia are the geom's frame: a file's vertex ``v`` is at ``conj(quat) · (scale ∘ v − pos)`` in the
    geom's frame (``quat`` is ``[w, x, y, z]``)."""

    name: str
    asset: str | None
    scale: list[float]
    pos: list[float]
    quat: list[float]


class GeomInfo(BaseModel):
    """One MuJoCo geom, in its body's frame. ``type``: MuJoCo's geom type (``box``, ``sphere``,
    ``capsule``, ``cylinder``, ``ellipsoid``, ``plane``, ``mesh``...); ``size``: MuJoCo's three size
    numbers (box: half-extents; sphere: radius; capsule and cylinder: radius, half-length along the
    geom's z; ellipsoid: radii; plane: half-extents, 0 meaning infinite; mesh: half-extents of its
    bounding box). ``quat`` is ``[w, x, y, z]``; ``rgba`` in 0..1 (the geom's own; see ``material``);
    ``group``: MuJoCo's visibility group (0–2 are drawn by default); ``mesh``: a mesh geom's file."""

    name: str
    type: str
    size: list[float]
    pos: list[float]
    quat: list[float]
    rgba: list[float]
    group: int = 0
    material: MaterialInfo | None = None
    mesh: MeshInfo | None = None


class BodyInfo(BaseModel):
    """A moving body: ``parent`` is the index of its parent in ``bodies`` (-1: the world)."""

    name: str
    parent: int
    geoms: list[GeomInfo]


class SkinBone(BaseModel):
    """One bone of a skin: a body (its index in ``bodies``), the body's pose when the skin was bound
    (``bindpos``, ``bindquat`` ``[w, x, y, z]``, world frame), and the skin vertices it moves with their
    weights."""

    body: int
    bindpos: list[float]
    bindquat: list[float]
    vertices: list[int]
    weights: list[float]


class SkinInfo(BaseModel):
    """A MuJoCo skin (MJCF ``<skin>``): a triangle surface whose vertices follow bodies, drawn over
    them (the dolphin's body surface over its nodes). ``vertices`` (V·3) are the bind positions,
    ``faces`` (F·3) vertex indices. A vertex's world position at poses is MuJoCo's (``mjv_updateSkin``):
    ``Σ_bones w · (R(q) v + p − R(q) bindpos)`` with ``q = quat ⊗ bindquat⁻¹`` and (p, quat) the
    bone's body pose; then it is pushed ``inflate`` metres along its normal."""

    name: str
    rgba: list[float]
    inflate: float = 0.0
    vertices: list[float]
    faces: list[int]
    bones: list[SkinBone]


class ModelGeometry(BaseModel):
    """What a client draws for a model, from the artifact's MJCF: its bodies and their geoms, the geoms
    fixed to the world, its skins, the rest state (MuJoCo's qpos0, which a joint's ``ref`` moves off
    zero: the dolphin's nodes sit at their rest positions) and every body's world pose
    ``[x, y, z, qw, qx, qy, qz]`` there. ``center`` and ``extent`` are MuJoCo's estimate of the model's middle and size (for a camera)."""

    model: str
    version: str
    bodies: list[BodyInfo]
    world: list[GeomInfo]
    skins: list[SkinInfo] = []
    rest_state: list[float] | None = Field(
        None, description="the state at MuJoCo's qpos0 with nothing moving (a Playground start at rest)"
    )
    rest_poses: list[list[float]]
    center: list[float]
    extent: float


class PosesRequest(_Wire):
    """States (K, S) of one model version (the latest unless ``version`` is given) to pose."""

    states: Annotated[list[Vector], Field(min_length=1)]
    version: str | None = None


class PosesResponse(BaseModel):
    """``poses`` (K, bodies, 7): each body's world pose ``[x, y, z, qw, qx, qy, qz]`` in each state."""

    model: str
    version: str
    bodies: list[str]
    poses: list[list[list[float]]]


# ---------------------------------------------------------------- sessions
class PolicyDrive(_Wire):
    """A trained feedback policy of the model (``neuro policy``) that sets a session's controls every
    super-step from its state and a goal; ``goal`` (G values, the policy's ``goal_variables``)
    defaults to the policy's ``goal_default``."""

    name: str = Field(description="the policy's name (its task's), e.g. lander-landing")
    version: str | None = Field(None, description="a stored version of the policy; its latest when absent")
    goal: Vector | None = Field(None, description="the goal, G values; the policy's default when absent")


class PolicyStatus(BaseModel):
    """The policy driving a session and its goal. ``goal_low``..``goal_high``: the goals it was trained
    for; ``goal_outside`` names the goal variables outside them (accepted, less reliable)."""

    name: str
    version: str
    emulator_version: str = Field(description="the emulator version it was trained through (the session's)")
    goal_variables: list[str]
    goal: list[float]
    goal_low: list[float]
    goal_high: list[float]
    goal_default: list[float]
    goal_outside: list[str] = []
    timed: bool = Field(False, description="it reads the time left until its goal's check as well")


class SessionCreate(_Wire):
    """``state`` (S values) starts the session there; otherwise a random typical start drawn from
    ``seed`` (a fresh seed when absent, returned in the response)."""

    model: str
    version: str | None = None
    state: Vector | None = None
    seed: Annotated[int, Field(ge=0, strict=True)] | None = None
    driver: DriverParams | None = Field(
        None,
        description="run the model's driver (ModelDetail.driver) with these parameters ({} for its "
        "defaults): it sets the controls every super-step; without a state, the session starts where "
        "the driver starts (the runner: a running stride at the target speed)",
    )
    policy: PolicyDrive | None = Field(
        None,
        description="drive the session with a trained policy of the model: it sets the controls every "
        "super-step from the state and the goal; the client sends goals and forces. The session runs the "
        "emulator version the policy was trained through (version, when given, must be that one)",
    )


class SessionInfo(BaseModel):
    """A session: its id names the replica that owns it (``<replica>-<token>``)."""

    id: str
    model: str
    version: str
    state: list[float]
    t: float = Field(description="simulated time in seconds (super-steps × Δt)")
    steps: int
    diverged: bool
    seed: int | None = None
    ttl_s: float
    driver: dict[str, float] | None = Field(
        None,
        description="the driver's parameters when the model's driver sets the controls; null: the client",
    )
    policy: PolicyStatus | None = Field(None, description="the policy setting the controls, and its goal")


_GOAL_DOC = (
    "a policy-driven session only: its new goal (G values, the policy's goal_variables); the clock of "
    "a timed policy restarts when the goal changes"
)
_CONTROLS_DOC = "the controls the session's driver or policy chose (null: the client's)"
_GOAL_OUT_DOC = "a policy-driven session's goal (null otherwise)"
_GOAL_OUTSIDE_DOC = "the goal variables outside the goals the policy was trained for"


class StepRequest(_Wire):
    """Hold ``controls`` (U) and ``forces`` (F) for ``steps`` super-steps. A policy-driven session takes
    no controls (422): its policy sets them each super-step towards ``goal``."""

    controls: Vector = []
    forces: Vector = []
    steps: Annotated[int, Field(ge=1, strict=True)] = 1
    frames_per_step: Annotated[int, Field(ge=1, strict=True)] | None = None
    driver: DriverParams | None = Field(
        None,
        description="a driven session only: new parameters for its driver (the rest keep their values); "
        "its controls come from the driver, so controls may be left out",
    )
    goal: Vector | None = Field(None, description=_GOAL_DOC)


class StepResponse(BaseModel):
    """``states`` (steps, S) after each super-step, ``state`` the last of them. ``frames`` (when
    asked): steps·frames_per_step + 1 frames from the old state to the new one, evenly spaced in
    time (linear, slerp for quaternion groups). ``outside_envelope``: some new state is outside the
    states the emulator was trained on (``outside_groups`` names the groups); it is less accurate
    there."""

    id: str
    state: list[float]
    states: list[list[float]]
    frames: list[list[float]] | None = None
    t: float
    steps: int
    clipped: bool
    clipped_controls: list[int] = []
    clipped_forces: list[int] = []
    outside_envelope: bool = Field(
        False, description="a new state is outside the envelope of the states the emulator was trained on"
    )
    outside_groups: list[str] = Field([], description="the state groups outside the training envelope")
    controls: list[list[float]] | None = Field(
        None, description="(steps, U): the controls of each super-step, when the driver or policy chose them"
    )
    goal: list[float] | None = Field(None, description=_GOAL_OUT_DOC)
    goal_outside: list[str] = Field([], description=_GOAL_OUTSIDE_DOC)


class BatchStepItem(_Wire):
    """One session's inputs; a policy-driven session takes a ``goal`` (optional) and no controls."""

    session: str
    controls: Vector = []
    forces: Vector = []
    goal: Vector | None = Field(None, description=_GOAL_DOC)


class BatchStepRequest(_Wire):
    """One super-step of many sessions (any models) in one request; at most MAX_BATCH items."""

    items: list[BatchStepItem]


class ErrorBody(BaseModel):
    """Every error: a machine-readable ``error`` code and a readable ``message``; for bad input,
    the ``field`` (e.g. ``controls`` or ``items[2].forces``) and what was ``expected`` and ``got``."""

    error: str
    message: str
    field: str | None = None
    expected: Any = None
    got: Any = None


class BatchStepResult(BaseModel):
    """One item's outcome: the new state, or the session's error (others are unaffected)."""

    session: str
    state: list[float] | None = None
    t: float | None = None
    clipped: bool = False
    clipped_controls: list[int] = []
    clipped_forces: list[int] = []
    outside_envelope: bool = Field(
        False, description="a new state is outside the envelope of the states the emulator was trained on"
    )
    outside_groups: list[str] = Field([], description="the state groups outside the training envelope")
    controls: list[float] | None = Field(None, description=_CONTROLS_DOC)
    goal: list[float] | None = Field(None, description=_GOAL_OUT_DOC)
    goal_outside: list[str] = Field([], description=_GOAL_OUTSIDE_DOC)
    error: ErrorBody | None = None


class BatchStepResponse(BaseModel):
    results: list[BatchStepResult]


# ---------------------------------------------------------------- websockets
class WsStep(_Wire):
    """Client → server, lock-step mode: one super-step under these inputs."""

    type: Literal["step"]
    controls: Vector = []
    forces: Vector = []
    driver: DriverParams | None = Field(
        None,
        description="a driven session only: new parameters for its driver (the rest keep their values); "
        "its controls come from the driver, so controls may be left out",
    )
    goal: Vector | None = Field(None, description=_GOAL_DOC)
    seq: int | None = None


class WsPing(_Wire):
    type: Literal["ping"]
    seq: int | None = None


class WsStart(_Wire):
    """Client → server: switch the connection's mode and/or the format of its state frames.

    ``realtime``: the server advances the session every Δt of wall time with the latest inputs (set by
    ``controls`` messages or binary frames) and pushes each new state (a slow reader gets the newest
    ones; older ones are dropped). ``lockstep`` (the default): one state per ``step``. ``format``
    ``binary`` sends states as binary frames (proto/frames.md); errors stay JSON. Also available as
    query parameters: ``/ws/sessions/{id}?mode=realtime&format=binary``.

    ``poses: true`` adds each body's world pose (``GET /models/{model}/geometry`` lists the bodies) to
    every state message. ``shadow: true`` (re)starts a MuJoCo twin of the session from its current
    state: the service steps it with the same held inputs and sends its state (and poses, when asked)
    along in each state message as ``shadow``; ``shadow: false`` stops it. Both need the JSON format.
    Omitted (``null``) leaves the setting as it was."""

    type: Literal["start"]
    mode: Literal["lockstep", "realtime"] = "lockstep"
    format: Literal["json", "binary"] | None = None
    poses: bool | None = None
    shadow: bool | None = None
    seq: int | None = None


class WsControls(_Wire):
    """Client → server: the inputs held from now on; real-time mode steps with the latest of them
    (its state messages echo the ``seq`` of the controls they used)."""

    type: Literal["controls"]
    controls: Vector = []
    forces: Vector = []
    driver: DriverParams | None = Field(
        None,
        description="a driven session only: new parameters for its driver (the rest keep their values); "
        "its controls come from the driver, so controls may be left out",
    )
    goal: Vector | None = Field(None, description=_GOAL_DOC)
    seq: int | None = None


ClientMessage = Annotated[WsStep | WsPing | WsStart | WsControls, Field(discriminator="type")]


class ShadowState(BaseModel):
    """The MuJoCo twin of a session (``shadow: true``): the physics stepped with the same held inputs
    from the state the twin started at. ``diverged``: its state stopped being finite; it is no longer
    stepped."""

    state: list[float]
    poses: list[list[float]] | None = None
    diverged: bool = False
    controls: list[float] | None = Field(
        None, description="the controls its own copy of the session's driver or policy chose"
    )


class WsState(BaseModel):
    """Server → client: the session's new state (``seq`` echoes the request's). ``poses`` (with
    ``poses: true``): per body, ``[x, y, z, qw, qx, qy, qz]`` in the world frame; ``shadow`` (with
    ``shadow: true``): the MuJoCo twin's state. Both are left out when not asked for. A driven session's
    state carries the ``controls`` its driver or policy chose for the step; a policy-driven one's also
    its ``goal`` and ``goal_outside`` (left out for the others)."""

    type: Literal["state"] = "state"
    seq: int | None = None
    state: list[float]
    t: float
    steps: int
    clipped: bool = False
    clipped_controls: list[int] = []
    clipped_forces: list[int] = []
    outside_envelope: bool = Field(
        False, description="a new state is outside the envelope of the states the emulator was trained on"
    )
    outside_groups: list[str] = Field([], description="the state groups outside the training envelope")
    poses: list[list[float]] | None = None
    shadow: ShadowState | None = None
    controls: list[float] | None = Field(None, description=_CONTROLS_DOC)
    goal: list[float] | None = Field(None, description=_GOAL_OUT_DOC)
    goal_outside: list[str] = Field([], description=_GOAL_OUTSIDE_DOC)


class WsPong(BaseModel):
    type: Literal["pong"] = "pong"
    seq: int | None = None


class WsError(ErrorBody):
    """Server → client: this message could not be served; the connection stays open."""

    type: Literal["error"] = "error"
    seq: int | None = None


class WsStarted(BaseModel):
    """Server → client: the mode and format now in force; real-time states come every ``period_s``."""

    type: Literal["started"] = "started"
    seq: int | None = None
    mode: Literal["lockstep", "realtime"]
    format: Literal["json", "binary"]
    super_timestep: float
    period_s: float
    state_size: int
    num_controls: int
    num_forces: int
    poses: bool = False
    shadow: bool = False


ServerMessage = Annotated[WsState | WsPong | WsError | WsStarted, Field(discriminator="type")]
