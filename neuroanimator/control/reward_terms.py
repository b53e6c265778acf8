"""A user's reward task (``contracts.controller.RewardTaskSpec``) built into the ``SuiteTask`` a reward
policy is trained for (``reward_policy``), on any model: the terms read places and velocities
through ``kinematics`` from the emulator's state, as the suite's own rewards do, so that a policy
learns through the emulator what MuJoCo pays.

    RewardTaskSpec --build_reward_task(spec, model, layout, super_timestep, contact)--> SuiteTask

The episode is ``episode_s`` in super-steps, the reward paid at each (``control_substeps`` is the
super-step: an action a step). A body on the ground (``contact``: its emulator reads the floor's
clearance) learns as the suite's ground tasks do (``suite_tasks._ground``); a ``height`` term also
says when it has fallen (down to half its bound after four fifths of it).

Shapes: B batch, S state, U controls.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

import mujoco
import numpy as np
import torch
from pydantic import ValidationError
from torch import Tensor

from neuroanimator.artifacts import registry
from neuroanimator.contracts.controller import RewardTaskSpec, RewardTermSpec
from neuroanimator.control.suite_tasks import (
    GROUND_SEEDS,
    Context,
    Fall,
    FloatArray,
    ResetFn,
    SuiteTask,
    random_joints,
    tolerance,
)
from neuroanimator.core.state import LayoutGroup

GROUND_HORIZON = 8  # (``suite_tasks._ground``'s: gradient paths through contact kept short)
GROUND_KEEP = 1024
REST_NOISE = 0.05  # radians or metres on each hinge and slide of a start from rest
UNTOUCHED_TRIES = 100  # random draws looked through for one that touches nothing
DEFAULT_UPRIGHT = 0.9

Term = Callable[[Context, Tensor, Tensor], Tensor]


class RewardTaskError(ValueError):
    """A reward task that does not fit its model: the ``field`` inside the task and what was wrong."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field


def root_body(m: mujoco.MjModel) -> str:
    """The first body below the world (a model's root), by name."""
    for b in range(1, m.nbody):
        if int(m.body_parentid[b]) == 0:
            return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"body {b}"
    raise RewardTaskError("terms", "the model has no body below the world")


def _body(m: mujoco.MjModel, term: RewardTermSpec, i: int) -> str:
    name = term.body or root_body(m)
    if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) < 0:
        known = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, m.nbody)]
        raise RewardTaskError(f"terms[{i}].body", f"the model has no body {name!r}; its bodies: {known}")
    return name


def _term(m: mujoco.MjModel, term: RewardTermSpec, i: int) -> Term:
    """One term as a function of (context, states (B, S), controls (B, U)) → (B,) in [0, 1]."""
    if term.kind == "small_control":
        low, high = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
        limited = m.actuator_ctrllimited.astype(bool) & (high > low)
        mid = torch.tensor(np.where(limited, (low + high) / 2, 0.0))
        half = torch.tensor(np.where(limited, (high - low) / 2, 1.0))

        def small(ctx: Context, s: Tensor, u: Tensor) -> Tensor:
            share = (u - mid.to(u.dtype)) / half.to(u.dtype)
            return (tolerance(share, 0.0, 0.0, 1.0, "quadratic", 0.0).mean(dim=1) + 4) / 5

        return small
    body = _body(m, term, i)
    if term.kind == "height":
        h = float(term.at_least or 0.0)
        margin = term.margin or max(abs(h) / 2, 0.05)

        def height(ctx: Context, s: Tensor, u: Tensor) -> Tensor:
            z = ctx.kin.locator("body", body).position(ctx.kin.places(s))[:, 2]
            return tolerance(z, h, math.inf, margin)

        return height
    if term.kind == "upright":
        c = DEFAULT_UPRIGHT if term.at_least is None else float(term.at_least)
        margin = term.margin or 1 + c

        def upright(ctx: Context, s: Tensor, u: Tensor) -> Tensor:
            zz = ctx.kin.locator("body", body).rotation(ctx.kin.places(s))[:, 2, 2]
            return tolerance(zz, c, math.inf, margin, "linear", 0.0)

        return upright
    axis = 0 if term.axis == "x" else 1
    if term.kind == "speed":
        v = float(term.at_least or 0.0)
        margin = term.margin or abs(v)
        lower, upper = (v, math.inf) if v > 0 else (-math.inf, v)

        def speed(ctx: Context, s: Tensor, u: Tensor) -> Tensor:
            along = ctx.kin.subtree_velocity(s, body)[:, axis]
            return tolerance(along, lower, upper, margin, "linear", 0.0)

        return speed
    margin = term.margin or 2.0

    def still(ctx: Context, s: Tensor, u: Tensor) -> Tensor:
        return tolerance(ctx.kin.subtree_velocity(s, body)[:, :2], 0.0, 0.0, margin).mean(dim=1)

    return still


