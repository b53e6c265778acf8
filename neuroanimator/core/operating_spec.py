"""The operating spec: the typical motion a user declares for a model of their own, and the operating
point the trainer settled on.

A drone hovers, an arm holds a pose against gravity: their useful motion is a narrow band around an
operating point, not every control anywhere in its ``ctrlrange``. The trainer finds that point in the
model (``sim.operating``); ``OperatingSpec`` lets the user say more, as a small JSON file::

    {
      "version": 1,
      "keyframe": "hover",
      "controls": {"thrust1": {"centre": 3.25, "spread": 1.0}, "thrust2": {"range": [2, 5]}},
      "control_spread": 0.1,
      "start": {"joints": {"hinge": 0.2}, "position_spread": 0.3, "velocity_spread": 0.3,
                "tilt": 0.3, "speed": 0.5},
      "held_share": 0.2,
      "time_scale_s": 1.0,
      "run_s": 5.0
    }

Every field is optional. ``OperatingRecord`` is what the trainer used, in the model's spec (and so in
the artifact's manifest, and in the emulator service's envelope): where it came from, why, the
controls' centres and spread, and whether it was narrowed because the wider motion diverged.

Plain data: no MuJoCo here. ``sim.operating.apply`` checks a spec against a model (actuator and joint
names, ``ctrlrange``, keyframe names) and turns it into the model's typical starts and controls.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

SPEC_VERSION: Literal[1] = 1


class ControlBand(BaseModel):
    """The typical values of one control: a ``centre`` and a half-width ``spread`` (either may be left
    to the operating point found), or a ``range`` [low, high], not both."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    centre: float | None = Field(None, description="the control's typical value, in its own units")
    spread: float | None = Field(None, ge=0, description="half-width around the centre, in its own units")
    range: tuple[float, float] | None = Field(None, description="[low, high], instead of centre and spread")

    @model_validator(mode="after")
    def _one_way(self) -> ControlBand:
        if self.range is not None:
            if self.centre is not None or self.spread is not None:
                raise ValueError("give either range or centre/spread, not both")
            if self.range[0] > self.range[1]:
                raise ValueError(f"range {list(self.range)}: low above high")
        return self


class StartSpread(BaseModel):
    """How typical runs start around the operating state: a spread (half-width, uniform) per joint by
    name, else ``position_spread`` on every joint's position (rad or m) and ``velocity_spread`` on every
    velocity; a free root's ``tilt`` (rad, a random horizontal axis) and linear ``speed`` (m/s)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    joints: dict[str, float] = Field(default_factory=dict, description="joint name -> position spread")
    position_spread: float | None = Field(None, ge=0)
    velocity_spread: float | None = Field(None, ge=0)
    tilt: float | None = Field(None, ge=0, le=3.1416, description="a free root's largest tilt, rad")
    speed: float | None = Field(None, ge=0, description="a free root's linear velocity spread, m/s")


class OperatingSpec(BaseModel):
    """Typical motion as the user declares it (see the module doc). ``control_spread`` is the half-width
    of every control not in ``controls``, as a share of its ``ctrlrange`` (0..1); ``time_scale_s`` the
    seconds between the smooth controls' points; ``run_s`` how long a training run goes before it
    restarts from a typical start; ``held_share`` the share of runs whose controls stay at their centres
    (what holds the model still: an emulator of a hovering drone must hover), and, drawn apart, the share
    that start exactly at an operating state."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    version: Literal[1] = SPEC_VERSION
    keyframe: str | None = Field(None, description="the keyframe to operate around; None: every keyframe")
    controls: dict[str, ControlBand] = Field(default_factory=dict, description="actuator name -> band")
    control_spread: float | None = Field(None, gt=0, le=1, description="share of ctrlrange, half-width")
    start: StartSpread = Field(default_factory=StartSpread)
    held_share: float | None = Field(
        None,
        ge=0,
        le=1,
        description="share of runs whose controls stay at their centres (holding still), and apart, of runs that "
        "start at an operating state",
    )
    time_scale_s: float | None = Field(None, gt=0, description="seconds between control points")
    run_s: float | None = Field(None, gt=0, description="seconds a training run goes on")


OperatingSource = Literal["keyframe", "hold", "spec", "none"]


class OperatingRecord(BaseModel):
    """The operating point a model was trained around, and how it was found: ``source`` (its keyframes,
    the controls that hold it still, the user's spec alone, or none: controls over their ranges),
    ``reason`` in words, the keyframes used, the controls' centres (one row per keyframe, U values) and
    half-widths (U), what the divergence check narrowed (``narrowed``), a spin-up seen in typical motion
    (``spin_up``), and the user's spec as given."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    source: OperatingSource
    reason: str
    keyframes: list[str] = Field(default_factory=list)
    control_centres: list[list[float]] = Field(default_factory=list)
    control_spread: list[float] = Field(default_factory=list)
    held_share: float = Field(0.0, ge=0, le=1, description="share of runs with the controls at their centres")
    narrowed: str | None = None
    spin_up: str | None = None
    spec: OperatingSpec | None = None

    def describe(self) -> str:
        """One line for a log, a training's status and the CLI."""
        extra = "".join(f"; {x}" for x in (self.narrowed, self.spin_up) if x)
        return f"operating point from {self.source}: {self.reason}{extra}"
