"""Whether an emulator can tell neighbouring policies apart as MuJoCo does: the measure of a contact
emulator for learning, beside its one-step error.

Every learner steps by the differences between the returns of nearby policies: a gradient is their
limit, random search reads them off. An emulator whose one-step error is small can still get them
wrong; the cheetah's (0.0345) credited the gaits MuJoCo found within a tenth, yet the step augmented
random search (ARS) took through it was unrelated to MuJoCo's or opposed (docs/experiments/policies.md).
So, at a policy: ``directions`` random directions δ in the weights of its network, each tried both
ways (θ ± νδ) on the same ``episodes`` starts, on the emulator and on MuJoCo, and ARS's step from each
(Σ (R(θ+νδ) − R(θ−νδ)) δ, every direction) compared by their cosine. MuJoCo's step from other starts
against its own is the ceiling: how much one batch of starts says about the step at all.

Shapes: N directions, E starts, S state, P parameters, D the network's weights.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from neuroanimator.control.random_search import (
    RandomSearch,
    flat_weights,
    held_on_mujoco,
    policies_returns,
)
from neuroanimator.control.reward_policy import ChoicePolicy, RewardPolicy, draw_starts
from neuroanimator.control.suite_tasks import Context, SuiteTask
from neuroanimator.sim.model import PhysicalModel


@dataclass(frozen=True)
class StepAgreement:
    """ARS's step at a policy, from the emulator's returns and from MuJoCo's (module doc)."""

    cosine: float  # the emulator's step against MuJoCo's, the same starts (nan: MuJoCo's is zero)
    ceiling: float  # MuJoCo's step from other starts against it: the most the cosine could say
    same_sign: float  # share of the directions whose return difference has the same sign on both
    return_mujoco: float  # mean return of the policies tried, on MuJoCo
    return_emulator: float  # ... and on the emulator
    directions: int
    episodes: int
    noise: float  # ν
    mujoco_steps: int  # physical steps the measurement took


def cosine(a: Tensor, b: Tensor) -> float:
    """The cosine of two (D,) vectors; nan when either is zero (no direction to agree with)."""
    na, nb = float(torch.linalg.vector_norm(a)), float(torch.linalg.vector_norm(b))
    return float(a @ b) / (na * nb) if na > 0 and nb > 0 else math.nan


def step_agreement(
    task: SuiteTask,
    physical: PhysicalModel,
    ctx: Context,
    substeps: int,
    emulator: Callable[[Tensor, Tensor], Tensor],
    policy: RewardPolicy,
    seed: int,
    directions: int = 32,
    episodes: int = 4,
    noise: float = RandomSearch.noise,
) -> StepAgreement | None:
    """The agreement of the emulator's super-step ``emulator`` ((B, S), (B, U) → (B, S)) with MuJoCo's
    at ``policy``, over whole episodes of ``task`` from 2·``episodes`` of its starts drawn with
    ``seed`` (the first half for both, the second for the ceiling); None for a policy whose network
    is not a stack of layers, or that chooses among candidates (value iteration's copy)."""
    net = policy.net
    if isinstance(policy, ChoicePolicy) or not isinstance(net, nn.Sequential):
        return None
    theta = flat_weights(net)
    deltas = torch.randn(directions, theta.numel(), generator=torch.Generator().manual_seed(seed))
    tried = torch.cat([theta + noise * deltas, theta - noise * deltas])
    drawn = draw_starts(task, physical, np.random.default_rng(seed), 2 * episodes)
    starts, params = (torch.as_tensor(x, dtype=torch.float32) for x in drawn)
    mujoco = held_on_mujoco(physical, substeps)
    unbounded = (torch.full_like(starts[0], -math.inf), torch.full_like(starts[0], math.inf))

    def returns(step: Callable[[Tensor, Tensor], Tensor], rows: slice) -> Tensor:
        return policies_returns(
            policy, net, tried, starts[rows], params[rows], task.policy_steps, step,
            lambda s, u, p: task.reward(ctx, s, u, p, False), task.repeat, unbounded,
        )[0]  # fmt: skip

    first, second = slice(0, episodes), slice(episodes, 2 * episodes)
    on_mujoco, on_emulator, elsewhere = (
        returns(mujoco, first),
        returns(emulator, first),
        returns(mujoco, second),
    )

    def ars_step(got: Tensor) -> tuple[Tensor, Tensor]:
        diff = got[:directions] - got[directions:]
        return diff, (diff.unsqueeze(1) * deltas).sum(dim=0)

    (d_mujoco, mujoco_step), (d_emulator, emulator_step) = ars_step(on_mujoco), ars_step(on_emulator)
    return StepAgreement(
        cosine=cosine(emulator_step, mujoco_step),
        ceiling=cosine(ars_step(elsewhere)[1], mujoco_step),
        same_sign=float((d_mujoco * d_emulator > 0).float().mean()),
        return_mujoco=float(on_mujoco.mean()),
        return_emulator=float(on_emulator.mean()),
        directions=directions,
        episodes=episodes,
        noise=noise,
        mujoco_steps=2 * len(tried) * episodes * task.policy_steps * substeps,
    )
