"""Policies learned by backpropagation through the emulator (thesis 7.2.3; SHAC's and Brax's analytic
policy gradients, with a learned model as SuperTrack and ControlVAE use one).

``train_policy`` reads top to bottom:

1. the task's goals from MuJoCo's typical motion (``policy_data.reached_goals``) and the policy's
   input scales from the same states;
2. batches of starts × goals rolled out through the frozen torch emulator under the policy, the
   loss the weighted distance of every state to its target (counted from ``settle_s`` after a goal is
   set, lightly before) plus a small control effort, gradients through the whole rollout, truncated
   every ``truncate`` super-steps, clipped in norm, Adam;
3. every ``refine_every`` of the budget, the policy is run on MuJoCo and on the emulator from new
   starts and goals: its success on both is measured, and where the two verdicts differ by more than
   ``refine_gap`` (``refine``), the MuJoCo runs are added to the emulator's data and the emulator
   fine-tuned on them (``train_over_rollouts``), so the model is right where the policy goes;
4. the policy kept is the one that did best on MuJoCo; it ends with its success on held-out starts and
   goals, on MuJoCo and on the emulator.

The emulator a policy is trained through is the artifact's own; once refined, the refined copy is
the one it is judged on at the end and stored with it (``store.save_tuned``: a version of its own that
the policy names), so that its sessions run the emulator it learned through.

Shapes: B batch, K super-steps, S state, G goal variables, U controls.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.control.bptt import FastStep, FrozenStep
from neuroanimator.control.objectives import CheckPenalty
from neuroanimator.control.policy_data import GoalPool, reached_goals, sample_starts
from neuroanimator.control.policy_net import (
    PolicyNet,
    PolicyShape,
    describe_body_frame,
    describe_columns,
    wrap,
)
from neuroanimator.control.threads import torch_threads
from neuroanimator.core.manifest import Manifest
from neuroanimator.emulator.hierarchy import HierarchicalEmulator
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.goals import criteria
from neuroanimator.goals.policy_task import PolicyTask, goal_schedule
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.train import fine_tune_on_runs

log = logging.getLogger(__name__)
CHECK_MARGIN = 0.25  # a check met with room to spare: its measure within half its bound
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PolicySettings:
    """How a policy is trained; ``seconds`` is the wall-clock budget of the whole training."""

    seconds: float = 600.0
    max_iterations: int | None = None  # a cap on the updates besides the budget
    batch: int = 256
    learning_rate: float = 2e-3  # cosine-annealed to a tenth over the budget
    truncate: int = 0  # super-steps between cuts of the gradient's path (0: the whole run)
    grad_clip: float = 1.0
    hidden: tuple[int, ...] | None = None  # default: the task's
    refine: bool = True
    refine_every: float = 0.2  # share of the budget between MuJoCo evaluations
    refine_gap: float = 0.1  # refine when success on the emulator and on MuJoCo differ by more
    refine_runs: int = 128
    refine_seconds: float = 20.0
    evaluate_runs: int = 100
    seed: int = 0
    threads: int = 1  # one: its matrices are small, and a second thread only waits under load


class PolicyProgress(TypedDict):
    """What ``on_progress`` receives: the iteration, the batch's loss, the last success share on
    MuJoCo (None before the first check), the MuJoCo steps used so far and the elapsed seconds."""

    iteration: int
    loss: float | None
    success_physics: float | None
    mujoco_steps: int
    elapsed_s: float


@dataclass
class Evaluation:
    """A policy run on MuJoCo or on the emulator from starts (N, S) towards goals (N, P, G): the states
    (N, K+1, S), the controls held (N, K, U), which runs met every check (N,) and when and where the
    checks of the failed ones first failed."""

    states: FloatArray
    controls: FloatArray
    success: NDArray[np.bool_]

    @property
    def rate(self) -> float:
        return float(self.success.mean()) if len(self.success) else 0.0


@dataclass
class PolicyResult:
    """A trained policy and how it did."""

    net: PolicyNet
    task: PolicyTask
    manifest: Manifest
    success_physics: float
    success_emulator: float
    mujoco_steps: int
    iterations: int
    wall_s: float
    loss_history: list[float] = field(default_factory=list)
    success_history: list[tuple[int, float]] = field(default_factory=list)
    evaluate_runs: int = 0
    stop: str = "budget"
    refinements: int = 0  # fine-tunings of the emulator on the policy's MuJoCo runs
    goals: FloatArray | None = None  # (N, G) the goals it was trained for
    # the emulator refined on its runs (served with it) and (S,) lows and highs of the states it was
    # refined on; None: the stored one unchanged
    emulator: StructuredEmulator | None = None
    envelope: tuple[FloatArray, FloatArray] | None = None


def frozen_step(emu: StructuredEmulator | HierarchicalEmulator) -> nn.Module:
    """The emulator's super-step ``(state (B,S), controls (B,U)) → (B,S)`` in its exported form, frozen."""
    return FrozenStep(emu) if isinstance(emu, HierarchicalEmulator) else FastStep(emu)


