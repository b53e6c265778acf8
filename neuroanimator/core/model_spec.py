"""``ModelSpec``: everything about a physical system that its MJCF does not say.

A catalog model and a user's model are both an MJCF file plus a ``ModelSpec``; the spec is plain
data (saved in every artifact's manifest), so a model can be rebuilt from its artifact alone. It
imports neither MuJoCo nor torch, so processes that only read manifests stay light.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from neuroanimator.core.operating_spec import OperatingRecord
from neuroanimator.core.state import StateGroup


class ForceInput(BaseModel):
    """An external-force input of the emulator: one component of ``xfrc_applied`` on one body.

    ``component`` 0-2 are the world force axes x, y, z; 3-5 the world torque axes.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    body: str
    component: int = Field(ge=0, le=5)
    low: float
    high: float


class ControlInfo(BaseModel):
    """What one control means, for people and game clients: the MJCF says it only in numbers.

    A control value ``u`` applies ``gain · u`` of ``unit`` (a force in N, a torque in N·m; for a servo,
    the target angle in rad or position in m); ``sign`` says in words what a positive value does. Every
    field is optional: ``PhysicalModel.control_info`` derives what the spec leaves out from the MJCF's
    actuator (its transmission, gear and gain).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    label: str | None = Field(None, description="a short name in words, e.g. 'main jet'")
    unit: str | None = Field(None, description="unit of what the control applies: N, N·m, rad, m, rad/s, m/s")
    gain: float | None = Field(None, description="what a control value of 1 applies, in unit")
    sign: str | None = Field(None, description="what a positive value does (the sign convention), in words")


class InitialStates(BaseModel):
    """Typical initial states: uniform perturbations of the model's rest state, or of its operating states.

    ``low``/``high`` (S values each, or empty for none) are added to the state built from MuJoCo's
    ``qpos0`` and zero velocity, or, where ``centres`` holds operating states (S values each: a model's
    keyframes), to one of them drawn at random per start. For a model with a free root, ``random_yaw`` turns it about the
    vertical axis uniformly and ``max_tilt`` tilts it about a random horizontal axis (radians).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    low: list[float] = Field(default_factory=list)
    high: list[float] = Field(default_factory=list)
    random_yaw: bool = False
    max_tilt: float = 0.0
    centres: list[list[float]] = Field(default_factory=list, description="operating states; empty: rest")


FRAME_QUANTITIES = ("centre", "axis1", "axis2", "centre_vel", "axis1_rate", "axis2_rate")
"""The frame quantities of a hierarchy's part, 3 world values each, in this order: the global network
predicts them as groups ``<part>.<quantity>``."""


class HierarchyPart(BaseModel):
    """One part of a hierarchical emulator (thesis 4.4): a set of state groups that one network predicts
    in the part's own frame.

    ``points`` are the part's material points, each a position group and a velocity group of 3 world
    values. The part's frame is fixed linear maps of the model's points (any part's): its centre is
    ``centre`` (weights of this part's points, summing to 1), and two axes ``axis1``, ``axis2``
    (weights of any points' positions, by position group, summing to 0) give its orientation by
    Gram-Schmidt. Groups of the part that are not points (e.g. a plate's orientation) are predicted
    as they are. The velocities of the centre and of the axes are the same maps of the velocities.
    ``neighbours`` are points of other parts that this part's network reads (not writes), in its frame:
    the forces on a part depend on what it is attached to, which its own points alone do not say.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    groups: list[str] = Field(min_length=1, description="state groups the part's network writes")
    points: list[tuple[str, str]] = Field(min_length=1, description="(position group, velocity group)")
    centre: list[float] = Field(description="weight of each point in the centre, summing to 1")
    axis1: list[tuple[str, float]] = Field(min_length=1, description="(position group, weight)")
    axis2: list[tuple[str, float]] = Field(min_length=1, description="(position group, weight)")
    neighbours: list[tuple[str, str]] = Field(
        default_factory=list,
        description="other parts' points (position group, velocity group) that this part's network reads, "
        "in this part's frame: what its springs or joints attach to",
    )


class Branch(BaseModel):
    """One branch of an articulated hierarchical emulator (thesis 4.4, Fig. 4.8: the runner's arms and
    legs): state groups, its joints' angles and rates, that one network writes after the trunk network.

    The trunk network writes every group that no branch holds (the root and the joints between the
    branches) and reads the whole state and every control. A branch's network then reads, in the
    root's frame like the trunk's, its own groups, the trunk's groups, the trunk's predicted change,
    the groups in ``reads`` and the controls in ``controls``: a limb moves with what it hangs from
    and with its own motors; what else it depends on (another limb, through the ground) is listed.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    groups: list[str] = Field(min_length=1, description="state groups the branch's network writes")
    reads: list[str] = Field(
        default_factory=list, description="other branches' state groups that this branch's network reads"
    )
    controls: list[str] | None = Field(
        None, description="the controls (actuator names) the branch's network reads; None: all"
    )


