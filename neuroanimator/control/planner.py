"""A sampling planner through the emulator: model-predictive control that a reward policy can copy.

Some tasks defeat a policy's gradient: the acrobot must pump energy into two links over several
swings before any reward is paid, and an actor-critic through its (near exact) emulator learned to
hang and wave (returns 30-41 of 1,000). A planner does not need that gradient. Every super-step it
searches the emulator's futures from the state it is in and acts on the best, then searches again
from where it lands (the improved cross-entropy method of Pinneri et al. 2020, as TD-MPC and PETS plan
through learned models):

1. a mean control sequence over ``horizon_s``, the last step's best shifted by one super-step;
2. ``iterations`` times: ``samples`` sequences around the mean, their noise coloured (power falling
   as 1/f^``colour`` along the horizon: slow pushes, not jitter), rolled out through the emulator in
   one batch and scored by the task's reward over the horizon (exact, plus ``shaping`` times its
   smooth form, which pays a tip approaching the target before it is there); the best tenth sets the
   next mean and spread, and the best sequence so far is carried along;
3. the best sequence's first control is applied.

Measured on the acrobot (``docs/experiments/policies.md``, ``bench/planner.py``): 3 s of horizon,
256 samples, three iterations: 367-373 on the bench's 10 held-out MuJoCo episodes, where the
actor-critic learns 41 (2 s of horizon, the smooth reward alone: 142; 3 s, the smooth alone: 232). A planner costs hundreds of emulator rollouts a step, far too much to
serve; ``reward_policy`` copies it into a policy network (DAgger: the policy drives, the planner says
what it would have done), and that network is what is served.

Shapes: N states planned for side by side, K samples each, H super-steps of horizon, U controls,
P task parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from neuroanimator.control.suite_tasks import Context, SuiteTask

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PlannerSettings:
    """How far and how widely the planner searches (module doc)."""

    horizon_s: float = 3.0  # the acrobot: 2 s gave 142, 3 s 232, 4 s 250 (the smooth score alone)
    samples: int = 256  # control sequences per state and iteration (512: no better at twice the cost)
    iterations: int = 3
    elite_share: float = 0.1
    colour: float = 2.0  # the noise's spectrum along the horizon falls as 1/f^colour
    spread: float = 0.6  # the first iteration's noise, a share of each control's half range
    min_spread: float = 0.05  # the spread never collapses below this share
    shaping: float = 0.3  # the smooth reward's weight beside the exact one in the score


class SamplingPlanner:
    """Plans for N states at once through a frozen emulator step ``(B,S),(B,U) -> (B,S)``; keeps each
    state's best sequence to warm-start its next plan (``reset`` forgets them)."""

    def __init__(
        self,
        step: nn.Module,
        task: SuiteTask,
        ctx: Context,
        low: FloatArray,
        high: FloatArray,
        super_timestep: float,
        settings: PlannerSettings | None = None,
        seed: int = 0,
    ) -> None:
        self.step, self.task, self.ctx = step, task, ctx
        self.settings = settings or PlannerSettings()
        # no further than an episode: what lies past its end earns nothing
        self.horizon = max(1, min(task.policy_steps, round(self.settings.horizon_s / super_timestep)))
        self.low = torch.as_tensor(low, dtype=torch.float32)
        self.high = torch.as_tensor(high, dtype=torch.float32)
        self.centre = (self.low + self.high) / 2
        self.half = (self.high - self.low) / 2
        self.elites = max(2, round(self.settings.elite_share * self.settings.samples))
        self.generator = torch.Generator().manual_seed(seed)
        self.plans: Tensor | None = None  # (N, H, U) the last best sequences

    def reset(self) -> None:
        self.plans = None

    def noise(self, count: int) -> Tensor:
        """(count, H, U) unit-variance noise whose power falls as 1/f^colour along the horizon."""
        h, u = self.horizon, len(self.low)
        freqs = torch.fft.rfftfreq(h)
        freqs[0] = freqs[1] if h > 1 else 1.0  # the constant's power as the slowest wave's
        gain = freqs ** (-self.settings.colour / 2)
        shape = (count, u, len(freqs))
        spectrum = torch.complex(
            torch.randn(shape, generator=self.generator) * gain,
            torch.randn(shape, generator=self.generator) * gain,
        )
        x = torch.fft.irfft(spectrum, n=h)
        x = x / x.std(dim=2, keepdim=True).clamp_min(1e-6) if h > 1 else torch.randn(count, u, 1)
        return x.transpose(1, 2)

    def score(self, states: Tensor, params: Tensor, sequences: Tensor) -> Tensor:
        """(N, K) the reward over the horizon of K sequences (N, K, H, U) from each of N states."""
        n, k = sequences.shape[:2]
        x = states[:, None].expand(n, k, -1).reshape(n * k, -1)
        p = params[:, None].expand(n, k, -1).reshape(n * k, -1)
        total = torch.zeros(n * k)
        shaping = self.settings.shaping
        for t in range(self.horizon):
            u = sequences[:, :, t].reshape(n * k, -1)
            x = self.step(x, u)
            r = torch.nan_to_num(self.task.reward(self.ctx, x, u, p, False))
            if shaping > 0:
                r = r + shaping * torch.nan_to_num(self.task.reward(self.ctx, x, u, p, True))
            total = total + r
        return total.reshape(n, k)

    def follow(self, policy: nn.Module, states: Tensor, params: Tensor) -> Tensor:
        """(N, H, U) the controls a policy ``(B,S),(B,P) -> (B,U)`` gives along its own emulated run."""
        x, out = states, []
        for _ in range(self.horizon):
            u = policy(x, params)
            out.append(u)
            x = self.step(x, u)
        return torch.stack(out, dim=1)

    @torch.no_grad()
    def act(self, states: FloatArray, params: FloatArray, prior: nn.Module | None = None) -> FloatArray:
        """(N, U) the first control of each state's best plan, states (N, S), parameters (N, P). A
        ``prior`` policy's own run through the emulator is a candidate too, and the search starts
        around it: where the policy already does best, the plan is the policy's (a copy learns from
        labels that agree with it, not from the search's noise)."""
        cfg = self.settings
        s = torch.as_tensor(states, dtype=torch.float32)
        p = torch.as_tensor(params, dtype=torch.float32).reshape(len(s), -1)
        n, h, u = len(s), self.horizon, len(self.low)
        if self.plans is None or len(self.plans) != n:
            mean = self.centre.expand(n, h, u).clone()
        else:  # the last plan, a step on; its last control held
            mean = torch.cat([self.plans[:, 1:], self.plans[:, -1:]], dim=1)
        spread = torch.full((n, 1, 1), cfg.spread) * self.half
        floor = cfg.min_spread * self.half
        rows = torch.arange(n)
        best = mean
        best_score = torch.full((n,), -torch.inf)
        if prior is not None:
            best = self.follow(prior, s, p)
            best_score = self.score(s, p, best[:, None])[:, 0]
            mean = best
        for _ in range(cfg.iterations):
            seq = mean[:, None] + spread[:, None] * self.noise(n * cfg.samples).reshape(n, cfg.samples, h, u)
            seq[:, 0] = mean  # the mean itself is a candidate
            seq = torch.maximum(torch.minimum(seq, self.high), self.low)
            scores = self.score(s, p, seq)
            seq = torch.cat([seq, best[:, None]], dim=1)  # the best so far competes again
            scores = torch.cat([scores, best_score[:, None]], dim=1)
            top = scores.topk(self.elites, dim=1).indices
            elite = torch.gather(seq, 1, top[:, :, None, None].expand(-1, -1, h, u))
            mean = elite.mean(dim=1)
            spread = torch.maximum(elite.std(dim=1).mean(dim=1, keepdim=True), floor)
            pick = scores.argmax(dim=1)
            best, best_score = seq[rows, pick], scores[rows, pick]
        self.plans = best
        out: FloatArray = best[:, 0].numpy().astype(np.float64)
        return out
