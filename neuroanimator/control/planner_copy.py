"""A reward policy copied from the sampling planner (``planner.py``), as DAgger copies an expert
(Ross, Gordon and Bagnell 2011; guided policy search and TD-MPC pair a planner with a policy the same
way):

1. the planner drives ``copy_episodes`` of the task's episodes on MuJoCo, planning through the
   emulator at every super-step, and what it did in each state is the first set of examples;
2. the policy is fit to every example so far (mean squared error on controls scaled to ±1);
3. then the policy drives new episodes itself while the planner, planning from the same states, says
   what it would have done: the states a copy's own errors lead to, which the planner never visits,
   join the examples, and the policy is fit again; and so on until the budget is spent.

Every round ends with a check on MuJoCo as the actor-critic's checks are (``RewardTrainer.evaluate``):
the best policy is kept. Only the planner reads the emulator; MuJoCo gives the states, so the
examples are where the policy really goes.

Shapes: N episodes side by side, S state, U controls, P task parameters.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch
from numpy.typing import NDArray

from neuroanimator.control.planner import PlannerSettings, SamplingPlanner

if TYPE_CHECKING:
    from neuroanimator.control.reward_policy import RewardPolicy, RewardTrainer

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
PLANNER = "planner"  # ``RewardSettings.teacher``: copy the planner (before or instead of the actor-critic)
TEACHERS = ("none", PLANNER)


@dataclass(frozen=True)
class CopySettings:
    """How the planner is copied (module doc)."""

    episodes: int = 8  # episodes a round, planned for side by side
    epochs: int = 30  # passes over all the examples after each round
    batch: int = 256
    lr: float = 1e-3
    planner: PlannerSettings = field(default_factory=PlannerSettings)
    # from the second round the policy's own emulated run is the search's first candidate and mean
    # (``SamplingPlanner.act``'s prior)
    policy_prior: bool = True
    # rounds of copying, after which the actor-critic goes on from the copy, the planner's states
    # among its restarts (``RewardTrainer.train``); None: copying until the budget is spent
    rounds: int | None = None


class Stopped(Exception):
    """Raised inside a round when the job is cancelled: the round's episodes are dropped."""


@dataclass
class Examples:
    """What the planner did where: states (M, S), parameters (M, P), controls (M, U)."""

    states: list[FloatArray]
    params: list[FloatArray]
    controls: list[FloatArray]

    @property
    def count(self) -> int:
        return sum(len(s) for s in self.states)

    def joined(self) -> tuple[FloatArray, FloatArray]:
        """Every example's state (M, S) and parameters (M, P)."""
        states = np.concatenate(self.states)
        return states, np.concatenate(self.params).reshape(len(states), -1)

    def add(self, states: FloatArray, params: FloatArray, controls: FloatArray) -> None:
        self.states.append(np.array(states))
        self.params.append(np.array(params))
        self.controls.append(np.array(controls))


def fit(policy: RewardPolicy, examples: Examples, cfg: CopySettings, rng: np.random.Generator) -> float:
    """Fit the policy to every example (controls scaled by its half ranges); the last batch's loss."""
    s = torch.as_tensor(np.concatenate(examples.states), dtype=torch.float32)
    p = torch.as_tensor(np.concatenate(examples.params), dtype=torch.float32).reshape(len(s), -1)
    target = (torch.as_tensor(np.concatenate(examples.controls), dtype=torch.float32) - policy.centre) / (
        policy.half_range
    )
    opt = torch.optim.Adam(policy.parameters(), lr=cfg.lr)
    loss = torch.zeros(())
    for _ in range(cfg.epochs):
        order = torch.as_tensor(rng.permutation(len(s)))
        for i in range(0, len(s), cfg.batch):
            b = order[i : i + cfg.batch]
            out = (policy(s[b], p[b]) - policy.centre) / policy.half_range
            loss = ((out - target[b]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    return float(loss.detach())


class PlannerCopy:
    """Copies the planner into ``trainer.policy`` within ``trainer.settings.seconds`` (module doc)."""

    def __init__(self, trainer: RewardTrainer, cfg: CopySettings | None = None) -> None:
        self.trainer = trainer
        self.cfg = cfg or trainer.settings.copying
        self.planner = SamplingPlanner(
            trainer.step,
            trainer.task,
            trainer.ctx,
            trainer.low,
            trainer.high,
            trainer.manifest.super_timestep,
            self.cfg.planner,
            seed=trainer.settings.seed,
        )
        self.examples = Examples([], [], [])

    def round(self, driver: str) -> float:
        """One round of episodes on MuJoCo, the planner labelling every state; the round's mean return."""
        tr = self.trainer
        self.planner.reset()

        def act(states: FloatArray, p: FloatArray) -> FloatArray:
            if tr.should_stop is not None and tr.should_stop():
                raise Stopped
            prior = tr.policy if self.cfg.policy_prior and driver != PLANNER else None
            planned = self.planner.act(states, p, prior)
            self.examples.add(states, p, planned)
            return planned if driver == PLANNER else tr.policy.act(states, p)

        return tr.episodes(act, self.cfg.episodes, tr.rng).mean

    def train(self) -> tuple[tuple[float, dict[str, torch.Tensor]], list[tuple[int, float, float]], int, str]:
        """Rounds until the budget is spent: the best (return, weights), the checks' history
        (round, elapsed s, return), the rounds and why it stopped ("budget" or "cancelled")."""
        tr, cfg = self.trainer, self.cfg
        settings = tr.settings
        best: tuple[float, dict[str, torch.Tensor]] = (-math.inf, copy.deepcopy(tr.policy.state_dict()))
        history: list[tuple[int, float, float]] = []
        rounds, stop, last_round_s = 0, "budget", 0.0
        # a round that would end past the budget is not begun (the first always is)
        while rounds == 0 or tr.elapsed() + last_round_s < tr.deadline():
            if settings.max_iterations is not None and rounds >= settings.max_iterations:
                break
            if cfg.rounds is not None and rounds >= cfg.rounds:
                break
            t0 = time.perf_counter()
            driver = PLANNER if rounds == 0 else "policy"
            try:
                driven = self.round(driver)
            except Stopped:
                stop = "cancelled"
                break
            loss = fit(tr.policy, self.examples, cfg, tr.rng)
            runs, emulated = tr.evaluate(settings.eval_episodes, int(tr.rng.integers(1 << 30)))
            rounds += 1
            history.append((rounds, round(tr.elapsed(), 1), runs.mean))
            if runs.mean >= best[0]:
                best = (runs.mean, copy.deepcopy(tr.policy.state_dict()))
            tr.runs.append(runs)
            log.info(
                "%s: round %d, %s drove (return %.1f), %d examples, fit %.4f; the policy's return on "
                "MuJoCo %.1f, on the emulator %.1f",
                tr.task.name, rounds, driver, driven, self.examples.count, loss, runs.mean, emulated,
            )  # fmt: skip
            tr.report(rounds, loss, runs.mean)
            last_round_s = time.perf_counter() - t0
        return best, history, rounds, stop
