"""The thesis' control-synthesis tasks (section 6.2) as plain data: numpy only, no torch.

Every task is 20 s long: 40 super-steps of the n = 50 emulator (Δt = 0.5 s), with one control
point every two super-steps, i.e. 20 points per control: 60 variables for the pendulum, 80 for the
lander and 40 for the truck, as in the thesis. Each states its success criterion as checks on the
final state (``criteria.py``); the same checks are evaluated on the emulated trajectory and on the
MuJoCo replay, and their text is part of the task's description.
"""

from __future__ import annotations

import math

from neuroanimator.control.criteria import SuccessCheck
from neuroanimator.control.spec import Task

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
        SuccessCheck(check="angle", variables=list(PENDULUM_LABELS[:3]), max=0.1),
        SuccessCheck(check="abs", variables=list(PENDULUM_LABELS[3:]), max=0.1),
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
        SuccessCheck(check="distance", variables=list(LANDER_LABELS[:3]), max=1.0),
        SuccessCheck(check="orientation", variables=list(LANDER_LABELS[3:7]), max=math.radians(10.0)),
        SuccessCheck(check="range", variables=["velocity.z"], min=-1.0, max=0.0),
        SuccessCheck(check="norm", variables=["velocity.x", "velocity.y"], max=0.5),
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
        SuccessCheck(check="distance", variables=["position.x", "position.y"], max=1.0),
        SuccessCheck(check="angle", variables=["heading"], max=math.radians(10.0)),
        SuccessCheck(check="norm", variables=["velocity.x", "velocity.y"], max=0.3),
    ),
    initial_controls=(0.0, 0.0),
    mu_u=1e-4,
    mu_s=1.0,
    optimizer={"learning_rate": 1.5, "momentum": 0.5, "max_iterations": 100, "tolerance": 1e-6},
)

TASKS: dict[str, Task] = {t.name: t for t in (PENDULUM_SWING, LANDER_LANDING, TRUCK_PARKING)}
