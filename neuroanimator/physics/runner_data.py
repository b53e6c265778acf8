"""The runner's training data: its running motion and the neighbourhood of it (thesis 4.4, 6.1).

The thesis trained its runner emulator on one 30 s run, and it reproduced only that run. Here the
transitions come from many closed-loop runs (``runner_control.run``, the controller reading what it
can read from a state, ``KinematicSensors``), each a sample of the dynamics near running:

- target speeds drawn from ``TRAIN_SPEEDS`` (a few distinct speeds, so that a speed between two of them
  is one the data did not contain);
- Gaussian noise on every servo target each control period, of a standard deviation drawn per run up
  to ``MAX_NOISE`` radians (perturbed controls);
- a push of the torso in a random horizontal direction for ``PUSH_S`` seconds at a random time, of a
  force drawn up to ``MAX_PUSH`` newtons, in half of the runs.

The controller acts every super-step: the emulator's controls are the servo targets, held over its
super-step, and its force inputs the push. Transitions after a run fell (pelvis below 0.55 m, and the
half second before) are dropped: lying on the floor is not the neighbourhood of running.

Shapes: N examples, S = 71 state, U = 29 controls, F = 2 forces.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from neuroanimator.physics import runner_control as rc
from neuroanimator.physics.model import PhysicalModel
from neuroanimator.sampling import Examples

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]

TRAIN_SPEEDS = (1.8, 2.2, 2.6)  # m/s; 2.0 and 2.4 lie between them
MAX_NOISE = 0.08  # radians on the servo targets
MAX_PUSH = 150.0  # newtons on the torso
PUSH_S = 0.2
RUN_S = 10.0  # seconds per run
BATCH = 32  # runs stepped together
FALL_MARGIN_S = 0.5


def _batch(model: PhysicalModel, substeps: int, rng: np.random.Generator) -> tuple[FloatArray, ...]:
    """One batch of closed-loop runs -> states (N, S), controls (N, U), forces (N, F), next states (N, S)."""
    m = model.mj_model
    speeds = rng.choice(TRAIN_SPEEDS, BATCH)
    starts = np.stack([rc.running_start(m, float(v)) for v in speeds])
    noise = rng.uniform(0.0, MAX_NOISE)  # one level per batch: run() draws the noise itself
    angle = rng.uniform(0.0, 2 * np.pi, BATCH)
    size = rng.uniform(0.0, MAX_PUSH, BATCH) * (rng.random(BATCH) < 0.5)
    force = np.stack([size * np.cos(angle), size * np.sin(angle), np.zeros(BATCH)], axis=1)
    push = rc.Push(force=force, start_s=float(rng.uniform(1.0, RUN_S - 1.0)), duration_s=PUSH_S)
    res = rc.run(
        m,
        starts,
        speeds,
        RUN_S,
        control_every=substeps,
        push=push,
        kinematic=True,
        control_noise=noise,
        seed=int(rng.integers(2**31)),
    )
    states = model.from_physics(res.states)  # (R, T, S)
    t = np.arange(states.shape[1]) * res.dt
    keep = (t[:-1] + res.dt)[None, :] < (res.fell_at[:, None] - FALL_MARGIN_S)
    pushing = (t >= push.start_s) & (t < push.start_s + push.duration_s)
    forces = np.where(pushing[None, :, None], force[:, None, :2], 0.0)  # (R, T, 2)
    return (
        states[:, :-1][keep],
        res.controls[:, :-1][keep],
        forces[:, :-1][keep],
        states[:, 1:][keep],
    )


def examples(
    model: PhysicalModel, substeps: int, count: int, seed: int, *, progress: bool = True
) -> Examples:
    """``count`` shuffled transitions of ``substeps`` physical steps from closed-loop runs (see the
    module docstring); the controller acts every ``substeps`` steps."""
    if count < 1:
        raise ValueError(f"count must be positive, got {count}")
    rng = np.random.default_rng(seed)
    parts: list[tuple[FloatArray, ...]] = []
    have = 0
    with tqdm(total=count, desc=f"running {model.name} n={substeps}", unit="ex", disable=not progress) as bar:
        while have < count:
            part = _batch(model, substeps, rng)
            parts.append(part)
            have += len(part[0])
            bar.update(min(len(part[0]), count - bar.n))
    s, u, f, n = (np.concatenate([p[i] for p in parts]) for i in range(4))
    order = rng.permutation(len(s))[:count]
    log.info("%s: %d transitions from %d runs", model.name, len(s), BATCH * len(parts))
    return Examples(s[order], u[order], f[order], n[order])
