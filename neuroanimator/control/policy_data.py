"""Starts and goals of a policy task, drawn with MuJoCo (no torch).

Goals are what MuJoCo itself reaches: the goal variables of states of the model's typical motion
(its own sampler of smooth controls, as its emulator was trained on) started from the task's starts,
kept where they fall inside the goal's box (and, for ``at_rest`` goals, where every speed is small).
So every goal is reachable, and lies where the emulator was trained.

Shapes: B batch, S state, G goal variables.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core import quaternion as quat
from neuroanimator.goals.policy_task import PolicyTask
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.sim.operating import hold_controls

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]


class GoalsUnreachable(ValueError):
    """The model's typical motion never reaches the task's goal box."""


def sample_starts(model: PhysicalModel, task: PolicyTask, rng: np.random.Generator, batch: int) -> FloatArray:
    """(batch, S) starts uniform in the task's box, a quaternion group turned and tilted as it says."""
    lo, hi = np.asarray(task.starts.low), np.asarray(task.starts.high)
    states = lo + (hi - lo) * rng.random((batch, len(lo)))
    qg = model.layout.find("quaternion")
    if qg is not None:
        sl = model.layout.slice_of(qg.name)
        yaw = rng.uniform(-np.pi, np.pi, batch) if task.starts.random_yaw else np.zeros(batch)
        tilt = np.arccos(1.0 - rng.random(batch) * (1.0 - np.cos(min(task.starts.max_tilt, np.pi))))
        around = rng.uniform(-np.pi, np.pi, batch)
        axis = np.stack([np.cos(around), np.sin(around), np.zeros(batch)], axis=1)
        q = quat.multiply(
            quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), yaw), quat.from_axis_angle(axis, tilt)
        )
        states[:, sl] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return states


HOLD_TOLERANCE = 1e-3  # the generalised force a pose may leave unbalanced and count as held (N, N·m)


def holdable(model: PhysicalModel, states: FloatArray, limit: int) -> NDArray[np.bool_]:
    """(N,) which of the states (N, S) their model's controls can hold still (``hold_controls``), the
    first ``limit`` of them checked (the rest are not kept)."""
    m = model.mj_model
    full = model.to_physics(np.asarray(states[:limit], dtype=np.float64))
    at = model.qpos_slice
    ok = np.zeros(len(states), dtype=bool)
    for i, row in enumerate(full):
        _, _, left = hold_controls(m, row[at])
        ok[i] = left < HOLD_TOLERANCE
    return ok


@dataclass
class GoalPool:
    """Goals (N, G) drawn from MuJoCo's typical motion, the states' spread (S,) in that motion (what
    the policy's inputs are scaled by) and the MuJoCo steps it took."""

    goals: FloatArray
    state_mean: FloatArray
    state_scale: FloatArray
    mujoco_steps: int

    def draw(self, rng: np.random.Generator, shape: tuple[int, ...]) -> FloatArray:
        """Goals of the pool at random: (*shape, G)."""
        idx = rng.integers(0, len(self.goals), size=shape)
        return self.goals[idx]

    def draw_moving(
        self, rng: np.random.Generator, batch: int, moves: int, max_move: float | None, tries: int = 32
    ) -> FloatArray:
        """(batch, moves, G) goals of the pool, each within ``max_move`` of the one before it (the first
        anywhere); where none of ``tries`` candidates is, the goal stays where it was."""
        out = self.draw(rng, (batch, moves))
        if max_move is None or moves < 2:
            return out
        for k in range(1, moves):
            cand = self.draw(rng, (batch, tries))  # (B, T, G)
            near = np.linalg.norm(cand - out[:, k - 1 : k], axis=2) <= max_move  # (B, T)
            first = np.argmax(near, axis=1)
            found = near[np.arange(batch), first]
            out[:, k] = np.where(found[:, None], cand[np.arange(batch), first], out[:, k - 1])
        return out


def reached_goals(
    model: PhysicalModel,
    task: PolicyTask,
    substeps: int,
    rng: np.random.Generator,
    count: int = 4096,
    runs: int = 256,
) -> GoalPool:
    """``count`` goals from runs of the model's typical motion from the task's starts, one run at a time
    in batches of ``runs``, until enough fall in the goal's box (at most 8 batches).
    ``GoalsUnreachable`` when none does."""
    cols = task.goal_columns
    lo, hi = np.asarray(task.goal.low), np.asarray(task.goal.high)
    speed_cols = np.array(
        [c for g in model.layout.placed() if g.source == "qvel" for c in range(g.offset, g.offset + g.size)],
        dtype=np.int64,
    )
    steps = max(1, round(task.episode_s / model.dt))
    found: list[FloatArray] = []
    seen: list[FloatArray] = []
    used = 0
    for _ in range(8):
        s0 = sample_starts(model, task, rng, runs)
        times = np.arange(steps, dtype=np.float64) * model.dt
        u = model.typical_controls(rng, runs, times)
        f = model.typical_forces(rng, runs, times) if model.num_forces else None
        states, diverged = model.simulate_runs(s0, u, f)
        used += runs * steps
        states = states[~diverged][:, substeps - 1 :: substeps]  # (R, K, S) at super-step boundaries
        flat = states.reshape(-1, states.shape[-1])
        seen.append(flat)
        g = flat[:, cols]
        keep = np.all((g >= lo) & (g <= hi), axis=1)
        if task.goal.at_rest and speed_cols.size:
            keep &= np.all(np.abs(flat[:, speed_cols]) < task.goal.rest_speed, axis=1)
        if task.goal.holdable:
            keep[keep] = holdable(model, flat[keep], count)
        found.append(g[keep])
        if sum(len(x) for x in found) >= count:
            break
    goals = np.concatenate(found)
    if not len(goals):
        raise GoalsUnreachable(
            f"policy task {task.name}: no state of {used} MuJoCo steps of typical motion from its starts "
            f"has its goal variables {list(task.goal.variables)} within {lo.tolist()}..{hi.tolist()}"
        )
    everything = np.concatenate(seen)
    mean = everything.mean(axis=0)
    scale = np.maximum(everything.std(axis=0), 1e-3)
    pick = rng.permutation(len(goals))[:count]
    log.info("%s: %d goals from %d MuJoCo steps of typical motion", task.name, len(goals), used)
    return GoalPool(goals[pick], mean, scale, used)
