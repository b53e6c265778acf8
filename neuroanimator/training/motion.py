"""How fast typical motion turns, and whether it spins up: what bounds the super-step of a free body.

A quadrotor driven by thrusts drawn independently around its hover tumbles: the differential thrust
is a random torque, and its angular speed grows over a run until drag balances it (Menagerie's Skydio
X2 at ±10 % of its thrust range: a 90th percentile of 6.4 rad/s at 0.5 s, 11.5 at 1 s, 15-17 from 2 s
on). A body that turns more than half a turn within one super-step cannot be emulated at it: its
orientation after the step aliases (a turn by θ and by θ − 2π leave the same quaternion, and the
network sees neither the path nor the count of turns). So the chooser keeps only super-steps within which
the typical body turns at most ``MAX_TURN``. A body whose speed grows far beyond its start's spins up:
that is reported, and the runs are cut short (they restart from a typical start before they tumble).

Only bodies that turn in 3-D (a free root, a ball joint) are bounded: a hinge's angle is one number,
which networks follow through many turns (dm_control's cartpole swings its pole at over 10 rad/s and is
emulated at n = 50 to 0.0006).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray

from neuroanimator.sim.model import PhysicalModel

MAX_TURN = 2 * math.pi
"""The most the typical body may turn within one super-step, rad: a full turn aliases (a turn by θ and
by θ − 2π leave the same quaternion). Measured on Menagerie's X2 tumbling under thrusts of ±10 % of
their range: a median of 10 rad/s (5 rad per super-step of 0.5 s), a 99th percentile of 26, and
emulated at n = 50 to a one-step error of 0.0046; so the median, not the fastest run, is bounded."""
SPIN_GROWTH = 5.0
"""A turning body whose 90th-percentile angular speed grows to this many times its start's spins up."""
SPIN_FLOOR = 0.2
"""rad/s: starts slower than this count as this fast (a start at rest would make any motion a spin-up)."""
MIN_RUN_SUPER_STEPS = 4
"""A run cut for spin-up keeps at least this many of the shortest super-steps."""


@dataclass(frozen=True)
class FastestMotion:
    """How fast typical motion turns: at times since the run's start (``times``, s), the median and
    the 90th percentile over the runs of the angular speed of the group that turns fastest
    (``group``; rad/s)."""

    times: NDArray[np.float64]
    median: NDArray[np.float64]
    p90: NDArray[np.float64]
    group: str | None

    @property
    def speed(self) -> float:
        """rad/s: the highest median angular speed over a run (0 for a model with no free body)."""
        return float(self.median.max()) if self.median.size else 0.0

    def allows(self, seconds: float) -> bool:
        """Whether the typical body turns at most ``MAX_TURN`` within a super-step of ``seconds``."""
        return self.speed * seconds <= MAX_TURN

    def spin_up(self) -> tuple[float, str] | None:
        """(seconds into a run at which the speed reached ``SPIN_GROWTH`` times the start's, in words)
        when typical motion spins the body up; None when it does not."""
        if self.group is None:
            return None
        start = max(float(self.p90[0]), SPIN_FLOOR)
        over = np.flatnonzero(self.p90 > SPIN_GROWTH * start)
        if not over.size:
            return None
        at = float(self.times[over[0]])
        top = int(np.argmax(self.p90))
        rate = (float(self.p90[top]) - start) / max(float(self.times[top]), 1e-9)
        return at, (
            f"{self.group} spins up: its 90th-percentile angular speed grows from {start:.3g} rad/s at the start "
            f"to {float(self.p90[top]):.3g} rad/s by {float(self.times[top]):.3g} s (about {rate:.3g} rad/s per s)"
        )


def _turning_groups(model: PhysicalModel) -> list[tuple[str, slice]]:
    """The angular velocity groups of bodies that turn in 3-D: a free joint's and a ball joint's."""
    m = model.mj_model
    out = []
    for j in range(m.njnt):
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            address = int(m.jnt_dofadr[j]) + 3
        elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            address = int(m.jnt_dofadr[j])
        else:
            continue
        for g, sl in model.layout.group_slices():
            if g.source == "qvel" and g.address == address and g.size == 3:
                out.append((g.name, sl))
    return out


def fastest_motion(
    model: PhysicalModel, *, runs: int = 32, seed: int = 0, every_s: float = 0.05
) -> FastestMotion:
    """Simulate ``runs`` typical runs of the model's run length (``spec.episode_s``, at most 20 s) and
    measure their turning (see ``FastestMotion``)."""
    groups = _turning_groups(model)
    if not groups:
        return FastestMotion(np.zeros(0), np.zeros(0), np.zeros(0), None)
    steps = max(2, round(min(model.spec.episode_s, 20.0) / model.dt))
    times = np.arange(steps, dtype=np.float64) * model.dt
    traj = model.simulate(*model.typical_runs(np.random.default_rng(seed), runs, steps))  # (R, T, S)
    at = np.arange(0, steps, max(1, round(every_s / model.dt)))
    speed = np.stack([np.linalg.norm(traj[:, at, sl], axis=2) for _, sl in groups])  # (G, R, K)
    fastest = int(np.argmax(np.median(speed, axis=1).max(axis=1)))
    return FastestMotion(
        times[at],
        np.median(speed[fastest], axis=0),
        np.percentile(speed[fastest], 90, axis=0),
        groups[fastest][0],
    )


def cut_spin_up(model: PhysicalModel, motion: FastestMotion, shortest: int) -> str | None:
    """Where typical motion spins a body up (``FastestMotion.spin_up``) away from an operating point (its
    keyframes, the controls that hold it still), cut the model's runs (``spec.episode_s``) to when it
    has, but to no fewer than ``MIN_RUN_SUPER_STEPS`` super-steps of ``shortest`` physical steps: its runs
    restart near the point before they tumble. A model without one (a ball pushed about its floor, rolling
    ever faster: 0.4 → 127 rad/s over 20 s) keeps its runs; the spin-up is said. What was seen and done,
    or None."""
    seen = motion.spin_up()
    if seen is None:
        return None
    at, said = seen
    if not model.spec.initial.centres:  # no operating point to restart near: a ball rolling ever faster
        return said
    run = max(at, MIN_RUN_SUPER_STEPS * shortest * model.dt)
    if run >= model.spec.episode_s:
        return said
    model.spec = model.spec.model_copy(update={"episode_s": run})
    return f"{said}; runs cut to {run:.3g} s"


def bound_super_steps(
    model: PhysicalModel, candidates: tuple[int, ...], motion: FastestMotion
) -> tuple[tuple[int, ...], str | None]:
    """The candidates (super-steps in physical steps, longest first) within which the typical body turns
    at most ``MAX_TURN``, and why others were left out (None when none was); the shortest stays."""
    if motion.group is None:
        return candidates, None
    allowed = tuple(n for n in candidates if motion.allows(n * model.dt)) or candidates[-1:]
    if allowed == candidates:
        return candidates, None
    left = [n for n in candidates if n not in allowed]
    return allowed, (
        f"n={', '.join(map(str, left))} left out: {motion.group} turns at a median of up to {motion.speed:.3g} "
        "rad/s, a full turn or more within such a super-step"
    )