class Schedule:
    """When goals change and when checks hold over a run of ``steps`` super-steps."""

    def __init__(self, task: PolicyTask, super_dt: float, goals: int | None = None) -> None:
        self.steps, self.per_goal, self.check = goal_schedule(task, super_dt)
        if goals is not None:  # fewer goals per run than the task's (training on one period at a time)
            self.steps = self.per_goal * goals
        self.goals = self.steps // self.per_goal
        settle = max(0, min(self.check, round(task.settle_s / super_dt)))
        tau = np.arange(1, self.per_goal + 1)  # steps since the goal was set, after each step
        w = np.where(tau >= settle, 1.0, 0.05)
        if task.timed and task.settle_s <= 0:  # only arriving on time counts, and staying there a little
            w = np.where(np.abs(tau - self.check) <= max(1, self.check // 10), 1.0, 0.0)
        w[self.check - 1] += 2.0
        self.weights = np.tile(w / w.sum(), self.goals)  # (K,)

    def goal_index(self, k: int) -> int:
        return k // self.per_goal

    def time_left(self, k: int) -> float:
        """Share of a goal's period left until its check, at the start of super-step k."""
        return (self.check - k % self.per_goal) / self.per_goal

    def check_steps(self) -> list[int]:
        """The states (indices into (K+1,)) at which the checks hold, one per goal."""
        return [g * self.per_goal + self.check for g in range(self.goals)]


class TargetDistance(nn.Module):
    """The weighted distance of states (B,S) to targets (B,S): √(Σ w_i d_i² + ε), d an angle's wrapped
    difference and a quaternion's difference to the nearer of ±target; a distance (not its square)
    keeps far starts from drowning out the last centimetres."""

    w: Tensor

    def __init__(self, manifest: Manifest, weights: tuple[float, ...]) -> None:
        super().__init__()
        angles: list[int] = []
        quats: list[int] = []
        for g in manifest.layout:
            if g.kind in ("angle", "heading"):
                angles += range(g.offset, g.offset + g.size)
            if g.kind in ("quaternion", "local_quaternion"):
                quats.append(g.offset)
        self.angles, self.quats = angles, quats
        self.register_buffer("w", torch.tensor(weights, dtype=torch.float32), persistent=False)

    def forward(self, state: Tensor, target: Tensor) -> Tensor:
        d = state - target
        if self.angles:
            d = d.clone()
            d[:, self.angles] = wrap(d[:, self.angles])
        for q in self.quats:
            dot = (state[:, q : q + 4] * target[:, q : q + 4]).sum(dim=1, keepdim=True)
            d = d.clone()
            d[:, q : q + 4] = state[:, q : q + 4] - torch.sign(dot + 1e-12) * target[:, q : q + 4]
        return torch.sqrt((self.w * d * d).sum(dim=1) + 1e-6)


class PolicyTrainer:
    """One policy being trained for a task through an artifact's emulator (module doc)."""

    def __init__(
        self,
        task: PolicyTask,
        path: Path,
        settings: PolicySettings,
        on_progress: Callable[[PolicyProgress], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> None:
        self.t0 = time.perf_counter()  # the budget counts everything: loading, drawing the goals
        self.task, self.settings = task, settings
        self.manifest = registry.read_manifest(path)
        self.path = path
        self.physical: PhysicalModel = registry.load_physical_model(path, self.manifest)
        self.emu = artifacts.load_emulator(path)
        self.step = frozen_step(self.emu)
        self.substeps = self.manifest.substeps
        self.schedule = Schedule(task, self.manifest.super_timestep)
        # a goal that moves is learned one period at a time: the gradient's path is one goal long,
        # and a batch covers four times the goals in the time of one whole run
        self.train_schedule = Schedule(task, self.manifest.super_timestep, 1 if task.goal_period_s else None)
        self.rng = np.random.default_rng(settings.seed)
        torch.manual_seed(settings.seed)
        self.on_progress, self.should_stop = on_progress, should_stop
        self.pool: GoalPool = reached_goals(self.physical, task, self.substeps, self.rng)
        self.mujoco_steps = self.pool.mujoco_steps
        self.net = PolicyNet(self._shape())
        self.distance = TargetDistance(self.manifest, task.state_weights)
        self.checks = CheckPenalty(task.success, self.manifest.layout, list(task.target_state))
        self.target = torch.tensor(task.target_state, dtype=torch.float32)
        self.goal_cols = task.goal_columns
        self.refinements = 0  # fine-tunings of the emulator on the policy's MuJoCo runs
        self.refined_on: tuple[FloatArray, FloatArray] | None = None  # (S,) lows and highs of their states

    def _shape(self) -> PolicyShape:
        task, m, pool = self.task, self.manifest, self.pool
        angles, plain, goal_angles, heading, planar = describe_columns(m.layout, task.goal_columns)
        quat, spatial, world_velocity = describe_body_frame(m.layout, task.goal_columns)
        goal_scale = np.maximum(pool.goals.std(axis=0), 0.1 * (np.asarray(task.goal.high) - task.goal.low))
        return PolicyShape(
            state_size=m.state_size,
            mean=tuple(float(v) for v in pool.state_mean),
            scale=tuple(float(v) for v in pool.state_scale),
            angle_columns=tuple(angles),
            plain_columns=tuple(plain),
            goal_columns=tuple(task.goal_columns),
            goal_scale=tuple(float(max(v, 1e-3)) for v in goal_scale),
            goal_angles=tuple(goal_angles),
            heading=heading,
            planar=tuple(planar),
            low=tuple(c.low for c in m.controls),
            high=tuple(c.high for c in m.controls),
            limit_low=tuple(max(c.limit_low, -1e9) for c in m.controls),
            limit_high=tuple(min(c.limit_high, 1e9) for c in m.controls),
            timed=task.timed,
            hidden=self.settings.hidden or task.hidden,
            quat=quat,
            spatial=tuple(spatial),
            world_velocity=tuple(world_velocity),
        )

    # ---------------------------------------------------------------- rollouts
    def draw(self, batch: int, goals_per_run: int | None = None) -> tuple[FloatArray, FloatArray]:
        """Starts (B, S) and goals (B, P, G), one goal per period of the run (``goals_per_run`` of them,
        default the task's)."""
        starts = sample_starts(self.physical, self.task, self.rng, batch)
        moves = self.schedule.goals if goals_per_run is None else goals_per_run
        goals = self.pool.draw_moving(self.rng, batch, moves, self.task.goal.max_move)
        return starts, goals

    def targets(self, goals: Tensor) -> Tensor:
        """Targets (B, P, S): the task's target state with each goal written in."""
        t = self.target.expand(goals.shape[0], goals.shape[1], -1).clone()
        t[:, :, self.goal_cols] = goals
        return t

    def rollout_loss(self, starts: FloatArray, goals: FloatArray) -> Tensor:
        """The weighted distance to the targets along a rollout through the emulator, plus control effort."""
        sch, cfg = self.train_schedule, self.settings
        s = torch.as_tensor(starts, dtype=torch.float32)
        g = torch.as_tensor(goals, dtype=torch.float32)
        targets = self.targets(g)
        total = torch.zeros(())
        for k in range(sch.steps):
            if k and cfg.truncate and k % cfg.truncate == 0:
                s = s.detach()
            i = sch.goal_index(k)
            left = torch.full((len(s), 1), sch.time_left(k))
            u = self.net(s, g[:, i], left)
            s = self.step(s, u)
            dist = self.distance(s, targets[:, i])
            effort = (self.net.normalised(u) ** 2).sum(dim=1)
            total = (
                total
                + float(sch.weights[k]) * dist.mean()
                + self.task.control_weight * effort.mean() / sch.steps
            )
        return total

    def check_margin(self, states: Tensor, targets: Tensor) -> Tensor:
        """(B,) how far states (B,S) are from meeting every success check with room to spare (each
        check's measure within half its bound): Σ_checks √max(0, r − ¼), r the measure over the bound,
        squared (``objectives.CheckPenalty``); about the measure in units of its bound once outside."""
        r = self.checks.residuals(states, CHECK_MARGIN, targets.to(states.dtype))
        return torch.sqrt(r + 1e-6).sum(dim=1)

    @torch.no_grad()
    def run(self, starts: FloatArray, goals: FloatArray, physics: bool) -> Evaluation:
        """The policy closed around MuJoCo (``physics``) or the emulator from starts (N, S) towards goals
        (N, P, G); success as the task's checks say, at every check step."""
        sch = self.schedule
        n = len(starts)
        states = np.zeros((n, sch.steps + 1, starts.shape[1]))
        controls = np.zeros((n, sch.steps, len(self.manifest.controls)))
        s = np.asarray(starts, dtype=np.float64)
        states[:, 0] = s
        for k in range(sch.steps):
            i = sch.goal_index(k)
            left = torch.full((n, 1), sch.time_left(k))
            u = self.net(torch.as_tensor(s, dtype=torch.float32), torch.as_tensor(goals[:, i]).float(), left)
            u_np = u.double().numpy()
            if physics:
                s = self.physical.step_held(s, u_np, None, self.substeps)
            else:
                s = self.step(torch.as_tensor(s, dtype=torch.float32), u).double().numpy()
            states[:, k + 1], controls[:, k] = s, u_np
        if physics:
            self.mujoco_steps += n * sch.steps * self.substeps
        return Evaluation(states, controls, self.successes(states, goals))

    def successes(self, states: FloatArray, goals: FloatArray) -> NDArray[np.bool_]:
        """(N,) whether each run meets every check at every goal's check step."""
        ok = np.ones(len(states), dtype=bool)
        labels = self.manifest.state_labels
        for i, k in enumerate(self.schedule.check_steps()):
            for r in range(len(states)):
                if not ok[r]:
                    continue
                target = np.asarray(self.task.target_with(goals[r, i]))
                final = states[r, k]
                ok[r] = (
                    bool(np.all(np.isfinite(final)))
                    and criteria.evaluate(self.task.success, final, target, labels)[0]
                )
        return ok

    # ---------------------------------------------------------------- refinement
    def refine_emulator(self, runs: Evaluation) -> None:
        """Fine-tune the emulator on the policy's MuJoCo runs (windows of 8 super-steps, the rollout
        loss), then rebuild the frozen step."""
        if not isinstance(self.emu, StructuredEmulator):
            return
        fine_tune_on_runs(
            self.emu,
            runs.states,
            runs.controls,
            self.manifest.train_config,
            self.settings.refine_seconds,
            int(self.rng.integers(1 << 30)),
            should_stop=self.should_stop,
        )
        self.step = frozen_step(self.emu)
        seen = runs.states.reshape(-1, runs.states.shape[-1])
        seen = seen[np.isfinite(seen).all(axis=1)]
        if len(seen):
            low, high = seen.min(axis=0), seen.max(axis=0)
            if self.refined_on is not None:
                low, high = np.minimum(low, self.refined_on[0]), np.maximum(high, self.refined_on[1])
            self.refined_on = (low, high)

    # ---------------------------------------------------------------- the loop
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def report(self, it: int, loss: float | None, success: float | None) -> None:
        if self.on_progress is not None:
            self.on_progress(
                {
                    "iteration": it,
                    "loss": loss,
                    "success_physics": success,
                    "mujoco_steps": self.mujoco_steps,
                    "elapsed_s": round(self.elapsed(), 3),
                }
            )

    def train(self) -> PolicyResult:
        cfg = self.settings
        opt = torch.optim.Adam(self.net.parameters(), lr=cfg.learning_rate)
        budget = cfg.seconds
        check_every = max(1.0, cfg.refine_every * budget)
        # counted from the first update: setup (the sandboxed compile, the goals drawn) is not training
        next_check = self.elapsed() + check_every
        best: tuple[float, dict[str, Tensor]] = (-1.0, copy.deepcopy(self.net.state_dict()))
        losses: list[float] = []
        successes: list[tuple[int, float]] = []
        last_success: float | None = None
        it, stop = 0, "budget"
        # at least one update, however much of the budget its setup took (goals drawn on a busy machine)
        while (it == 0 or self.elapsed() < budget) and (
            cfg.max_iterations is None or it < cfg.max_iterations
        ):
            if self.should_stop is not None and self.should_stop():
                stop = "cancelled"
                break
            for group in opt.param_groups:
                group["lr"] = cfg.learning_rate * (
                    0.55 + 0.45 * math.cos(math.pi * min(1.0, self.elapsed() / budget))
                )
            starts, goals = self.draw(cfg.batch, self.train_schedule.goals)
            loss = self.rollout_loss(starts, goals)
            opt.zero_grad()
            if torch.isfinite(loss):
                loss.backward()
                grads_ok = all(
                    p.grad is None or bool(torch.isfinite(p.grad).all()) for p in self.net.parameters()
                )
                if grads_ok:
                    nn.utils.clip_grad_norm_(self.net.parameters(), cfg.grad_clip)
                    opt.step()
            it += 1
            value = float(loss.detach()) if bool(torch.isfinite(loss)) else None
            if value is not None:
                losses.append(value)
            last = self.elapsed() >= budget or (cfg.max_iterations is not None and it >= cfg.max_iterations)
            if self.elapsed() >= next_check or last:
                next_check = self.elapsed() + check_every
                starts, goals = self.draw(cfg.refine_runs)
                runs = self.run(starts, goals, physics=True)
                emulated = self.run(starts, goals, physics=False)
                last_success = runs.rate
                successes.append((it, last_success))
                gap = abs(emulated.rate - runs.rate)
                log.info(
                    "%s: iteration %d, loss %.4g, success on MuJoCo %.2f, on the emulator %.2f",
                    self.task.name,
                    it,
                    value or float("nan"),
                    last_success,
                    emulated.rate,
                )
                if last_success >= best[0]:
                    best = (last_success, copy.deepcopy(self.net.state_dict()))
                # the model must be right where the policy goes: where the emulator's verdict on the
                # policy's runs differs from MuJoCo's, it learns from those runs
                if cfg.refine and gap > cfg.refine_gap and self.elapsed() < budget * 0.9:
                    self.refine_emulator(runs)
                    self.refinements += 1
            self.report(it, value, last_success)
        self.net.load_state_dict(best[1])
        return self.finish(it, losses, successes, stop)

    def finish(
        self, it: int, losses: list[float], successes: list[tuple[int, float]], stop: str
    ) -> PolicyResult:
        """The kept policy's success on held-out starts and goals, on MuJoCo and on the emulator (not
        measured, 0, for a training cancelled before its first check)."""
        if stop == "cancelled" and not successes:
            return PolicyResult(
                self.net, self.task, self.manifest, 0.0, 0.0, self.mujoco_steps, it, self.elapsed(),
                losses, successes, stop=stop, goals=self.pool.goals,
            )  # fmt: skip
        held_out = np.random.default_rng(self.settings.seed + 1_000_003)
        rng, self.rng = self.rng, held_out
        starts, goals = self.draw(self.settings.evaluate_runs)
        self.rng = rng
        phys = self.run(starts, goals, physics=True)
        # judged on the emulator it is served with: the refined one (stored beside it), else the stored one
        refined = self.emu if self.refinements > 0 and isinstance(self.emu, StructuredEmulator) else None
        self.step = frozen_step(refined if refined is not None else artifacts.load_emulator(self.path))
        emu = self.run(starts, goals, physics=False)
        return PolicyResult(
            net=self.net,
            task=self.task,
            manifest=self.manifest,
            success_physics=phys.rate,
            success_emulator=emu.rate,
            mujoco_steps=self.mujoco_steps,
            iterations=it,
            wall_s=self.elapsed(),
            loss_history=losses,
            success_history=successes,
            evaluate_runs=len(starts),
            stop=stop,
            refinements=self.refinements,
            goals=self.pool.goals,
            emulator=refined,
            envelope=self.refined_on if refined is not None else None,
        )


def train_policy(
    task: PolicyTask,
    path: Path,
    settings: PolicySettings | None = None,
    on_progress: Callable[[PolicyProgress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> PolicyResult:
    """Train a policy for ``task`` through the emulator artifact at ``path`` (module doc)."""
    settings = settings or PolicySettings(seconds=task.train_seconds)
    with torch_threads(settings.threads):
        return PolicyTrainer(task, path, settings, on_progress, should_stop).train()