def _reset(m: mujoco.MjModel, how: str) -> ResetFn:
    """Random joints drawn until nothing touches (the last of ``UNTOUCHED_TRIES`` otherwise: a body
    that cannot avoid its floor starts on it), or rest: the first keyframe (else ``qpos0``) with
    ``REST_NOISE`` on hinges and slides."""
    rest = np.array(m.key_qpos[0] if m.nkey else m.qpos0, dtype=np.float64)
    rest_vel = np.array(m.key_qvel[0] if m.nkey else np.zeros(m.nv), dtype=np.float64)
    movable = np.zeros(m.nq, dtype=bool)
    for j in range(m.njnt):
        if int(m.jnt_type[j]) in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            movable[int(m.jnt_qposadr[j])] = True
    d = mujoco.MjData(m)

    def from_rest(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
        qpos = rest + np.where(movable, rng.uniform(-REST_NOISE, REST_NOISE, m.nq), 0.0)
        return qpos, rest_vel.copy(), np.zeros(0)

    def random(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
        qpos = rest.copy()
        for _ in range(UNTOUCHED_TRIES):
            qpos = rest.copy()
            random_joints(m, rng, qpos)
            d.qpos[:] = qpos
            mujoco.mj_forward(m, d)
            if d.ncon == 0:
                break
        return qpos, np.zeros(m.nv), np.zeros(0)

    return from_rest if how == "rest" else random


def unread_travel(m: mujoco.MjModel, layout: list[LayoutGroup]) -> tuple[str, ...]:
    """The state groups of the root's unlimited horizontal slides (how far a planar body has gone):
    left unread by its policy, as the suite's observations leave them, so that going further does not
    show it values it never saw."""
    out = []
    names = {g.name for g in layout}
    for j in range(m.njnt):
        body = int(m.jnt_bodyid[j])
        if int(m.jnt_type[j]) != mujoco.mjtJoint.mjJNT_SLIDE or int(m.body_parentid[body]) != 0:
            continue
        axis = np.abs(np.asarray(m.jnt_axis[j]))
        if m.jnt_limited[j] or axis[2] >= max(axis[0], axis[1]):
            continue
        group = f"{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)}.pos"
        if group in names:
            out.append(group)
    return tuple(out)


def build_reward_task(
    spec: RewardTaskSpec,
    m: mujoco.MjModel,
    layout: list[LayoutGroup],
    substeps: int,
    super_timestep: float,
    contact: bool,
) -> SuiteTask:
    """The task ``spec`` asks of model ``m`` (its emulator's ``layout``, ``substeps`` and
    ``super_timestep``; ``contact``: the emulator reads the floor's clearance), or ``RewardTaskError``
    naming the term that does not fit (a body the model lacks)."""
    terms = [_term(m, t, i) for i, t in enumerate(spec.terms)]
    mean = spec.combine == "mean"

    def reward(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
        values = torch.stack([t(ctx, s, u) for t in terms], dim=1)
        return values.mean(dim=1) if mean else values.prod(dim=1)

    fall = None
    for i, t in enumerate(spec.terms):
        if t.kind == "height" and t.at_least is not None and t.at_least > 0:
            body = _body(m, t, i)
            level = _height_of(body)
            fall = Fall(level, above=0.8 * float(t.at_least), below=0.5 * float(t.at_least))
            break
    task = SuiteTask(
        name=spec.name or f"custom-{spec.model}",
        domain=spec.model,
        substeps=substeps,
        control_substeps=substeps,
        episode_steps=max(1, round(spec.episode_s / super_timestep)),
        summary=spec.summary,
        reset=_reset(m, spec.starts),
        reward=reward,
        fall=fall,
        unobserved=unread_travel(m, layout),
    )
    return (
        replace(task, horizon=GROUND_HORIZON, refine_keep=GROUND_KEEP, seeds=GROUND_SEEDS)
        if contact
        else task
    )


def _height_of(body: str) -> Callable[[Context, Tensor], Tensor]:
    def height(ctx: Context, s: Tensor) -> Tensor:
        return ctx.kin.locator("body", body).position(ctx.kin.places(s))[:, 2]

    return height


def reward_task_at(spec: RewardTaskSpec, emulator: Path) -> SuiteTask:
    """``build_reward_task`` for the emulator artifact at ``emulator`` (its model, layout and
    super-step; contact when it reads the floor's clearance)."""
    manifest = registry.read_manifest(emulator)
    physical = registry.load_physical_model(emulator, manifest)
    task = build_reward_task(
        spec,
        physical.mj_model,
        list(manifest.layout),
        manifest.substeps,
        manifest.super_timestep,
        bool(manifest.train_config.clearance),
    )
    # its terms are closures: another process (a seed of ``seed_race``) builds it again from here
    return replace(task, rebuild=partial(reward_task_at, spec, emulator))


def reward_task_file(path: Path, root: registry.Root) -> SuiteTask:
    """A reward task written as JSON (``RewardTaskSpec``, as ``POST /policies`` takes it) on its model's
    emulator in ``root`` (at its ``substeps``, else the model's latest); ``ValueError`` saying what
    does not fit."""
    try:
        spec = RewardTaskSpec.model_validate_json(path.read_bytes())
    except ValidationError as exc:
        raise ValueError(f"{path}: not a reward task: {exc}") from exc
    return reward_task_at(spec, registry.resolve(root, spec.model, None, spec.substeps))
