"""The thesis' control-synthesis tasks (section 6.2) as plain data: numpy only, no torch.

Every task is 20 s long: 40 super-steps of the n = 50 emulator (Δt = 0.5 s), with one control
point every two super-steps, i.e. 20 points per control: 60 variables for the pendulum, 80 for the
lander and 40 for the truck, as in the thesis. Each states its success criterion as checks on the
final state (``criteria.py``); the same checks are evaluated on the emulated trajectory and on the
MuJoCo replay, and their text is part of the task's description.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from neuroanimator.control import criteria

HORIZON = 40  # super-steps: 20 s of the n = 50 emulator
SUBSTEPS = 50
POINTS_PER_STEP = 0.5  # one control point every two super-steps: 20 points per control

# Labels of the catalog models' states (StateLayout.labels()), written out so this module needs
# neither MuJoCo nor a manifest to be imported.
PENDULUM_LABELS = ("angles.j0", "angles.j1", "angles.j2", "rates.j0", "rates.j1", "rates.j2")
LANDER_LABELS = (
    "position.x",
    "position.y",
    "position.z",
    "orientation.w",
    "orientation.x",
    "orientation.y",
    "orientation.z",
    "velocity.x",
    "velocity.y",
    "velocity.z",
    "angular_velocity.x",
    "angular_velocity.y",
    "angular_velocity.z",
)
TRUCK_LABELS = ("position.x", "position.y", "heading", "velocity.x", "velocity.y", "yaw_rate")


@dataclass(frozen=True)
class Task:
    """A control-synthesis problem: a model, where it starts, where it must end, and how to judge it.

    States are in the model's layout order (``labels``). ``success`` holds the criterion's checks;
    ``optimizer`` the defaults of the momentum update (eqs. 5.5-5.6).
    """

    name: str
    model: str
    summary: str
    labels: tuple[str, ...]
    initial_state: tuple[float, ...]
    target_state: tuple[float, ...]
    state_weights: tuple[float, ...]
    success: tuple[dict[str, Any], ...]
    initial_controls: tuple[float, ...]
    mu_u: float
    mu_s: float
    terms: tuple[dict[str, Any], ...] = ()
    optimizer: dict[str, Any] = field(default_factory=dict)
    horizon: int = HORIZON
    substeps: int = SUBSTEPS
    points_per_step: float = POINTS_PER_STEP

    @property
    def success_text(self) -> str:
        return criteria.describe(list(self.success), self.target_state, self.labels)

    @property
    def description(self) -> str:
        return f"{self.summary} Success {self.success_text}."

    def control_variables(self, num_controls: int) -> int:
        return num_points(self.horizon, self.points_per_step) * num_controls

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able data, for ``GET /tasks``."""
        return {
            "name": self.name,
            "model": self.model,
            "description": self.description,
            "success_criterion": self.success_text,
            "success": [dict(c) for c in self.success],
            "horizon": self.horizon,
            "substeps": self.substeps,
            "points_per_step": self.points_per_step,
            "state_labels": list(self.labels),
            "initial_state": list(self.initial_state),
            "target_state": list(self.target_state),
            "state_weights": list(self.state_weights),
            "initial_controls": list(self.initial_controls),
            "mu_u": self.mu_u,
            "mu_s": self.mu_s,
            "terms": [dict(t) for t in self.terms],
            "optimizer": dict(self.optimizer),
        }


def num_points(horizon: int, points_per_step: float) -> int:
    """Control points per control for a horizon of super-steps: round(horizon · points_per_step), >= 1."""
    return max(1, round(horizon * points_per_step))