class DriverParam(BaseModel):
    """One setting of a model's driver that a client may change while it runs (a target speed)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    label: str = Field(description="what it sets, in words")
    unit: str = ""
    low: float
    high: float
    default: float

    @model_validator(mode="after")
    def _ordered(self) -> DriverParam:
        if not self.low <= self.default <= self.high:
            raise ValueError(f"driver parameter {self.name!r}: need low <= default <= high")
        return self


MOVED_MODULES = {
    "neuroanimator.physics.runner_control": "neuroanimator.catalog.runner.gait",
    "neuroanimator.physics.runner_data": "neuroanimator.catalog.runner.data",
}
"""Modules named in specs (``DriverSpec.factory``, ``ModelSpec.data_source``) that have moved since a
committed artifact was written: an old name is read as the new one, so that artifact loads unchanged."""


def current_module(name: str) -> str:
    """``name`` (``module`` or ``module:function``) with a moved module's current name."""
    module, sep, rest = name.partition(":")
    return MOVED_MODULES.get(module, module) + sep + rest


class DriverSpec(BaseModel):
    """A model's own closed-loop controller, which the emulator service can run for a session (the
    runner's running controller). Each super-step it reads the session's state and sets every control;
    a client sets only its ``params`` (and the force inputs, which stay the client's). ``factory`` is
    ``"module:function"`` in this package, called with the ``PhysicalModel``, the super-step's
    physical steps and the parameters; it returns a ``neuroanimator.sim.driver.Driver``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    description: str = ""
    factory: str = Field(pattern=r"^neuroanimator\.[\w.]+:\w+$")
    params: list[DriverParam] = Field(default_factory=list)

    @field_validator("factory", mode="before")
    @classmethod
    def _moved(cls, v: object) -> object:
        return current_module(v) if isinstance(v, str) else v


class HingeAlignment(BaseModel):
    """A hinged part held in line with two of the regulariser's points, as a plate hung from one node
    and tied to another by springs is: its angle about ``axis`` follows the turn of the line from
    ``anchor`` to ``target`` about that axis since rest (``rest``: that line when the angle is 0).
    ``angle`` and ``rate`` name its state groups (one value each: the hinge's angle and rate)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    angle: str
    rate: str
    anchor: int = Field(ge=0, description="index into the regulariser's points")
    target: int = Field(ge=0, description="index into the regulariser's points")
    axis: tuple[float, float, float] = Field(description="the hinge's axis in world coordinates")
    rest: tuple[float, float, float] = Field(description="target − anchor at angle 0")

    @model_validator(mode="after")
    def _a_line_across_the_axis(self) -> HingeAlignment:
        if abs(math.fsum(a * a for a in self.axis) - 1.0) > 1e-6:
            raise ValueError(f"hinge {self.angle!r}: axis {self.axis} must be a unit vector")
        along = math.fsum(a * r for a, r in zip(self.axis, self.rest, strict=True))
        across = math.fsum((r - along * a) ** 2 for a, r in zip(self.axis, self.rest, strict=True))
        if self.anchor == self.target or across < 1e-18:
            raise ValueError(f"hinge {self.angle!r}: its anchor and target must span a line across its axis")
        return self


class SpringRegularizer(BaseModel):
    """The regulariser of thesis 6.1.3 for a mass-spring model: after each emulated super-step, ``steps``
    explicit Euler steps of the spring forces between the model's points,

        v ← v + dt·f(x, v)/m,   x ← x + dt·v,

    pull an accumulating deformation back. f is, per spring, −(stiffness·(l − l_r) + damping·l̇) along
    it; a muscle's rest length moves with its control, l_r = rest + u·(contracted − rest). Softer and
    more damped than the simulation's springs (explicit Euler is stable only so), and internal forces
    only: the body's momentum is untouched.

    ``points`` are (position group, velocity group) pairs of 3 world values, ``masses`` theirs;
    ``springs`` (a, b, rest length) index ``points``; ``muscles`` (spring, control, contracted length).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    steps: int = Field(5, ge=0, description="Euler steps after each super-step (0: off)")
    dt: float = Field(gt=0, description="seconds per Euler step")
    stiffness: float = Field(gt=0, description="N/m, every spring")
    damping: float = Field(ge=0, description="N·s/m along every spring")
    points: list[tuple[str, str]] = Field(min_length=2, description="(position group, velocity group)")
    masses: list[float] = Field(description="kg, one per point")
    springs: list[tuple[int, int, float]] = Field(min_length=1, description="(point a, point b, rest length)")
    muscles: list[tuple[int, int, float]] = Field(
        default_factory=list, description="(spring, control, rest length at control 1)"
    )
    hinges: list[HingeAlignment] = Field(
        default_factory=list, description="hinged parts that follow the line between two points"
    )
    hinge_pull: float = Field(
        0.0, ge=0, le=1, description="share of each hinge's misalignment removed after each super-step"
    )

    @model_validator(mode="after")
    def _indices_agree(self) -> SpringRegularizer:
        n = len(self.points)
        if len(self.masses) != n or any(m <= 0 for m in self.masses):
            raise ValueError(f"masses: {len(self.points)} positive values expected, got {self.masses}")
        for a, b, rest in self.springs:
            if not (0 <= a < n and 0 <= b < n) or a == b or rest <= 0:
                raise ValueError(
                    f"spring ({a}, {b}, {rest}): two different points below {n} and a rest length > 0"
                )
        for spring, control, contracted in self.muscles:
            if not 0 <= spring < len(self.springs) or control < 0 or contracted <= 0:
                raise ValueError(f"muscle ({spring}, {control}, {contracted}): no such spring or control")
        for hinge in self.hinges:
            if hinge.anchor >= n or hinge.target >= n:
                raise ValueError(
                    f"hinge {hinge.angle!r}: points {hinge.anchor}, {hinge.target} not below {n}"
                )
        return self


class TravellingWaves(BaseModel):
    """Typical controls of a rhythmic gait, for a share of the sampler's runs (thesis 4.5: training data
    under the controls the model will be driven with). A swimmer moves by waves of contraction whose
    antagonists alternate; independent random controls rarely line up so, and an emulator trained on
    them alone underrates the strokes a controller then finds. Control k of a wave run is

        centre_k + amplitude·half_range_k·sin(2π·t/period − phase_k − lag·rank_k + φ₀),

    with period, lag, amplitude and φ₀ drawn per run from their ranges, then blended with the run's
    random smooth controls: (1 − blend)·wave + blend·random, clipped to the range.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    fraction: float = Field(gt=0, le=1, description="share of the runs under waves")
    period_s: tuple[float, float] = Field(description="range of the wave's period, seconds")
    lag: tuple[float, float] = Field(description="range of the phase lag between consecutive ranks, radians")
    amplitude: tuple[float, float] = Field(description="range of the amplitude, in half control ranges")
    phase: list[float] = Field(
        min_length=1, description="per control, its phase offset (antagonists π apart)"
    )
    rank: list[int] = Field(
        min_length=1, description="per control, its place along the wave (lags behind rank 0)"
    )
    blend: float = Field(0.0, ge=0, lt=1, description="weight of the run's random smooth controls")

    @model_validator(mode="after")
    def _ranges(self) -> TravellingWaves:
        if len(self.phase) != len(self.rank):
            raise ValueError(f"phase and rank: one per control, got {len(self.phase)} and {len(self.rank)}")
        for name in ("period_s", "lag", "amplitude"):
            low, high = getattr(self, name)
            if low > high:
                raise ValueError(f"{name}: low {low} above high {high}")
        if self.period_s[0] <= 0 or self.amplitude[0] < 0 or self.amplitude[1] > 1:
            raise ValueError("period_s must be positive and amplitude within [0, 1] half ranges")
        return self


