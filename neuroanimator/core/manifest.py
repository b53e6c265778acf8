"""``Manifest``: what an artifact version is, read from its ``manifest.json``; the one owner of its keys.

A manifest says which model and version an artifact is, its time steps (δt and the super-step
Δt = n·δt), the state layout, the controls and external forces with their ranges, the inputs and
output of its ONNX graph, how the emulator is built from networks, how it was trained, and hashes of
what it was made from. Everything that reads an artifact reads this type; nothing reads the JSON by key.

The emulator is described as networks plus a composition (``EmulatorGraph``), so that an emulator
made of several networks is a manifest of the same shape as today's one-network emulator:

- the one-network emulator: one network ``core`` in the model's root frame that reads every state
  group it needs, the controls and the forces, and writes the change of every state group;
  ``stages = [["core"]]``;
- a hierarchy: a network ``body`` in the root frame writing the root's groups, then one network per
  body part in that part's frame (``frame.part``: an MJCF body), each reading the root's new state
  (``reads.predicted``) and its own part's groups; ``stages = [["body"], ["arm_l", "arm_r", ...]]``;
- a hierarchy over ``parts`` (thesis 4.4, ``neuroanimator.emulator.hierarchy``): a network ``global`` writing
  every part's frame quantities (derived groups ``<part>.<quantity>``, not state groups), then one
  network per part in that part's frame (``frame.part``: a name in ``parts``), reading its predicted
  frame and writing its part's state groups; ``stages = [["global"], [part, ...]]``.

The file carries a schema version, ``format``. Older formats are upgraded when read
(``parse_manifest``); a format this code does not know is refused, naming the versions it reads.
Imports neither torch nor MuJoCo.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from neuroanimator.core.model_spec import (
    FRAME_QUANTITIES,
    ForceInput,
    HierarchyPart,
    ModelSpec,
    SpringRegularizer,
)
from neuroanimator.core.state import LayoutGroup, StateLayout
from neuroanimator.core.train_config import TrainConfig

FORMAT: Literal[2] = 2
"""The manifest format this code writes."""
READABLE_FORMATS = (1, 2)
"""The formats this code reads (older ones are upgraded in memory)."""

Activation = Literal["sigmoid", "tanh", "silu", "gelu", "relu"]
GraphInput = Literal["state", "controls", "forces"]


class ManifestError(ValueError):
    """A manifest that cannot be read as this code understands it; the message says why."""


class _Strict(BaseModel):
    # Python's json writes an unlimited control's ±inf as Infinity, and reads it back: keep that.
    model_config = ConfigDict(extra="forbid", frozen=True, ser_json_inf_nan="constants")


class ControlInput(_Strict):
    """One control: ``low``..``high`` is the range the emulator was trained over (inputs are clipped
    to it); ``limit_low``/``limit_high`` the actuator's hard limits (±inf where unlimited).

    What it means (``ModelSpec.control_info``, else derived from the MJCF's actuator): a value ``u``
    applies ``gain · u`` of ``unit``, and ``sign`` says what a positive value does. Versions written
    before these were recorded have None there."""

    name: str
    low: float
    high: float
    limit_low: float
    limit_high: float
    label: str | None = None
    unit: str | None = None
    gain: float | None = None
    sign: str | None = None


class Symmetries(_Strict):
    """The symmetries that are true of the physics: translation of each root-position axis, and
    rotation about the vertical axis (``PhysicalModel.frame``)."""

    translate: list[bool]
    rotate: bool
    # scalar groups of root slide joints it is translation-invariant along (``PhysicalModel.frame``)
    slides: list[str] = []


class GraphIO(_Strict):
    """The ONNX graph's inputs, in order (each (B, width)), and its output ``next_state`` (B, S)."""

    inputs: list[GraphInput]
    output: Literal["next_state"] = "next_state"


class InputGroup(_Strict):
    """A block of a network's inputs that shares normalisation statistics (``mode="group"``)."""

    name: str
    size: int = Field(ge=1)


class Normalization(_Strict):
    """T^σ of one network: inputs ``x`` (D values) and outputs ``y`` are normalised to zero mean and
    unit deviation, per group (``"group"``, thesis eqs. 4.10-4.11) or per variable (``"variable"``)."""

    mode: Literal["group", "variable"]
    input_groups: list[InputGroup]
    x_mean: list[float]
    x_std: list[float]
    y_mean: list[float]
    y_std: list[float]

    @model_validator(mode="after")
    def _sizes_agree(self) -> Normalization:
        d = sum(g.size for g in self.input_groups)
        if not len(self.x_mean) == len(self.x_std) == d:
            raise ValueError(
                f"x_mean and x_std must have {d} values (the input groups' sizes), "
                f"got {len(self.x_mean)} and {len(self.x_std)}"
            )
        if len(self.y_mean) != len(self.y_std):
            raise ValueError(f"y_mean and y_std differ in length: {len(self.y_mean)} and {len(self.y_std)}")
        return self


class NetworkFrame(_Strict):
    """The frame a network's inputs and outputs are expressed in.

    ``part`` is ``None`` for the model's root frame, else the MJCF body whose frame it is (a body
    part of a hierarchy), or the name of one of ``EmulatorGraph.parts``. ``translate`` (one flag per root-position axis) and ``rotate`` (about the
    vertical axis) are the symmetries removed; ``force_pairs`` lists force inputs (indices into the
    forces) that are rotated together as one vector. ``body``: the frame turns with the whole attitude
    of the root (the body frame, gravity entering as the body-frame up vector), not only its heading.
    """

    part: str | None = None
    translate: list[bool] = []
    rotate: bool = False
    force_pairs: list[list[int]] = []
    control_pairs: list[list[int]] = []  # controls along world axes (indices), turned with the frame
    body: bool = False
    slides: list[str] = []  # scalar groups of root slides translated away: not read (``Symmetries.slides``)


class NetworkLimit(_Strict):
    """A limited joint the network reads through ramps past its limits (see ``structured.JointLimit``):
    ``position``/``velocity`` are state columns, ``low``/``high`` the range, ``horizon`` the seconds
    over which the joint is extrapolated (one super-step), ``margin`` how far past the range a
    predicted position may go (None: no bound; see ``structured.JointLimit``)."""

    position: int = Field(ge=0)
    velocity: int | None = Field(default=None, ge=0)
    low: float
    high: float
    horizon: float = Field(ge=0.0)
    margin: float | None = Field(default=None, ge=0.0)


class NetworkReads(_Strict):
    """What a network reads: state groups of the current state (``state``), state groups of the next
    state as written by networks of earlier stages (``predicted``), controls and forces, by name."""

    state: list[str]
    predicted: list[str] = []
    controls: list[str] = []
    forces: list[str] = []


class NetworkClearance(_Strict):
    """The geoms whose height above the floor the network reads (``neuroanimator.emulator.clearance``), the
    pairs of geoms whose distance it reads (``neuroanimator.emulator.proximity``) and the tendons whose slack it
    reads, by MJCF name, each at the start, middle and end of a super-step of ``horizon`` seconds."""

    geoms: list[str] = []
    pairs: list[tuple[str, str]] = []
    tendons: list[str] = []  # limited tendons through sites: the slack before each one's upper limit
    horizon: float = Field(ge=0.0)

    @model_validator(mode="after")
    def _reads_something(self) -> NetworkClearance:
        if not (self.geoms or self.pairs or self.tendons):
            raise ValueError("clearance names no geom, pair of geoms or tendon")
        return self


class Network(_Strict):
    """One network of an emulator: an MLP (``hidden`` widths, ``activation``) between its
    normalisation, reading ``reads`` in its frame and predicting the change of the state groups in
    ``writes``. ``input_size`` D and ``output_size`` are its widths; ``weights`` its parameter count;
    ``skip``: a linear map of the inputs is added to the MLP's output."""

    name: str
    frame: NetworkFrame
    reads: NetworkReads
    writes: list[str]
    hidden: list[int]
    activation: Activation
    normalization: Normalization
    input_size: int = Field(ge=1)
    output_size: int = Field(ge=1)
    weights: int = Field(ge=0)
    skip: bool = False
    limits: list[NetworkLimit] = []
    clearance: NetworkClearance | None = None
    # the MLP is the mean of this many MLPs of the same widths (an ensemble, neuroanimator.emulator.articulated)
    members: int = Field(1, ge=1)

    @model_validator(mode="after")
    def _widths_agree(self) -> Network:
        norm = self.normalization
        if len(norm.x_mean) != self.input_size:
            raise ValueError(
                f"network {self.name!r}: input_size is {self.input_size}, its normalisation has {len(norm.x_mean)}"
            )
        if len(norm.y_mean) != self.output_size:
            raise ValueError(
                f"network {self.name!r}: output_size is {self.output_size}, its normalisation has {len(norm.y_mean)}"
            )
        return self


class EmulatorGraph(_Strict):
    """An emulator as networks and their composition.

    ``stages`` lists the networks by stage: the networks of a stage run after those of earlier stages
    (they may read what those wrote, ``reads.predicted``) and are independent of each other. Every
    state group is written by exactly one network; the next state is the state plus every network's
    change, back in world axes. A one-network emulator is ``stages = [[name]]``.

    ``parts`` (a hierarchy of ``neuroanimator.emulator.hierarchy``): the parts whose frames are derived groups
    ``<part>.<quantity>`` (3 values each), which networks may write and read like state groups.
    """

    networks: list[Network] = Field(min_length=1)
    stages: list[list[str]] = Field(min_length=1)
    parts: list[HierarchyPart] = []
    regularizer: SpringRegularizer | None = Field(
        None,
        description="after the networks, this many Euler steps of the model's springs (thesis 6.1.3), "
        "in the ONNX graph; None: none",
    )

    @model_validator(mode="after")
    def _composition_is_sound(self) -> EmulatorGraph:
        names = [n.name for n in self.networks]
        if len(set(names)) != len(names):
            raise ValueError(f"network names must be unique, got {names}")
        staged = [name for stage in self.stages for name in stage]
        if sorted(staged) != sorted(names) or any(not stage for stage in self.stages):
            raise ValueError(f"stages must name every network once, in non-empty stages; got {self.stages}")
        writers: dict[str, str] = {}
        by_name = {n.name: n for n in self.networks}
        for stage in self.stages:
            for name in stage:
                net = by_name[name]
                for group in net.reads.predicted:
                    if group not in writers:
                        raise ValueError(
                            f"network {name!r} reads the predicted {group!r}, which no earlier stage writes"
                        )
            for name in stage:
                for group in by_name[name].writes:
                    if group in writers:
                        raise ValueError(
                            f"state group {group!r} is written by {writers[group]!r} and {name!r}"
                        )
                    writers[group] = name
        return self

    @property
    def derived(self) -> dict[str, int]:
        """The derived groups (the parts' frame quantities) by name, with their sizes."""
        return {f"{p.name}.{q}": 3 for p in self.parts for q in FRAME_QUANTITIES}

    @property
    def written(self) -> list[str]:
        """Every state group some network writes."""
        derived = self.derived
        return [g for n in self.networks for g in n.writes if g not in derived]

    @property
    def weights(self) -> int:
        return sum(n.weights for n in self.networks)

    def only(self) -> Network:
        """The network of a one-network emulator; ``ManifestError`` for a composed one."""
        if len(self.networks) != 1:
            raise ManifestError(
                f"this emulator is composed of {len(self.networks)} networks "
                f"({[n.name for n in self.networks]}); only one-network emulators can be used here"
            )
        return self.networks[0]


class TrainMetrics(BaseModel):
    """Measured when the emulator was trained: sizes, held-out one-step errors, seconds spent.
    Further measurements recorded at training time are kept beside these."""

    model_config = ConfigDict(extra="allow", frozen=True)

    weights: int
    examples: int
    test_examples: int
    one_step_rel_error: float
    linear_baseline_rel_error: float
    validation_rel_error: float
    data_seconds: float
    train_seconds: float
    total_seconds: float


class ModelAsset(_Strict):
    """A file the model's MJCF names (a mesh, texture, height field or skin), stored once per model by
    its content: ``<root>/<model>/assets/<name>``, ``name`` = ``<sha256><extension>``, shared by every
    version that uses it. ``source`` is where it was found, relative to the model's folder."""

    name: str = Field(pattern=r"^[0-9a-f]{64}(\.[A-Za-z0-9]+)?$")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    kind: Literal["mesh", "texture", "hfield", "skin"]
    size: int = Field(ge=0, description="bytes")
    source: str = ""


class EnvelopeGroup(_Strict):
    """The values one state group took in the training data (the states and the next states the emulator
    learnt from), widened by a margin: ``low[i]``..``high[i]`` for its value i. ``None`` where the
    emulator is indifferent to the value: a root-position axis it is translation-invariant along, a
    heading its frame removes, a hinge angle (it enters as sin and cos), an orientation quaternion."""

    group: str
    low: list[float | None]
    high: list[float | None]


class Hashes(_Strict):
    """SHA-256 of the MJCF, of the training data (``Examples.sha256``) and of ``emulator.onnx``."""

    mjcf_sha256: str
    training_data_sha256: str
    onnx_sha256: str


class Tuning(_Strict):
    """How a version was made from another: fine-tuned on the MuJoCo runs of a policy's training (its
    exploring runs, its refinements), so that the policy is served with the emulator it learned through."""

    from_version: str = Field(description="the version it was fine-tuned from")
    task: str = Field(description="the task whose policy's training fine-tuned it")
    refinements: int = Field(ge=1, description="how many times it was fine-tuned")


class Manifest(_Strict):
    """One artifact version (``<root>/<model>/<version>/manifest.json``); see the module docstring.

    Shapes: S = ``state_size`` (the layout's total), U = ``len(controls)``, F = ``len(forces)``.
    """

    format: Literal[2] = FORMAT
    model: str
    version: str
    created: str = Field(description="ISO 8601 time the version was written (UTC)")
    substeps: int = Field(ge=1, description="n: physical steps per super-step")
    timestep: float = Field(gt=0, description="δt of the physics, seconds")
    super_timestep: float = Field(gt=0, description="Δt = n·δt, seconds")
    description: str = ""
    state_size: int
    layout: list[LayoutGroup]
    state_labels: list[str]
    controls: list[ControlInput]
    forces: list[ForceInput]
    frame: Symmetries
    io: GraphIO
    emulator: EmulatorGraph
    train_config: TrainConfig
    metrics: TrainMetrics
    hashes: Hashes
    spec: ModelSpec
    assets: list[ModelAsset] = Field(
        default_factory=list, description="the files model.xml names, stored by content beside the versions"
    )
    envelope: list[EnvelopeGroup] | None = Field(
        None,
        description="per state group, the range of the training data (absent in older artifacts): a "
        "state outside it is beyond what the emulator was trained on",
    )
    tuned: Tuning | None = Field(
        None,
        description="present when the version was fine-tuned from another for a policy (no pointer "
        "names it: the policy's sessions run it)",
    )

    @model_validator(mode="after")
    def _parts_agree(self) -> Manifest:
        layout = self.state_layout()  # offsets in order, names unique
        if layout.size != self.state_size or len(self.state_labels) != self.state_size:
            raise ValueError(
                f"state_size is {self.state_size}, the layout has {layout.size} values "
                f"and {len(self.state_labels)} labels"
            )
        groups = [g.name for g in self.layout]
        if sorted(self.emulator.written) != sorted(groups):
            raise ValueError(
                f"the networks must write every state group once: groups {groups}, written {self.emulator.written}"
            )
        derived = self.emulator.derived
        clash = sorted(set(derived) & set(groups))
        if clash:
            raise ValueError(f"the parts' frame quantities {clash} have the names of state groups")
        sizes = {g.name: g.size for g in self.layout} | derived
        controls, forces = {c.name for c in self.controls}, {f.name for f in self.forces}
        for net in self.emulator.networks:
            written = sum(sizes[g] for g in net.writes)
            if net.output_size != written:
                raise ValueError(
                    f"network {net.name!r} writes {net.writes} ({written} values), but its output_size is {net.output_size}"
                )
            r = net.reads
            for kind, read, known in (
                ("state group", r.state + r.predicted, set(groups) | set(derived)),
                ("control", r.controls, controls),
                ("force", r.forces, forces),
            ):
                unknown = sorted(set(read) - known)
                if unknown:
                    raise ValueError(f"network {net.name!r} reads unknown {kind}s {unknown}")
        for env in self.envelope or []:
            if env.group not in sizes or not len(env.low) == len(env.high) == sizes[env.group]:
                raise ValueError(
                    f"envelope of {env.group!r}: one low and one high per value of a state group "
                    f"({sizes.get(env.group)} values), got {len(env.low)} and {len(env.high)}"
                )
        return self

    @property
    def num_controls(self) -> int:
        return len(self.controls)

    @property
    def num_forces(self) -> int:
        return len(self.forces)

    def state_layout(self) -> StateLayout:
        """The layout as a ``StateLayout`` (slices, labels, lookups by kind)."""
        return StateLayout.of(self.layout)


def parse_manifest(data: Mapping[str, Any], source: str = "manifest") -> Manifest:
    """A manifest from its JSON data, upgraded from an older format if need be.

    ``source`` names the file in messages. Raises ``ManifestError`` for a format this code does not
    read (naming the format found and the formats read) and for data that does not fit the format.
    """
    found = data.get("format")
    if isinstance(found, bool) or found not in READABLE_FORMATS:  # true == 1 in Python, not in JSON
        raise ManifestError(
            f"{source}: manifest format {found!r} is not one this code reads (it reads formats "
            f"{list(READABLE_FORMATS)}); a newer NeuroAnimator wrote it, or the file is not a manifest"
        )
    try:
        upgraded = _upgrade_1_to_2(data) if found == 1 else data
        return Manifest.model_validate(_with_later_fields(upgraded))
    except (ValidationError, KeyError, TypeError, ValueError) as exc:
        raise ManifestError(f"{source}: not a valid format-{found} manifest: {exc}") from exc


# TrainConfig fields added later, as an artifact written before them was trained: on thesis 4.5's spaced
# examples (``sampling.SAMPLERS``), with no time budget over its phases
BEFORE_LATER_FIELDS = {"sampler": "spaced", "time_budget": None}


def _with_later_fields(data: Mapping[str, Any]) -> Mapping[str, Any]:
    """A manifest's training config with the fields it predates (``BEFORE_LATER_FIELDS``) set as its
    training was, so that it stays a true record rather than taking today's defaults."""
    cfg = data.get("train_config")
    if not isinstance(cfg, Mapping):
        return data
    return {**data, "train_config": {**BEFORE_LATER_FIELDS, **cfg}}


def _upgrade_1_to_2(old: Mapping[str, Any]) -> dict[str, Any]:
    """Format 1 described its one network by ``normalization`` and ``architecture``; format 2 by
    ``emulator`` (networks and their composition). Everything else is unchanged."""
    data = {k: v for k, v in old.items() if k not in ("normalization", "architecture")}
    norm, arch = old["normalization"], old["architecture"]
    groups = [{"name": str(name), "size": int(size)} for name, size in norm["input_groups"]]
    read = {g["name"] for g in groups}
    frame = arch["frame"]
    core = {
        "name": "core",
        "frame": {
            "part": None,
            "translate": frame["translate"],
            "rotate": frame["rotate"],
            "force_pairs": frame.get("force_pairs", []),
        },
        "reads": {
            "state": [g["name"] for g in old["layout"] if g["name"] in read],
            "controls": [c["name"] for c in old["controls"]] if "controls" in read else [],
            "forces": [f["name"] for f in old["forces"]] if "forces" in read else [],
        },
        "writes": [g["name"] for g in old["layout"]],
        "hidden": arch["hidden"],
        "activation": arch["activation"],
        "normalization": {
            "mode": norm["mode"],
            "input_groups": groups,
            "x_mean": norm["x_mean"],
            "x_std": norm["x_std"],
            "y_mean": norm["y_mean"],
            "y_std": norm["y_std"],
        },
        "input_size": arch["input_size"],
        "output_size": arch["output_size"],
        "weights": arch["weights"],
    }
    data["format"] = FORMAT
    data["emulator"] = {"networks": [core], "stages": [["core"]]}
    # format 1 trained in the heading frame, without the linear path or the rollout phase
    data["train_config"] = {**old["train_config"], "frame": "heading", "skip": False, "rollout_steps": 0}
    return data