# --------------------------------------------------------------------------- pendulum-swing
# From hanging at rest, end 20 s later at a pose well to the side, at zero velocity. Holding the
# pose would need a torque of about 9.8·(0.25 + 0.75 + 1.25)·sin(θ) ≈ 18 N·m at the base; the
# motors give at most 2, so the pendulum must pump energy by swinging back and forth and arrive at
# the top of a swing (the thesis' Fig. 6.8 problem).
PENDULUM_SWING = Task(
    name="pendulum-swing",
    model="pendulum-active",
    summary=(
        "Three-link pendulum (pendulum-active, torque limit 2 N·m per joint): from hanging at rest, "
        "end at the target pose with zero velocity after 20 s. The torque is far too low to lift the "
        "links there directly, so the controller must swing back and forth to gain momentum."
    ),
    labels=PENDULUM_LABELS,
    initial_state=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    target_state=(1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 1.0, 1.0, 1.0, 1.0),
    success=(
        {"check": "angle", "variables": list(PENDULUM_LABELS[:3]), "max": 0.1},
        {"check": "abs", "variables": list(PENDULUM_LABELS[3:]), "max": 0.1},
    ),
    initial_controls=(0.0, 0.0, 0.0),
    mu_u=1e-4,
    mu_s=1.0,
    optimizer={"learning_rate": 2.0, "momentum": 0.5, "max_iterations": 100, "tolerance": 1e-6},
)

# --------------------------------------------------------------------------- lander-landing
# Descend from 25 m up and 12 m off to the side, drifting, to a soft landing on the pad at the
# origin: upright, on the spot, barely moving down. The attitude jets are weak (0.05 rad/s² at
# most), so the lander must plan its tilt early to move sideways with the main jet.
LANDER_LANDING = Task(
    name="lander-landing",
    model="lander",
    summary=(
        "Lunar lander: from 25 m above and 12 m beside the pad, drifting, land softly on the pad "
        "(the origin) in 20 s: upright, on the spot, with a small downward speed. Sideways motion "
        "needs tilting the main jet with weak attitude jets."
    ),
    labels=LANDER_LABELS,
    initial_state=(-10.0, 6.0, 25.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.0, -1.0, 0.0, 0.0, 0.0),
    target_state=(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.5, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 1.0, 10.0, 10.0, 10.0, 10.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0),
    success=(
        {"check": "distance", "variables": list(LANDER_LABELS[:3]), "max": 1.0},
        {"check": "orientation", "variables": list(LANDER_LABELS[3:7]), "max": math.radians(10.0)},
        {"check": "range", "variables": ["velocity.z"], "min": -1.0, "max": 0.0},
        {"check": "norm", "variables": ["velocity.x", "velocity.y"], "max": 0.5},
    ),
    initial_controls=(16.2, 0.0, 0.0, 0.0),  # hover thrust, no attitude jets
    mu_u=1e-4,
    mu_s=1.0,
    optimizer={"learning_rate": 1.5, "momentum": 0.5, "max_iterations": 100, "tolerance": 1e-6},
)

# --------------------------------------------------------------------------- truck-parking
TRUCK_PARKING = Task(
    name="truck-parking",
    model="truck",
    summary=(
        "Truck: from rest at the origin facing +x, park 20 m ahead and 10 m to the left, facing +y, "
        "and stop there within 20 s."
    ),
    labels=TRUCK_LABELS,
    initial_state=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    target_state=(20.0, 10.0, math.pi / 2, 0.0, 0.0, 0.0),
    state_weights=(1.0, 1.0, 10.0, 10.0, 10.0, 10.0),
    success=(
        {"check": "distance", "variables": ["position.x", "position.y"], "max": 1.0},
        {"check": "angle", "variables": ["heading"], "max": math.radians(10.0)},
        {"check": "norm", "variables": ["velocity.x", "velocity.y"], "max": 0.3},
    ),
    initial_controls=(0.0, 0.0),
    mu_u=1e-4,
    mu_s=1.0,
    optimizer={"learning_rate": 1.5, "momentum": 0.5, "max_iterations": 100, "tolerance": 1e-6},
)

TASKS: dict[str, Task] = {t.name: t for t in (PENDULUM_SWING, LANDER_LANDING, TRUCK_PARKING)}
