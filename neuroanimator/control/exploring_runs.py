"""MuJoCo runs from a task's own starts under random controls, for the emulator to be fine-tuned on
before a reward policy is learned through it.

An emulator is trained on its model's typical motion, drawn the same way for every model; a task's
reward can lie where that motion hardly goes. The ball in the cup is the case measured: the ball
resting in the cup while the cup moves is a contact state the generic runs seldom reach, and the
emulator trained on them let the ball fall out of a cup MuJoCo kept it in (with the cup pushed at
random, inside the cup after 1.6 s on MuJoCo 77 % of the time, on the emulator 0 %; of the steps
MuJoCo spent with the ball inside under random controls from the task's starts, the emulator agreed
on 1 %), and a value fitted through it earned 99 of 1,000 on MuJoCo. Runs from the task's starts
under random controls reach the catch by chance (5-10 % of their steps): after the emulator was
fine-tuned on 2,048 of them (28 s of MuJoCo, 240 s of fine-tuning) it kept the ball 86 % of the
time and agreed on 54 % of those steps, and the value fitted through it earned 939; on 4,096 (360 s),
950 (measured, docs/experiments). As MBPO and Dreamer begin from a random policy's data, the first
data here is a random policy's, where the task begins.

Each control is drawn anew every ``hold`` super-steps: half the time at the ends or the middle of
its range (where bang-bang control lies), half uniform over it.

Shapes: N runs, K super-steps, S state, U controls.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from neuroanimator.sim.model import PhysicalModel

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ExploringRuns:
    """How many random runs are made from the task's starts before learning, how long, and how long
    the emulator is fine-tuned on them (module doc). ``runs`` 0: none."""

    runs: int = 0
    steps: int = 250  # super-steps a run
    hold: int = 3  # super-steps each random control is held
    seconds: float = 240.0  # of fine-tuning the emulator on them

    def __post_init__(self) -> None:
        if self.runs < 0 or self.steps < 1 or self.hold < 1 or self.seconds < 0:
            raise ValueError(
                "exploring runs are a count ≥ 0 of runs of ≥ 1 super-step, each control held ≥ 1 "
                "super-step, fine-tuned on for ≥ 0 seconds"
            )


def random_controls(low: FloatArray, high: FloatArray, n: int, rng: np.random.Generator) -> FloatArray:
    """(n, U) controls: half at the low end, the middle or the high end of each control's range,
    half uniform over it."""
    ends = np.stack([low, (low + high) / 2, high])  # (3, U)
    pick = ends[rng.integers(3, size=(n, len(low))), np.arange(len(low))]
    uniform = rng.uniform(low, high, (n, len(low)))
    return np.where(rng.random((n, 1)) < 0.5, uniform, pick)


def random_runs(
    physical: PhysicalModel,
    starts: FloatArray,
    substeps: int,
    low: FloatArray,
    high: FloatArray,
    how: ExploringRuns,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """Runs on MuJoCo from ``starts`` (N, S), ``substeps`` physical steps a super-step, the controls
    random (``random_controls``) and each held ``how.hold`` super-steps: states (N, K+1, S) and
    controls (N, K, U)."""
    n, k = len(starts), how.steps
    states = np.zeros((n, k + 1, starts.shape[1]))
    controls = np.zeros((n, k, len(low)))
    states[:, 0] = s = np.asarray(starts, dtype=np.float64)
    u = random_controls(low, high, n, rng)
    for i in range(k):
        if i and i % how.hold == 0:
            u = random_controls(low, high, n, rng)
        s = physical.step_held(s, u, None, substeps)
        states[:, i + 1], controls[:, i] = s, u
    return states, controls
