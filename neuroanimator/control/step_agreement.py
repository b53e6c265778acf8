"""Whether an emulator can tell neighbouring policies apart as MuJoCo does: the measure of a contact
emulator for learning, beside its one-step error.

Every learner steps by the differences between the returns of nearby policies: a gradient is their
limit, random search reads them off. An emulator whose one-step error is small can still get them
wrong; the cheetah's (0.0345) credited the gaits MuJoCo found within a tenth, yet the step augmented
random search (ARS) took through it was unrelated to MuJoCo's or opposed (docs/experiments/policies.md).
So, at a policy: ``directions`` random directions δ in the weights of its network, each tried both
ways (θ ± νδ) on the same ``episodes`` starts, on the emulator and on MuJoCo, and ARS's step from each
(Σ (R(θ+νδ) − R(θ−νδ)) δ, every direction) compared by their cosine. A second batch of starts says
how much the step depends on the starts: the emulator's step from it against MuJoCo's from the first,
beside MuJoCo's own from it (a noisy step agrees with itself across starts less than a perfect
emulator does from the same ones).

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
    """ARS's step at a policy, from the emulator's returns and from MuJoCo's (module doc). Two pairs:
    from the same starts, and across two batches of starts, the emulator's and MuJoCo's own; the
    second pair alike in how the step depends on the starts, the first sharing them."""

    cosine: float  # the emulator's step against MuJoCo's, from the same starts
    # the emulator's step from the other starts against MuJoCo's from the first ...
    cosine_across_starts: float
    # ... and MuJoCo's own from the other starts: how much the step depends on the starts at all
    mujoco_across_starts: float
    # share of the directions whose return difference has the same sign on both, the same starts
    same_sign: float
    # mean return of the policies tried from the first starts, on MuJoCo and on the emulator: the
    # reward at each super-step times its control steps (``policies_returns``), not the task's
    # return over every control step (``run_on_mujoco``)
    return_mujoco: float
    return_emulator: float
    directions: int
    episodes: int
    noise: float  # ν
    mujoco_steps: int  # physical steps the measurement took


def cosine(step: Tensor, reference: Tensor) -> float:
    """The cosine of a (D,) step with a reference one, in double precision: nan where the reference
    is zero (every policy tried earned the same: no step to agree with), 0 where only the step is."""
    a, b = step.double(), reference.double()
    na, nb = float(torch.linalg.vector_norm(a)), float(torch.linalg.vector_norm(b))
    if nb == 0:
        return math.nan
    return max(-1.0, min(1.0, float(a @ b) / (na * nb))) if na > 0 else 0.0


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
    at ``policy``, over whole episodes of ``task`` from two batches of ``episodes`` of its starts
    drawn with ``seed``, each run on both; None for a policy whose network is not a stack of layers,
    or that chooses among candidates (value iteration's copy)."""
    if directions < 1 or episodes < 1:
        raise ValueError(
            f"the step agreement takes at least a direction and a start, not {directions} and {episodes}"
        )
    net = policy.net
    if isinstance(policy, ChoicePolicy) or not isinstance(net, nn.Sequential):
        return None
    theta = flat_weights(net)
    deltas = torch.randn(directions, theta.numel(), generator=torch.Generator().manual_seed(seed))
    tried = torch.cat([theta + noise * deltas, theta - noise * deltas])
    drawn = draw_starts(task, physical, np.random.default_rng(seed), 2 * episodes)
    starts, params = (torch.as_tensor(x, dtype=torch.float32) for x in drawn)
    held = held_on_mujoco(physical, substeps)
    counted = 0

    def mujoco(s: Tensor, u: Tensor) -> Tensor:
        nonlocal counted
        counted += len(s) * substeps
        return held(s, u)

    unbounded = (torch.full_like(starts[0], -math.inf), torch.full_like(starts[0], math.inf))

    def returns(step: Callable[[Tensor, Tensor], Tensor], rows: slice) -> Tensor:
        return policies_returns(
            policy, net, tried, starts[rows], params[rows], task.policy_steps, step,
            lambda s, u, p: task.reward(ctx, s, u, p, False), task.repeat, unbounded,
        )[0]  # fmt: skip

    def ars_step(got: Tensor) -> tuple[Tensor, Tensor]:
        """(N,) return differences of each direction's two sides and the (D,) step they make."""
        diff = got[:directions] - got[directions:]
        return diff, (diff.unsqueeze(1) * deltas).sum(dim=0)

    first, other = slice(0, episodes), slice(episodes, 2 * episodes)
    on_mujoco, on_emulator = returns(mujoco, first), returns(emulator, first)
    (d_mujoco, mujoco_step), (d_emulator, emulator_step) = ars_step(on_mujoco), ars_step(on_emulator)
    mujoco_other, emulator_other = ars_step(returns(mujoco, other))[1], ars_step(returns(emulator, other))[1]
    return StepAgreement(
        cosine=cosine(emulator_step, mujoco_step),
        cosine_across_starts=cosine(emulator_other, mujoco_step),
        mujoco_across_starts=cosine(mujoco_other, mujoco_step),
        same_sign=float((torch.sign(d_mujoco) == torch.sign(d_emulator)).double().mean())
        if bool(d_mujoco.any())
        else math.nan,
        return_mujoco=float(on_mujoco.mean()),
        return_emulator=float(on_emulator.mean()),
        directions=directions,
        episodes=episodes,
        noise=noise,
        mujoco_steps=counted,
    )