class ModelSpec(BaseModel):
    """What the trainer needs beyond the MJCF to build an emulator of a model."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    description: str = ""
    substeps: int = Field(50, ge=1, description="default super timestep n (Δt = n·δt)")
    layout: list[StateGroup] | None = Field(
        None, description="explicit state groups; None derives them from the MJCF's joints"
    )
    control_low: list[float] | None = Field(
        None, description="useful control range; None: actuator ctrlrange"
    )
    control_high: list[float] | None = None
    control_info: dict[str, ControlInfo] = Field(
        default_factory=dict,
        description="per control (actuator name): what it means, where the MJCF's numbers do not say it",
    )
    control_spacing_s: float = Field(
        1.0, gt=0, description="seconds between control points of typical controls"
    )
    travelling_waves: TravellingWaves | None = Field(
        None, description="a share of the typical controls as waves of a rhythmic gait (a swimmer's strokes)"
    )
    forces: list[ForceInput] = Field(default_factory=list)
    force_spacing_s: float = Field(1.0, gt=0)
    initial: InitialStates = Field(default_factory=InitialStates)
    episode_s: float = Field(60.0, gt=0, description="training runs restart from a typical state this often")
    passive_actuator_group: int = Field(
        3, description="actuators in this MJCF group model passive forces (friction, drag), not controls"
    )
    rotation_invariant: bool = Field(True, description="use the rotation about gravity as a symmetry")
    translation_invariant: bool = Field(True, description="use translations of the root as a symmetry")
    thesis_hidden: int | None = Field(None, description="hidden units of the thesis' network (Table 6.1)")
    parts: list[HierarchyPart] = Field(
        default_factory=list,
        description="a hierarchical emulator's parts (thesis 4.4): a global network predicts the motion of "
        "their frames, then one network per part its groups in its frame; empty: one network",
    )
    branches: list[Branch] = Field(
        default_factory=list,
        description="an articulated hierarchy's branches (thesis 4.4, the runner): a trunk network writes the "
        "groups no branch holds, then one network per branch its groups; empty: one network",
    )
    data_source: str | None = Field(
        None,
        description="a module whose functions examples and sequences generate the training transitions "
        "and rollout windows, called like neuroanimator.sim.sampling.generate and generate_sequences (a model "
        "whose motion comes from a controller); None: the sampler's, under typical controls",
    )
    driver: DriverSpec | None = Field(
        None,
        description="the model's own controller, which the emulator service runs for a session that asks "
        "for it (a model whose controls come from a controller: the runner's joint targets)",
    )

    @field_validator("data_source", mode="before")
    @classmethod
    def _moved_source(cls, v: object) -> object:
        return current_module(v) if isinstance(v, str) else v

    operating: OperatingRecord | None = Field(
        None,
        description="the operating point a model of one's own was trained around (its keyframes, the "
        "controls that hold it still, the user's operating spec): typical controls are drawn around its "
        "centres; None: over the control range",
    )
    regularizer: SpringRegularizer | None = Field(
        None, description="a mass-spring model's regulariser (thesis 6.1.3), on by default in its emulators"
    )
    train_at_start: bool = Field(
        True,
        description="the stack trains this model's emulator at start when none is stored; off for a model "
        "whose training takes long (it is then served once trained)",
    )
