"""Reward policies learned through the emulator (SHAC-style, ``control.reward_policy``) on a suite
task, judged on MuJoCo with the suite's exact reward; and ``bench/policies.py`` on a suite task."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import logging
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from dm_control import suite
from fastapi.testclient import TestClient
from torch import Tensor

from neuroanimator.artifacts import registry
from neuroanimator.artifacts.policies import read_policy, resolve_policy
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.control import value_iteration
from neuroanimator.control.bptt import FastStep
from neuroanimator.control.exploring_runs import ExploringRuns, random_runs
from neuroanimator.control.planner import PlannerSettings, SamplingPlanner
from neuroanimator.control.planner_copy import CopySettings, PlannerCopy
from neuroanimator.control.policy import PolicySettings
from neuroanimator.control.policy_job import PolicyJobError, run_policy_job
from neuroanimator.control.random_search import (
    RandomSearch,
    SearchLearner,
    flat_weights,
    held_on_mujoco,
    set_weights,
)
from neuroanimator.control.reward_policy import (
    ChoicePolicy,
    Meeting,
    RewardPolicy,
    RewardProgress,
    RewardResult,
    RewardSettings,
    RewardTrainer,
    actor_rate,
    draw_starts,
    root_drift,
    run_on_mujoco,
)
from neuroanimator.control.seed_race import cores_used, thread_count, train_reward_policy
from neuroanimator.control.step_agreement import cosine, step_agreement
from neuroanimator.control.suite_tasks import SUITE_TASKS
from neuroanimator.control.value_iteration import ValueFitter, ValueIteration, candidate_controls
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim import sampling
from services.emulator.app import create_app
from services.emulator.settings import Settings
from tests.helpers import run_bench

TASK = SUITE_TASKS["point_mass-easy"]
# loading the model counts in the budget (seconds), and takes seconds of its own on a loaded machine
QUICK = RewardSettings(seconds=120.0, max_iterations=12, envs=16, horizon=8, critic_steps=2, eval_episodes=2,
                       final_episodes=2, refine_seconds=1.0, refine_gap=0.0, refine_keep=64)  # fmt: skip


@pytest.fixture(scope="module")
def artifacts(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small point-mass emulator at the task's control period, trained as a user would."""
    root = tmp_path_factory.mktemp("suite")
    xml = Path(suite.__file__).parent / "point_mass.xml"
    subprocess.run(
        [sys.executable, "-m", "neuroanimator.cli", "train", "--mjcf", str(xml), "--name", "point_mass",
         "--substeps", str(TASK.substeps), "--examples", "3000", "--epochs", "30", "--hidden", "32",
         "--rollout-steps", "0", "--force", "--quiet", "--out", str(root)],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    return root


def test_training_runs_on_mujoco_keeps_the_best_and_counts_its_steps(artifacts: Path) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    trainer = RewardTrainer(TASK, path, QUICK)
    result = trainer.train()
    assert result.iterations > 0 and result.return_history
    assert all(np.isfinite(r) and 0 <= r <= TASK.episode_steps for _, _, r in result.return_history)
    assert len(result.returns_physics) == QUICK.final_episodes
    assert 0 <= result.return_physics <= TASK.episode_steps and np.isfinite(result.return_emulator)
    # every MuJoCo step is counted: the checks' episodes, the final ones and the typical motion's windows
    episodes = QUICK.eval_episodes * len(result.return_history) + QUICK.final_episodes
    assert QUICK.refine_keep is not None
    typical = QUICK.refine_keep * (sampling.lead_steps(trainer.physical, TASK.substeps) + 8 * TASK.substeps)
    assert result.mujoco_steps == episodes * TASK.episode_steps * TASK.control_substeps + typical
    assert result.refinements >= 1  # the emulator learned from the policy's MuJoCo runs (any gap)
    # ... beside windows of the typical motion it was trained on, drawn once
    assert trainer.kept is not None and trainer.kept.states.shape[:2] == (QUICK.refine_keep, 9)
    # ... and its envelope now holds the states of the runs it learnt (the first check's, at least)
    seen = trainer.runs[0].states.reshape(-1, trainer.manifest.state_size)
    assert np.all(trainer.env_low.numpy() <= seen.min(axis=0) + 1e-6)
    assert np.all(trainer.env_high.numpy() >= seen.max(axis=0) - 1e-6)
    assert result.stop == "budget" and 0 <= result.outside_share < QUICK.max_outside
    assert result.root_drift_m is not None and 0 <= result.root_drift_m < 10
    assert result.greedy_agreement is None and result.greedy_regret is None  # no value to follow
    # the policy's controls stay in the actuators' range, on states far outside what it saw
    s = torch.randn(64, trainer.manifest.state_size) * 10
    u = trainer.policy(s, torch.zeros(64, 0))
    assert torch.all(u >= torch.tensor(trainer.low) - 1e-6) and torch.all(
        u <= torch.tensor(trainer.high) + 1e-6
    )


def test_training_rollouts_on_mujoco_follow_the_physics_with_the_emulators_gradient(artifacts: Path) -> None:
    """rollouts="mujoco": each training super-step's value is MuJoCo's, its gradient the emulator's at
    that state; a training so counts its rollouts' steps beside its checks' and learns."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    settings = replace(QUICK, rollouts="mujoco")
    trainer = RewardTrainer(TASK, path, settings)
    starts, _ = draw_starts(TASK, trainer.physical, np.random.default_rng(1), 4)
    x = torch.as_tensor(starts, dtype=torch.float32).requires_grad_(True)
    u = torch.as_tensor(np.random.default_rng(2).uniform(trainer.low, trainer.high, (4, len(trainer.low))))
    u = u.float().requires_grad_(True)
    stepped = trainer.step_on_mujoco(x, u)
    real = trainer.physical.step_held(starts, u.detach().double().numpy(), None, TASK.substeps)
    np.testing.assert_allclose(stepped.detach().numpy(), real, rtol=1e-5, atol=1e-5)
    emulated = trainer.step(x, u)
    assert not torch.allclose(emulated, stepped)  # the model is not the physics ...
    weights = torch.randn_like(stepped)
    for inputs in (x, u):  # ... but the gradient is the model's, to the state and to the controls
        (through_mujoco,) = torch.autograd.grad((stepped * weights).sum(), inputs, retain_graph=True)
        (through_model,) = torch.autograd.grad((emulated * weights).sum(), inputs, retain_graph=True)
        torch.testing.assert_close(through_mujoco, through_model)
    assert trainer.mujoco_steps == 4 * TASK.substeps
    trainer = RewardTrainer(TASK, path, settings)
    result = trainer.train()
    assert result.iterations > 0 and np.isfinite(result.return_physics)
    episodes = settings.eval_episodes * len(result.return_history) + settings.final_episodes
    assert settings.refine_keep is not None and settings.horizon is not None
    windows = settings.refine_keep if trainer.kept is not None else 0  # drawn when first refined
    typical = windows * (sampling.lead_steps(trainer.physical, TASK.substeps) + 8 * TASK.substeps)
    rollouts = result.iterations * settings.envs * settings.horizon * TASK.substeps
    assert result.mujoco_steps == episodes * TASK.episode_steps * TASK.control_substeps + typical + rollouts
    with pytest.raises(ValueError, match="rollouts run on one of emulator, mujoco"):
        RewardSettings(rollouts="sky")


def test_episodes_on_mujoco_sum_the_suites_reward_at_every_control_step(artifacts: Path) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    trainer = RewardTrainer(TASK, path, QUICK)
    starts, params = draw_starts(TASK, trainer.physical, np.random.default_rng(0), 3)
    at_rest = np.zeros((3, trainer.physical.num_controls))
    runs = run_on_mujoco(TASK, trainer.physical, trainer.ctx, lambda s, p: at_rest, starts, params)
    assert runs.states.shape == (3, TASK.policy_steps + 1, trainer.manifest.state_size)
    # with no force the mass stays where it started: the reward is its distance's, every step
    start_reward = TASK.reward(
        trainer.ctx, torch.as_tensor(starts), torch.as_tensor(at_rest), torch.zeros(3, 0), False
    )
    np.testing.assert_allclose(runs.returns, TASK.episode_steps * start_reward.numpy(), rtol=0.05, atol=1.0)


def test_the_roots_drift_is_the_distance_between_the_two_closed_loops(artifacts: Path) -> None:
    """``root_drift``: with MuJoCo itself as the step the two loops agree (0 m); with a step that
    stands still it is how far the root moved on MuJoCo in that second."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    trainer = RewardTrainer(TASK, path, QUICK)
    starts, params = draw_starts(TASK, trainer.physical, np.random.default_rng(4), 6)
    push = np.tile(trainer.high, (6, 1))  # full force: the mass moves off its start

    def act(s: Tensor, p: Tensor) -> Tensor:
        return torch.as_tensor(push[: len(s)], dtype=s.dtype)

    runs = run_on_mujoco(TASK, trainer.physical, trainer.ctx, lambda s, p: push, starts, params)

    def mujoco(s: Tensor, u: Tensor) -> Tensor:
        return torch.as_tensor(
            trainer.physical.step_held(s.double().numpy(), u.double().numpy(), None, TASK.substeps)
        )

    dt = trainer.manifest.super_timestep
    assert root_drift(mujoco, act, trainer.ctx, runs, dt) == pytest.approx(0.0, abs=1e-5)
    k = round(1.0 / dt)
    moved = np.linalg.norm(runs.states[:, k, :2] - runs.states[:, 0, :2], axis=1).mean()
    assert moved > 0.05
    assert root_drift(lambda s, u: s, act, trainer.ctx, runs, dt) == pytest.approx(moved, rel=1e-5)
    assert root_drift(mujoco, act, trainer.ctx, runs, dt, seconds=1e6) is None  # longer than the episodes


def test_rewarded_restarts_begin_where_the_reward_is_paid(artifacts: Path) -> None:
    """A reverse curriculum's restarts (the best paid of a few draws in the envelope) are paid more
    than draws anywhere in it, and stay in the envelope's box."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    paid = {}
    for share in (0.0, 1.0):
        trainer = RewardTrainer(TASK, path, replace(QUICK, rewarded_share=share, seed=3))
        params = np.zeros((512, 0))
        states = trainer.envelope_states(params)
        low, high = trainer.envelope_box()
        assert np.all(states >= low) and np.all(states <= high)
        u = torch.zeros(512, len(trainer.low), dtype=torch.float64)
        r = TASK.reward(trainer.ctx, torch.as_tensor(states), u, torch.as_tensor(params), True)
        paid[share] = float(r.mean())
    assert paid[1.0] > 1.5 * paid[0.0] > 0


def test_exploring_restarts_drawn_from_the_typical_motion_are_its_states(artifacts: Path) -> None:
    """``explore_from="motion"``: exploring restarts are states of runs of the typical motion on
    MuJoCo (sampled once, its steps counted), not draws in the envelope's box; another value is refused."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    settings = replace(QUICK, explore_share=1.0, mujoco_share=0.0, rewarded_share=0.5, explore_from="motion")
    trainer = RewardTrainer(TASK, path, settings)
    assert trainer.mujoco_steps == 0
    states, _ = trainer.restart(64)
    pool = trainer.typical_motion().states.reshape(-1, states.shape[1])
    assert trainer.mujoco_steps >= pool.size // states.shape[1] * TASK.substeps // 2
    for row in states:
        assert np.isclose(pool, row).all(axis=1).any()
    with pytest.raises(ValueError, match="explore_from is 'box' or 'motion', not 'grid'"):
        RewardTrainer(TASK, path, replace(QUICK, explore_from="grid"))


def test_failing_restarts_practise_the_episodes_that_earned_least(artifacts: Path) -> None:
    """``Restarts.failing``: restarts from MuJoCo drawn from the states of a check's episodes that
    earned under half its best; none failing (or none paid), from every run's; a share outside [0, 1]
    refused."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    settings = replace(QUICK, mujoco_share=1.0, explore_share=0.0, failing_share=1.0, refine=False)
    trainer = RewardTrainer(TASK, path, settings)
    runs = trainer.episodes(trainer.act, 4, np.random.default_rng(1))
    width = runs.states.shape[2]

    def drawn_from(states: np.ndarray) -> set[int]:
        return {
            int(np.flatnonzero([np.isclose(run, row).all(axis=1).any() for run in runs.states])[0])
            for row in states
        }

    trainer.keep_runs(replace(runs, returns=np.array([100.0, 10.0, 90.0, 60.0])), 0.0, may_refine=False)
    states, _ = trainer.restart(256)
    assert states.shape == (256, width) and drawn_from(states) == {1}  # 10 < half of 100: it failed
    trainer.restarts = replace(trainer.restarts, failing=0.0)
    assert drawn_from(trainer.restart(256)[0]) == {0, 1, 2, 3}
    fresh = RewardTrainer(TASK, path, settings)
    fresh.keep_runs(replace(runs, returns=np.zeros(4)), 0.0, may_refine=False)  # none paid: none failing
    assert not fresh.failed and drawn_from(fresh.restart(256)[0]) == {0, 1, 2, 3}
    with pytest.raises(ValueError, match=r"failing share of restarts from MuJoCo is in \[0, 1\], not 1.5"):
        RewardTrainer(TASK, path, replace(settings, failing_share=1.5))


def test_value_iterations_candidates_span_one_controls_range_and_sample_the_box_of_more() -> None:
    rng = np.random.default_rng(0)
    one = candidate_controls(np.array([-1.0]), np.array([1.0]), 5, rng)
    assert one[:, 0].tolist() == [-1.0, -0.5, 0.0, 0.5, 1.0]
    two = candidate_controls(np.array([-1.0, 0.0]), np.array([1.0, 2.0]), 6, rng)
    assert two.shape == (6, 2) and two[0].tolist() == [0.0, 1.0]  # the centre, then draws
    assert torch.all(two >= torch.tensor([-1.0, 0.0])) and torch.all(two <= torch.tensor([1.0, 2.0]))
    assert len(torch.unique(two[1:, 0])) == 5
    # a count that is k to the number of controls: the grid of k over each, corners and centre included
    grid = candidate_controls(np.array([-1.0, 0.0]), np.array([1.0, 2.0]), 9, rng)
    corners = {(x, z) for x in (-1.0, 0.0, 1.0) for z in (0.0, 1.0, 2.0)}
    assert {tuple(row) for row in grid.tolist()} == corners
    with pytest.raises(ValueError, match="share of the budget is in"):
        ValueIteration(share=1.0)
    with pytest.raises(ValueError, match="one pass over its targets"):
        ValueIteration(fit_epochs=0)
    with pytest.raises(ValueError, match="checks are every"):
        ValueIteration(check_every=-1)
    with pytest.raises(ValueError, match="at least one super-step, not 0"):
        ValueIteration(hold=0)
    with pytest.raises(ValueError, match=r"actor-critic share is in \[0, 1 − share\), not 0.3"):
        ValueIteration(share=0.8, actor_critic=0.3)
    with pytest.raises(ValueError, match="needs a copy its gradient reaches"):
        ValueIteration(actor_critic=0.1)  # a choice of the best-scored candidate has no gradient
    with pytest.raises(ValueError, match="value_iteration is settings, None or 'off'"):
        RewardSettings(value_iteration="on")


def test_exploring_runs_hold_random_controls_from_the_tasks_starts_and_the_emulator_learns_them(
    artifacts: Path,
) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    trainer = RewardTrainer(TASK, path, QUICK)
    how = ExploringRuns(runs=12, steps=10, hold=3, seconds=1.0)
    starts = trainer.start_states[:12]
    states, controls = random_runs(
        trainer.physical, starts, TASK.substeps, trainer.low, trainer.high, how, np.random.default_rng(0)
    )
    assert states.shape == (12, 11, trainer.manifest.state_size) and controls.shape == (12, 10, 2)
    assert np.array_equal(states[:, 0], starts) and np.isfinite(states).all()
    assert np.all(controls >= trainer.low) and np.all(controls <= trainer.high)
    # each control held three super-steps, then drawn anew
    assert np.array_equal(controls[:, 0], controls[:, 2])
    assert not np.array_equal(controls[:, 2], controls[:, 3])
    # the runs are MuJoCo's: the first super-step is MuJoCo's step from the start under its control
    again = trainer.physical.step_held(starts, controls[:, 0], None, TASK.substeps)
    assert np.allclose(states[:, 1], again)
    # before learning, the emulator is fine-tuned on such runs; their steps counted, their states in its envelope
    weights = copy.deepcopy(trainer.emu.state_dict())
    steps = trainer.mujoco_steps
    trainer.exploring = how
    trainer.explore()
    assert trainer.refinements == 1
    assert any(not torch.equal(weights[k], v) for k, v in trainer.emu.state_dict().items())
    assert QUICK.refine_keep is not None
    typical = QUICK.refine_keep * (sampling.lead_steps(trainer.physical, TASK.substeps) + 8 * TASK.substeps)
    assert trainer.mujoco_steps - steps == 12 * 10 * TASK.substeps + typical
    # a budget too small for them: fewer runs, fine-tuned on for less, in proportion
    small = RewardTrainer(TASK, path, replace(QUICK, seconds=8.0))
    small.exploring = replace(how, runs=100, seconds=4.0)
    steps = small.mujoco_steps
    small.explore()
    assert small.mujoco_steps - steps == 50 * 10 * TASK.substeps + typical
    with pytest.raises(ValueError, match="exploring runs are a count"):
        ExploringRuns(runs=-1)


def test_a_job_cancelled_while_its_emulator_is_fine_tuned_stops_there(artifacts: Path) -> None:
    """Cancelling does not wait for the exploring runs' fine-tuning to use its time: it ends between
    two batches, the emulator as it was before the first one, and nothing more is trained."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    explored: list[int] = []
    trainer = RewardTrainer(
        TASK, path, replace(QUICK, exploring=ExploringRuns(runs=16, steps=10, seconds=600.0)),
        should_stop=lambda: bool(explored),
    )  # fmt: skip
    real = trainer.explore

    def explore() -> None:
        explored.append(1)  # the cancel comes as the fine-tuning starts
        real()

    trainer.explore = explore  # type: ignore[method-assign]
    weights = copy.deepcopy(trainer.emu.state_dict())
    result = trainer.train()
    assert result.stop == "cancelled" and result.iterations == 0 and result.return_history == []
    assert all(torch.equal(weights[k], v) for k, v in trainer.emu.state_dict().items())


def held_by_hand(fitter: ValueFitter, s: Tensor, p: Tensor, cands: Tensor) -> tuple[Tensor, list[Tensor]]:
    """(C, B) each candidate held ``hold`` super-steps from states (B, S): its discounted rewards and
    the discounted V where it ends; and every reward paid on the way ((B,) each)."""
    trainer, hold = fitter.trainer, fitter.how.hold
    v_low, v_high = fitter.value_bounds()
    q, paid = [], []
    with torch.no_grad():
        for c in cands:
            u, x, total = c.expand(len(s), -1), s, torch.zeros(len(s))
            for k in range(hold):
                x = trainer.step(x, u)
                paid.append(fitter.score(x, u, p))
                total = total + trainer.gamma**k * paid[-1]
            q.append(total + trainer.gamma**hold * trainer.critic(x, p).clamp(v_low, v_high))
    return torch.stack(q), paid


@pytest.mark.parametrize(("hold", "rows"), [(1, value_iteration.BACKUP_ROWS), (3, 5)])
def test_value_iteration_backs_up_the_best_held_control(
    artifacts: Path, hold: int, rows: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The backup is, from each state, the best candidate's discounted rewards while it is held
    ``hold`` super-steps plus the discounted value where it ends (recomputed here by hand); the
    next states it gives are one super-step on, and V's bounds are the rewards seen over 1 − γ.
    Stepped in pieces of ``rows`` (5: pieces that cut across the candidates), the same."""
    monkeypatch.setattr(value_iteration, "BACKUP_ROWS", rows)
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(share=0.5, states=1024, candidates=5, batch=256, hold=hold)
    trainer = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how, seed=2))
    fitter = ValueFitter(trainer, how)
    s, p = fitter.box(16)
    cands = candidate_controls(trainer.low, trainer.high, 3, np.random.default_rng(1))
    y, pick, nxt = fitter.backup(s, p, trainer.critic, cands)
    q, paid = held_by_hand(fitter, s, p, cands)
    v_low, v_high = fitter.value_bounds()
    assert v_low == pytest.approx(min(float(r.min()) for r in paid) / (1 - trainer.gamma))
    assert v_high == pytest.approx(max(float(r.max()) for r in paid) / (1 - trainer.gamma))
    torch.testing.assert_close(y, q.max(dim=0).values, rtol=1e-4, atol=1e-5)
    assert torch.equal(pick, q.argmax(dim=0)) and nxt.shape == (3, 16, s.shape[1])
    with torch.no_grad():
        torch.testing.assert_close(nxt[1], trainer.step(s, cands[1].expand(16, -1)))


def test_value_iteration_learns_where_the_reward_is(artifacts: Path) -> None:
    """Fitted over the envelope, V is higher at the target at rest than in the box's corners, and
    the critic it fitted is the one the actor starts with."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(share=0.5, states=1024, candidates=5, batch=256, lr=3e-3, iterations=80)
    trainer = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how, seed=2))
    fitter = ValueFitter(trainer, how)

    assert fitter.fit(600.0) == 80  # its iterations bound it, not the seconds
    low, high = trainer.envelope_box()
    at_target = torch.zeros(1, len(low))
    corners = torch.tensor([[lo, lo2, 0.0, 0.0] for lo, lo2 in ((low[0], low[1]), (high[0], high[1]))])
    with torch.no_grad():
        v_target = float(trainer.critic(at_target, torch.zeros(1, 0)))
        v_corners = trainer.critic(corners.float(), torch.zeros(2, 0))
    assert v_target > float(v_corners.max()) + 1.0
    # the critic it fitted is the target critic the actor starts with
    for a, b in zip(trainer.critic.parameters(), trainer.target_critic.parameters(), strict=True):
        assert torch.equal(a, b)


def test_value_iteration_backs_up_the_least_of_its_values_and_keeps_the_best_checked(artifacts: Path) -> None:
    """With two values each starts from its own weights and the backup takes the least of them;
    every ``check_every`` iterations the greedy policy is run on the emulator, and the value kept
    is the one whose greedy policy earned most there."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(share=0.5, states=256, candidates=3, batch=128, iterations=6, critics=2,
                         check_every=2, check_episodes=4)  # fmt: skip
    trainer = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how, seed=3))
    fitter = ValueFitter(trainer, how)
    first, second = fitter.value.values
    assert first is trainer.critic
    s, p = fitter.box(16)
    with torch.no_grad():
        both = torch.stack([first(s, p), second(s, p)])
        assert not torch.equal(both[0], both[1])
        torch.testing.assert_close(fitter.value(s, p), both.min(dim=0).values)
    assert fitter.fit(600.0) == 6
    assert [at for at, _ in fitter.checks] == [2, 4, 6]
    best = max(earned for _, earned in fitter.checks)
    assert fitter.emulated_return() == pytest.approx(best, rel=1e-3, abs=1e-3)


def test_value_iterations_greedy_policy_runs_on_mujoco_and_its_runs_refine_the_emulator(
    artifacts: Path,
) -> None:
    """Every ``refine_every`` iterations the greedy policy runs on MuJoCo (its steps counted, its runs
    kept as restarts and learned by the emulator where its returns there and on MuJoCo differ); the
    last V is run too when its iteration had no run."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(share=0.5, states=256, candidates=3, batch=128, iterations=7, check_every=0,
                         refine_every=3, refine_episodes=2)  # fmt: skip
    trainer = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how))
    before = {k: v.clone() for k, v in trainer.emu.state_dict().items()}
    fitter = ValueFitter(trainer, how)
    fitter.fit(600.0)
    assert [at for at, _ in fitter.mujoco_checks] == [3, 6, 7]
    assert len(trainer.runs) == len(trainer.visited) == 3
    assert all(r.states.shape[0] == 2 for r in trainer.runs)
    per_run = 2 * TASK.episode_steps * TASK.control_substeps
    assert trainer.mujoco_steps >= 3 * per_run
    assert trainer.refinements == 3  # the gap that refines is 0 in QUICK: any gap refines
    assert any(not torch.equal(v, trainer.emu.state_dict()[k]) for k, v in before.items())
    with pytest.raises(ValueError, match="runs on MuJoCo"):
        ValueIteration(refine_every=-1)


def test_with_runs_on_mujoco_the_value_kept_is_the_one_whose_greedy_policy_earned_most_there(
    artifacts: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Checked on MuJoCo, the V kept is the best there, whatever it earned on the emulator."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(share=0.5, states=256, candidates=3, batch=128, iterations=6, check_every=2,
                         check_episodes=2, refine_every=2)  # fmt: skip
    trainer = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how))
    fitter = ValueFitter(trainer, how)
    earned = iter([5.0, 9.0, 1.0])
    seen: list[dict[str, Tensor]] = []

    def scripted() -> float:
        seen.append(copy.deepcopy(fitter.value.state_dict()))
        fitter.mujoco_checks.append((fitter.iterations, next(earned)))
        return fitter.mujoco_checks[-1][1]

    monkeypatch.setattr(fitter, "on_mujoco", scripted)
    fitter.fit(600.0)
    assert len(seen) == 3
    for k, v in fitter.value.state_dict().items():
        assert torch.equal(v, seen[1][k])


@pytest.mark.parametrize("copy_as", ["choice", "control"])
def test_value_iteration_copies_the_greedy_policy_into_the_network_round_by_round(
    artifacts: Path, copy_as: str
) -> None:
    """With ``value_iteration`` the value is fitted first, then each round copies the policy greedy
    over it (DAgger), is checked on MuJoCo and the best kept; the copy learns the greedy policy's
    choices ("choice": a ``ChoicePolicy`` over the value's own candidates) or its controls
    ("control"); "off" keeps the actor-critic whatever the task says."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(share=0.5, states=256, candidates=3, batch=128, iterations=5, episodes=8, epochs=6,
                         copy_as=copy_as)  # fmt: skip
    settings = replace(QUICK, value_iteration=how, max_iterations=4)
    trainer = RewardTrainer(TASK, path, settings)
    assert next(trainer.critic.parameters()).shape[0] == how.hidden[0]
    assert next(trainer.policy.net.parameters()).shape[0] == how.policy_hidden[0]
    before = copy.deepcopy(trainer.policy)
    result = trainer.train()
    assert result.iterations == 4 and [it for it, _, _ in result.return_history] == [1, 2, 3, 4]
    assert 0 <= result.return_physics <= TASK.episode_steps and result.stop == "budget"
    fitter = trainer.value_fitter
    assert fitter is not None and fitter.iterations == how.iterations
    ((states, params, values),) = fitter.labels  # every round's, joined: each candidate's value
    assert len(states) == 4 * how.episodes * TASK.policy_steps and values.shape == (len(states), 3)
    greedy = fitter.grid[values.argmax(dim=1)]
    with torch.no_grad():
        copied, untrained = trainer.policy(states, params), before(states, params)
    if copy_as == "choice":
        assert isinstance(trainer.policy, ChoicePolicy) and torch.equal(trainer.policy.choices, fitter.grid)
        # every control it gives is one of the candidates, and more of them the greedy policy's
        chosen = (copied[:, None, :] == fitter.grid[None]).all(dim=2)
        assert bool(chosen.any(dim=1).all())
        agree = float((copied == greedy).all(dim=1).float().mean())
        assert agree > float((untrained == greedy).all(dim=1).float().mean()) + 0.1
        # the result says how often it takes the greedy choice where it drives, and what it loses
        assert result.greedy_agreement is not None and 0.0 < result.greedy_agreement <= 1.0
        assert result.greedy_regret is not None and result.greedy_regret >= 0.0
        trainer.policy.load_state_dict(before.state_dict())
        untrained_agreement, untrained_regret = fitter.follows()
        assert result.greedy_agreement > untrained_agreement
        assert result.greedy_regret < untrained_regret
    else:
        assert type(trainer.policy) is RewardPolicy
        err = float(((copied - greedy) ** 2).mean())
        assert err < 0.7 * float(((untrained - greedy) ** 2).mean())  # the kept round: the best on MuJoCo
        assert result.greedy_regret is not None and result.greedy_regret >= 0.0
        assert result.greedy_agreement is not None and 0.0 <= result.greedy_agreement <= 1.0
    # "off" keeps the actor-critic whatever the task says
    off = RewardTrainer(replace(TASK, value_iteration=how), path, replace(QUICK, value_iteration="off"))
    assert off.value_iteration is None and next(off.critic.parameters()).shape[0] == QUICK.critic_hidden[0]
    assert type(off.policy) is RewardPolicy


def test_value_iteration_hands_its_best_copy_and_its_value_to_the_actor_critic(
    artifacts: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``actor_critic``: the copy's rounds end that share of the budget early, and the actor-critic
    trains on from the best copy with the fitted V as its critic (its target the same), its
    iterations counted after the rounds and its checks beside theirs in the history."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(share=0.01, states=256, candidates=3, batch=128, iterations=3, episodes=4, epochs=2,
                         blend=1.0, actor_critic=0.98)  # fmt: skip
    # a budget its iterations end well within, on a busy machine too (the measure after the
    # actor-critic is kept from its end at the greedy episodes' pace)
    trainer = RewardTrainer(TASK, path, replace(QUICK, seconds=600.0, value_iteration=how, max_iterations=5))
    copies: list[dict[str, Tensor]] = []
    copy_round = ValueFitter.copy_round

    def recorded_round(fitter: ValueFitter, index: int, opt: torch.optim.Optimizer) -> float:
        loss = copy_round(fitter, index, opt)
        copies.append(copy.deepcopy(trainer.policy.state_dict()))
        return loss

    monkeypatch.setattr(ValueFitter, "copy_round", recorded_round)
    began: list[tuple[dict[str, Tensor], bool, bool]] = []
    iterate = trainer.iterate

    def recorded_iterate(s: Tensor, p: Tensor, opt_actor: Any, opt_critic: Any) -> tuple[Tensor, float]:
        critic, target = trainer.critic.state_dict(), trainer.target_critic.state_dict()
        fitted = trainer.value_fitter is not None and trainer.critic is trainer.value_fitter.value.values[0]
        synced = all(torch.equal(critic[k], target[k]) for k in critic)
        began.append((copy.deepcopy(trainer.policy.state_dict()), fitted, synced))
        return iterate(s, p, opt_actor, opt_critic)

    monkeypatch.setattr(trainer, "iterate", recorded_iterate)
    learn = trainer.learn
    annealed: list[tuple[float, float]] = []  # (anneal_from, seconds into the budget it was given)

    def recorded_learn(best: Any, history: Any, it: int, anneal_from: float = 0.0) -> Any:
        annealed.append((anneal_from, trainer.elapsed()))
        return learn(best, history, it, anneal_from=anneal_from)

    monkeypatch.setattr(trainer, "learn", recorded_learn)
    result = trainer.train()
    rounds = len(copies)
    assert rounds >= 1 and result.iterations == 5 and len(began) == 5 - rounds
    # its learning rate annealed from where it begins, not from the budget's start
    assert len(annealed) == 1 and 0.0 < annealed[0][0] <= annealed[0][1]
    # the first actor-critic update starts from the copy checked best (one round: that round's)
    if rounds == 1:
        assert all(torch.equal(began[0][0][k], v) for k, v in copies[0].items())
    assert began[0][1] and began[0][2]  # the fitted value is its critic, the target synced with it
    # its end leaves time for measuring how closely the policy follows the greedy one
    assert trainer.value_fitter is not None and trainer.measure_after_s > 0.0
    its = [it for it, _, _ in result.return_history]
    assert its[:rounds] == list(range(1, rounds + 1)) and its[-1] == 5
    assert 0 <= result.return_physics <= TASK.episode_steps and result.greedy_agreement is not None


def test_the_actors_rate_falls_on_a_cosine_to_a_tenth_from_where_it_is_annealed() -> None:
    """``actor_rate``: over the whole budget by default; from ``anneal_from`` (the actor-critic
    after value iteration) the full rate there, a tenth at the end, falling in between."""
    assert actor_rate(2e-3, 0.0, 100.0) == pytest.approx(2e-3)
    assert actor_rate(2e-3, 70.0, 100.0) == pytest.approx(2e-3 * (0.1 + 0.45 * (1 + math.cos(0.7 * math.pi))))
    assert actor_rate(2e-3, 70.0, 100.0, anneal_from=70.0) == pytest.approx(2e-3)
    assert actor_rate(2e-3, 50.0, 100.0, anneal_from=70.0) == pytest.approx(2e-3)  # before: the full rate
    rates = [actor_rate(2e-3, t, 100.0, anneal_from=70.0) for t in (70.0, 80.0, 90.0, 100.0, 130.0)]
    assert all(a > b for a, b in itertools.pairwise(rates[:4]))
    assert rates[3] == pytest.approx(2e-4) and rates[4] == pytest.approx(2e-4)  # past the end: a tenth
    assert actor_rate(2e-3, 100.0, 100.0, anneal_from=100.0) == pytest.approx(2e-3)  # no span: no fall


def _recorded(evaluate: Callable[[int, int], Any], calls: list[tuple[int, int]]) -> Callable[[int, int], Any]:
    """``evaluate`` (episodes, seed), each call's arguments kept in ``calls``."""

    def recorded(n: int, seed: int) -> Any:
        calls.append((n, seed))
        return evaluate(n, seed)

    return recorded


def test_value_iterations_rounds_are_checked_on_the_same_starts_when_fixed(
    artifacts: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``fixed_checks``: every round of copying is checked on MuJoCo from one set of starts, drawn
    once, and the final episodes are still the judged ones; without it each round draws new starts.
    Every check's MuJoCo steps are counted."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(
        share=0.5, states=256, candidates=3, batch=128, iterations=2, episodes=4, check_episodes=4
    )
    for fixed in (3, None):
        settings = replace(QUICK, value_iteration=replace(how, fixed_checks=fixed), max_iterations=3)
        trainer = RewardTrainer(TASK, path, settings)
        calls: list[tuple[int, int]] = []
        monkeypatch.setattr(trainer, "evaluate", _recorded(trainer.evaluate, calls))
        result = trainer.train()
        rounds, final = calls[:-1], calls[-1]
        assert final == (settings.final_episodes, settings.judged_on)
        assert [n for n, _ in rounds] == [fixed or settings.eval_episodes] * 3
        assert len({seed for _, seed in rounds}) == (1 if fixed else 3)
        episodes = sum(n for n, _ in calls)
        assert result.mujoco_steps == episodes * TASK.episode_steps * TASK.control_substeps
    with pytest.raises(ValueError, match="fixed checks"):
        ValueIteration(fixed_checks=0)


def test_the_copys_cross_entropy_weighs_each_state_by_its_stakes(artifacts: Path) -> None:
    """A state whose candidates are worth the same (nothing at stake) teaches the copy nothing, one
    with a wide gap between its best and worst twice what a gap half as wide does; ``stakes=False``
    weighs every state alike."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(candidates=3)
    trainer = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how))
    fitter = ValueFitter(trainer, how)
    assert isinstance(trainer.policy, ChoicePolicy)
    s, p = fitter.box(3)
    values = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.5, 1.0], [0.0, 1.0, 2.0]])
    soft = torch.softmax((values - values.max(dim=1, keepdim=True).values) / how.temperature, dim=1)
    with torch.no_grad():
        each = torch.nn.functional.cross_entropy(trainer.policy.scores(s, p), soft, reduction="none")
        weighed = fitter.copy_loss(s, p, values)
        alike = ValueFitter(trainer, replace(how, stakes=False)).copy_loss(s, p, values)
    torch.testing.assert_close(weighed, (each[1] + 2 * each[2]) / 3)
    torch.testing.assert_close(alike, each.mean())
    # every state a tie: nothing to learn, and a loss that says so rather than a NaN
    assert float(fitter.copy_loss(s, p, torch.ones(3, 3))) == 0.0


def test_a_choosing_policy_exports_its_choice_and_its_range(artifacts: Path) -> None:
    """A ``ChoicePolicy``'s graph gives the candidate its scores rank first, as torch does, and
    records the candidates' range as the range its controls never leave."""
    import onnx
    import onnxruntime as ort

    from neuroanimator.export.driven import CONTROLS_RANGE
    from neuroanimator.export.policy import policy_to_onnx

    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(candidates=4)
    trainer = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how))
    policy = trainer.policy
    assert isinstance(policy, ChoicePolicy) and policy.choices.shape == (4, 2)
    graph = policy_to_onnx(policy, trainer.manifest.state_size, 0, False, reads_time=False)
    s = torch.as_tensor(trainer.box_states(64), dtype=torch.float32)
    with torch.no_grad():
        want = policy(s, torch.zeros(64, 0))
        ranks = policy.scores(s, torch.zeros(64, 0)).argmax(dim=1)
    torch.testing.assert_close(want, policy.choices[ranks])
    got = ort.InferenceSession(graph).run(None, {"state": s.numpy(), "goal": np.zeros((64, 0), np.float32)})[
        0
    ]
    np.testing.assert_allclose(got, want.numpy(), rtol=0, atol=1e-6)
    meta = {p.key: p.value for p in onnx.load_from_string(graph).metadata_props}
    low, high = json.loads(meta[CONTROLS_RANGE])
    assert low == pytest.approx(policy.choices.min(dim=0).values.tolist())
    assert high == pytest.approx(policy.choices.max(dim=0).values.tolist())
    # blended (``ValueIteration.blend``): the candidates averaged by the scores' softmax, in torch and
    # in the graph alike, controls between the choices and inside their range, none of them a choice
    blending = RewardTrainer(TASK, path, replace(QUICK, value_iteration=replace(how, blend=0.5))).policy
    assert isinstance(blending, ChoicePolicy) and blending.blend == 0.5
    with torch.no_grad():
        mixed = blending(s, torch.zeros(64, 0))
        weights = torch.softmax(blending.scores(s, torch.zeros(64, 0)) / 0.5, dim=1)
    torch.testing.assert_close(mixed, weights @ blending.choices)
    assert not torch.isclose(mixed[:, None, :], blending.choices[None]).all(dim=2).any()
    assert bool((mixed >= blending.choices.min(dim=0).values - 1e-6).all())
    assert bool((mixed <= blending.choices.max(dim=0).values + 1e-6).all())
    graph = policy_to_onnx(blending, trainer.manifest.state_size, 0, False, reads_time=False)
    got = ort.InferenceSession(graph).run(None, {"state": s.numpy(), "goal": np.zeros((64, 0), np.float32)})[
        0
    ]
    np.testing.assert_allclose(got, mixed.numpy(), rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="blend is a temperature above 0"):
        ValueIteration(blend=0.0)
    # a policy that copies the planner first regresses onto its controls: it chooses nothing
    first_planner = RewardTrainer(TASK, path, replace(QUICK, value_iteration=how, teacher="planner"))
    assert type(first_planner.policy) is RewardPolicy
    with pytest.raises(ValueError, match="copies as one of choice, control, not 'both'"):
        ValueIteration(copy_as="both")
    with pytest.raises(ValueError, match="temperature is above 0"):
        ValueIteration(temperature=0.0)


def test_an_emulator_at_another_control_period_is_refused(artifacts: Path) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    with pytest.raises(ValueError, match="acts every 5 physical steps"):
        RewardTrainer(replace(TASK, substeps=5), path, QUICK)


def test_seeds_side_by_side_are_judged_on_the_same_episodes_and_the_best_is_kept(artifacts: Path) -> None:
    """``seeds=2``: two processes train seeds 5 and 6, both judged on the episodes of ``judged_on``;
    the kept policy is the best one's (its return is its own on those episodes, run again here),
    every seed's MuJoCo steps count, and progress is one stream."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    race = replace(QUICK, seed=5, seeds=2)
    progress: list[RewardProgress] = []
    result = train_reward_policy(TASK, path, race, on_progress=progress.append)
    assert len(result.seed_returns) == 2 and result.return_physics == max(result.seed_returns)
    assert result.seed == 5 + result.seed_returns.index(result.return_physics)
    trainer = RewardTrainer(TASK, path, QUICK)
    starts, params = draw_starts(
        TASK, trainer.physical, np.random.default_rng(race.judged_on), QUICK.final_episodes
    )
    again = run_on_mujoco(TASK, trainer.physical, trainer.ctx, result.policy.act, starts, params)
    assert again.mean == pytest.approx(result.return_physics, rel=1e-9)
    # each seed ran at least one check and the final episodes on MuJoCo
    episode = TASK.episode_steps * TASK.control_substeps
    assert result.mujoco_steps >= 2 * (QUICK.eval_episodes + QUICK.final_episodes) * episode
    assert progress and {"iteration", "loss", "return_physics", "mujoco_steps", "elapsed_s"} <= set(
        progress[-1]
    )
    assert progress[-1]["mujoco_steps"] > progress[0]["mujoco_steps"]  # both seeds' steps, growing


def test_a_seed_behind_when_the_seeds_meet_trains_on_from_the_best_ones_policy(artifacts: Path) -> None:
    """``meet_at``: at its first check past that share of the budget a seed meets the others; told
    of a better one, it takes that one's policy and critics, keeps it as its best, and says so."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    donor = RewardTrainer(TASK, path, replace(QUICK, seed=9))
    theirs = Meeting(
        99, 1e9, donor.policy.state_dict(), donor.critic.state_dict(), donor.target_critic.state_dict()
    )
    brought: list[Meeting] = []

    def meet(mine: Meeting) -> Meeting:
        brought.append(mine)
        return theirs

    result = RewardTrainer(TASK, path, replace(QUICK, seed=1, meet_at=0.0), meet=meet).train()
    (mine,) = brought  # once
    assert mine.seed == 1 and math.isfinite(mine.best_return) and result.took_from == 99
    kept = result.policy.state_dict()
    assert all(torch.equal(kept[k], v) for k, v in theirs.policy.items())  # no later check beat 1e9
    # a seed told to keep its own (None) keeps it
    alone = RewardTrainer(TASK, path, replace(QUICK, seed=1, meet_at=0.0), meet=lambda m: None).train()
    assert alone.took_from is None
    assert not all(torch.equal(alone.policy.state_dict()[k], v) for k, v in theirs.policy.items())


def test_seeds_side_by_side_meet_and_go_on_from_the_best(
    artifacts: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two seeds meeting at their last check: the one behind takes the other's best policy, so both
    are judged with the same policy on the same final episodes."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    caplog.set_level(logging.INFO, logger="neuroanimator.control.seed_race")
    result = train_reward_policy(TASK, path, replace(QUICK, seed=5, seeds=2, meet_at=0.0))
    assert "the seeds met" in caplog.text
    assert len(result.seed_returns) == 2 and result.seed_returns[0] == result.seed_returns[1]
    assert result.took_from in (None, 5, 6) and result.took_from != result.seed


MEETING_VALUES = ValueIteration(share=0.01, states=256, candidates=3, batch=128, iterations=3, episodes=4,
                                epochs=2, refine_every=3, refine_episodes=2, meet=True)  # fmt: skip


def test_a_seed_whose_value_is_behind_copies_the_best_ones_value(
    artifacts: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ValueIteration.meet``: once its value is fitted a seed brings the value and its check; told
    of a better one, it copies that value instead of its own, and says whose it took. Told to keep
    its own (None), it copies its own."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    settings = replace(QUICK, seed=1, value_iteration=MEETING_VALUES, max_iterations=2)
    donor = RewardTrainer(TASK, path, replace(settings, seed=9))
    donated = ValueFitter(donor, MEETING_VALUES).value.state_dict()
    theirs = Meeting(99, 1e9, donor.policy.state_dict(), donated, donor.target_critic.state_dict())
    brought: list[Meeting] = []
    copied_from: list[dict[str, Tensor]] = []
    copy_round = ValueFitter.copy_round

    def recorded_round(fitter: ValueFitter, index: int, opt: torch.optim.Optimizer) -> float:
        copied_from.append(copy.deepcopy(fitter.value.state_dict()))
        return copy_round(fitter, index, opt)

    monkeypatch.setattr(ValueFitter, "copy_round", recorded_round)

    def meet(mine: Meeting) -> Meeting:
        brought.append(mine)
        return theirs

    result = RewardTrainer(TASK, path, settings, meet=meet).train()
    (mine,) = brought  # once, with the value's check on MuJoCo
    assert mine.seed == 1 and math.isfinite(mine.best_return) and result.took_from == 99
    assert all(torch.equal(copied_from[0][k], v) for k, v in donated.items())
    copied_from.clear()
    alone = RewardTrainer(TASK, path, settings, meet=lambda m: None).train()
    assert alone.took_from is None
    assert not all(torch.equal(copied_from[0][k], v) for k, v in donated.items())


def test_seeds_side_by_side_meet_when_their_values_are_fitted(
    artifacts: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two seeds whose value iteration says ``meet``: they meet once, after their values (no
    ``meet_at``), and the one behind says whose value it took."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    caplog.set_level(logging.INFO, logger="neuroanimator.control.seed_race")
    settings = replace(QUICK, seed=5, seeds=2, value_iteration=MEETING_VALUES, max_iterations=2)
    result = train_reward_policy(TASK, path, settings)
    assert caplog.text.count("the seeds met") == 1
    assert (
        len(result.seed_returns) == 2 and result.took_from in (None, 5, 6) and result.took_from != result.seed
    )
    with pytest.raises(ValueError, match="meet on their values' checks on MuJoCo"):
        replace(MEETING_VALUES, refine_every=0)
    with pytest.raises(ValueError, match="meet once"):  # one meeting: the values', or meet_at's
        RewardTrainer(TASK, path, replace(settings, meet_at=0.5))


def test_seeds_side_by_side_stop_together_and_raise_what_one_seed_raises(artifacts: Path) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    result = train_reward_policy(TASK, path, replace(QUICK, seeds=2), should_stop=lambda: True)
    assert result.stop == "cancelled" and len(result.seed_returns) == 2
    with pytest.raises(ValueError, match="acts every 5 physical steps"):
        train_reward_policy(replace(TASK, substeps=5), path, replace(QUICK, seeds=2))


def test_a_seed_alone_trains_on_the_tasks_threads_unless_the_settings_say(artifacts: Path) -> None:
    """One seed trains on its task's threads (the acrobot's two), or the settings' where they say, at
    most the machine's cores, and gives the caller's count back; seeds side by side take a core each."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    cores, before = os.cpu_count() or 1, torch.get_num_threads()
    seen: list[int] = []

    def record() -> bool:
        seen.append(torch.get_num_threads())
        return False

    train_reward_policy(replace(TASK, threads=2), path, QUICK, should_stop=record)
    assert seen and set(seen) == {min(2, cores)} and torch.get_num_threads() == before
    assert thread_count(replace(TASK, threads=2), replace(QUICK, threads=1)) == 1
    assert thread_count(replace(TASK, threads=4 * cores), QUICK) == cores
    assert cores_used(SUITE_TASKS["acrobot-swingup"], RewardSettings()) == min(2, cores)
    assert cores_used(TASK, replace(QUICK, seeds=2)) == min(2, cores) and cores_used(TASK, QUICK) == 1


@pytest.mark.parametrize("learner", ["value iteration", "actor-critic"])
def test_a_training_ends_within_its_budget_its_final_judging_included(
    artifacts: Path, monkeypatch: pytest.MonkeyPatch, learner: str
) -> None:
    """``seconds`` is the whole training's: learning stops early enough for its last check, the final
    episodes on MuJoCo and (value iteration) the measure of how closely the copy follows, at the pace
    they ran so far (here half a second an episode on MuJoCo on top of its own: a training that judged
    after its budget would end seconds past it), and (value iteration) a round of copying foreseen to
    take longer than the one before, as its labels grow (here 2 s more each round: a round foreseen as
    long as the last would end past the budget). Episodes of 200 steps, so that rounds are short."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = ValueIteration(
        share=0.2,
        states=256,
        candidates=3,
        batch=128,
        iterations=2,
        episodes=4,
        fixed_checks=2,
        check_episodes=8,
    )
    settings = replace(
        QUICK,
        seconds=20.0,
        max_iterations=None,
        value_iteration=how if learner == "value iteration" else "off",
    )
    trainer = RewardTrainer(replace(TASK, episode_steps=200), path, settings)
    episodes = trainer.episodes

    def slow_episodes(act: Any, n: int, rng: np.random.Generator) -> Any:
        time.sleep(0.5 * n)
        return episodes(act, n, rng)

    monkeypatch.setattr(trainer, "episodes", slow_episodes)
    copy_round = ValueFitter.copy_round
    rounds: list[int] = []

    def growing_rounds(fitter: ValueFitter, round_index: int, opt: torch.optim.Optimizer) -> float:
        rounds.append(round_index)
        time.sleep(2.0 * round_index)
        return copy_round(fitter, round_index, opt)

    monkeypatch.setattr(ValueFitter, "copy_round", growing_rounds)
    result = trainer.train()
    assert len(rounds) >= 2 or learner == "actor-critic"
    assert len(result.return_history) >= 2 and trainer.episode_check_s >= 0.5
    assert 0.6 * settings.seconds <= result.wall_s <= settings.seconds + 0.5
    assert trainer.deadline() < settings.seconds - settings.final_episodes * 0.5


def test_bench_policies_runs_a_suite_task(artifacts: Path) -> None:
    lines, result = run_bench(
        "bench/policies.py", "--quick", "--tasks", "point_mass-easy", "--artifacts", str(artifacts),
        "--seeds", "2",
    )  # fmt: skip
    (row,) = result["tasks"]
    assert row["task"] == "point_mass-easy" and row["substeps"] == TASK.substeps
    # --seeds over the task's one: each seed's return in the row, SAC on as many cores
    sides = min(2, os.cpu_count() or 1)
    assert result["settings"]["seeds"] == 2 and len(row["seeds"]) == sides == row["cores"]
    # and whose policy each took when they met (None: its own; point_mass's seeds do not meet)
    assert all(seed["took_from"] is None for seed in row["seeds"])
    assert result["settings"]["baseline"] is True
    for key in ("return_physics", "return_emulator", "mujoco_steps", "wall_s"):
        assert isinstance(row[key], (int, float))
    # found in --artifacts, not trained again: its training's seconds count in the wall time all the same
    assert not row["emulator_trained_here"] and 0 < row["emulator_wall_s"] < row["wall_s"]
    assert row["model_free"]["algorithm"] == "sac" and row["model_free"]["env_steps"] > 0
    assert row["greedy_agreement"] is None and row["greedy_regret"] is None  # the actor-critic's
    # the root's drift on the training's final episodes and on the held-out ones the return is
    assert row["root_drift_1s_m"] >= 0.0 and row["root_drift_1s_m_held_out"] >= 0.0
    # ... and whether its emulator tells the policy's neighbours apart as MuJoCo does (quick: 4 directions, 1 start)
    agreement = row["step_agreement"]
    assert (agreement["directions"], agreement["episodes"]) == (4, 1)
    assert agreement["mujoco_steps"] == 2 * 8 * TASK.policy_steps * TASK.substeps
    assert agreement["cosine"] is None or -1.0 <= agreement["cosine"] <= 1.0
    assert agreement["mujoco_across_starts"] is None or -1.0 <= agreement["mujoco_across_starts"] <= 1.0
    assert any(line.startswith("| point_mass-easy |") for line in lines)


def test_bench_policies_without_the_baseline_measures_the_policy_alone(artifacts: Path) -> None:
    """--no-baseline: the policy's row as before, no SAC trained (its columns dashes, model_free null);
    --set changes the policy's settings for the run (here its iterations, its layers, and settings of
    their own given as a JSON object, echoed with their defaults)."""
    lines, result = run_bench(
        "bench/policies.py", "--quick", "--tasks", "point_mass-easy", "--artifacts", str(artifacts),
        "--no-baseline", "--set", "max_iterations=2", "--set", "hidden=[32, 32]",
        "--set", 'exploring={"runs": 0, "hold": 2}',
    )  # fmt: skip
    (row,) = result["tasks"]
    assert result["settings"]["baseline"] is False and row["model_free"] is None
    given = result["settings"]["set"]
    assert given["exploring"] == {**dataclasses.asdict(ExploringRuns()), "runs": 0, "hold": 2}
    assert {k: given[k] for k in ("max_iterations", "hidden")} == {"max_iterations": 2, "hidden": [32, 32]}
    assert row["iterations"] == 2
    assert isinstance(row["return_physics"], float) and row["wall_s"] > row["emulator_wall_s"] > 0
    (line,) = [line for line in lines if line.startswith("| point_mass-easy |")]
    assert line.endswith("| - | - | - |")


@pytest.mark.parametrize(
    ("pair", "says"),
    [
        ("nois=0.3", "KEY one of"),  # no such setting
        ("seed=3", "the bench's own flag"),  # --seed's
        ("noise=loud", "is a number"),
        ("teacher=oracle", "teacher is one of"),  # a value the settings refuse
        ('value_iteration={"candidate": 3}', "has no field candidate"),  # settings of their own
        ('value_iteration={"share": 1.5}', "share of the budget"),  # ... that they refuse
        ('noise={"loud": true}', "holds no settings of its own"),
    ],
)
def test_bench_policies_refuses_a_setting_it_cannot_apply(pair: str, says: str) -> None:
    with pytest.raises(subprocess.CalledProcessError) as refused:
        run_bench("bench/policies.py", "--quick", "--tasks", "point_mass-easy", "--set", pair)
    assert "--set" in refused.value.stderr and says in refused.value.stderr


def test_bench_policies_measures_the_baseline_alone() -> None:
    """--baseline-only: SAC alone on the task's MuJoCo model (no emulator, no policy: their columns
    dashes), judged on the held-out starts; refused with --no-baseline or a catalog task."""
    lines, result = run_bench("bench/policies.py", "--quick", "--tasks", "point_mass-easy", "--baseline-only")
    (row,) = result["tasks"]
    assert result["settings"]["baseline_only"] is True and row["return_physics"] is None
    free = row["model_free"]
    assert free["algorithm"] == "sac" and free["env_steps"] > 0 and free["threads"] == 1
    assert 0.0 <= free["return_physics"] <= TASK.episode_steps
    (line,) = [line for line in lines if line.startswith("| point_mass-easy |")]
    assert line.startswith(f"| point_mass-easy | {TASK.substeps} | - | - |")
    for wrong in (["point_mass-easy", "--no-baseline"], [next(iter(POLICY_TASKS))]):
        with pytest.raises(subprocess.CalledProcessError) as refused:
            run_bench("bench/policies.py", "--quick", "--baseline-only", "--tasks", *wrong)
        assert "--baseline-only" in refused.value.stderr


def test_the_driven_step_benchmark_drives_a_suite_tasks_model(artifacts: Path, tmp_path: Path) -> None:
    """bench/driven_step.py over a suite task's policy: trained briefly through the task's emulator in
    the data directory when none is stored there, then its sessions stepped driven and undriven."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(artifacts, data, symlinks=True)
    _, r = run_bench(
        "bench/driven_step.py", "--policy", TASK.name, "--sessions", "1,4", "--seconds", "0.05",
        "--data-dir", str(data),
    )  # fmt: skip
    assert (r["model"], r["policy"]) == ("point_mass", TASK.name)
    assert [row["sessions"] for row in r["rows"]] == [1, 4]
    assert all(row["driven_us"] > 0 and row["ort_composed_us"] > 0 for row in r["rows"])
    stored = resolve_policy(registry.Roots(data), "point_mass", TASK.name)
    assert stored.is_relative_to(data) and read_policy(stored).name == TASK.name
    with pytest.raises(subprocess.CalledProcessError) as refused:  # a task of no emulator there
        run_bench("bench/driven_step.py", "--policy", "acrobot-swingup", "--data-dir", str(data))
    assert "no acrobot emulator" in refused.value.stderr


CHOOSING = replace(
    QUICK,
    max_iterations=2,
    value_iteration=ValueIteration(share=0.5, states=256, candidates=3, batch=128, iterations=3, episodes=4),
)


@pytest.mark.parametrize("trained", [QUICK, CHOOSING], ids=["actor-critic", "choosing"])
def test_a_suite_task_is_a_policy_job_stored_and_served_as_a_driver(
    artifacts: Path, tmp_path: Path, trained: RewardSettings
) -> None:
    """``run_policy_job`` trains a suite task's policy as it does a goal-reaching one and stores it
    beside its emulator; the emulator service drives a session of the model with it, every super-step
    the stored graph's controls for the session's state (a task without parameters: an empty goal),
    a policy that chooses among candidates (``ChoicePolicy``) as one that squashes its output. An
    emulator refined on the policy's runs while it learned (the actor-critic's here) is stored as a
    version of its own in the data directory, the one the policy names and its sessions run; the
    model's latest version stays the one it was tuned from."""
    roots = registry.Roots(tmp_path / "data", artifacts)
    path = registry.resolve(roots, "point_mass", substeps=TASK.substeps)
    done = run_policy_job(TASK.name, roots, trained)
    assert done.folder is not None and done.folder.parent.parent.name == "point_mass"
    assert done.folder.is_relative_to(tmp_path / "data")  # the data directory, never the defaults
    m = read_policy(done.folder)
    result = done.result
    assert isinstance(result, RewardResult)
    assert isinstance(result.policy, ChoicePolicy) == (trained is CHOOSING)
    tuned = trained is QUICK  # (refined whenever its returns differ at all: refine_gap=0)
    assert (result.refinements > 0) == tuned and (result.emulator is not None) == tuned
    served = registry.resolve(roots, "point_mass", m.emulator_version)
    stored = registry.read_manifest(served)
    if tuned:
        assert served.parent == tmp_path / "data" / "point_mass" and m.emulator_version.startswith(
            f"{path.name}-tuned-"
        )
        assert stored.tuned is not None and (stored.tuned.from_version, stored.tuned.task) == (
            path.name,
            TASK.name,
        )
        assert stored.tuned.refinements == result.refinements
        assert registry.latest_version(roots, "point_mass", TASK.substeps) == path.name  # no pointer moved
        # the stored graph is the fine-tuned emulator, which differs from the one it was tuned from
        x = np.asarray(
            draw_starts(TASK, registry.load_physical_model(path), np.random.default_rng(1), 4)[0], np.float32
        )
        u = np.zeros((4, 2), np.float32)
        assert result.emulator is not None
        with torch.no_grad():
            want = result.emulator(torch.as_tensor(x), torch.as_tensor(u)).numpy()
        np.testing.assert_allclose(
            OnnxEmulator(served / registry.ONNX_FILE).step(x, u), want, rtol=1e-4, atol=1e-4
        )
        assert not np.allclose(OnnxEmulator(path / registry.ONNX_FILE).step(x, u), want, atol=1e-6)
    else:
        assert served == path and stored.tuned is None
    assert (m.name, m.model, m.substeps) == (TASK.name, "point_mass", 2)
    assert (m.goal_variables, m.goal_low, m.goal_high, m.timed) == ([], [], [], False)
    assert m.task["kind"] == "reward" and m.metrics.success_physics is None
    assert m.metrics.return_physics == round(result.return_physics, 2)
    assert m.metrics.evaluate_runs == trained.final_episodes and m.metrics.mujoco_steps == result.mujoco_steps
    # how far the emulator was to be trusted under it, kept with it: a point mass has no fall
    assert m.metrics.outside_envelope == round(result.outside_share, 4) and m.metrics.falls == []
    assert result.root_drift_m is not None and m.metrics.root_drift_m == round(result.root_drift_m, 4)

    settings = Settings(artifacts_dir=artifacts, data_dir=tmp_path / "data", max_wait_ms=1.0,
                        registry_poll_s=0.0, redis_url="", api_keys="", api_key_secret="t")  # fmt: skip
    emulator = OnnxEmulator(served / registry.ONNX_FILE)
    with TestClient(create_app(settings)) as client:
        r = client.post("/sessions", json={"model": "point_mass", "seed": 3, "policy": {"name": TASK.name}})
        assert r.status_code == 201, r.text
        info = r.json()
        assert info["version"] == m.emulator_version and info["policy"]["goal_variables"] == []
        state = np.asarray(info["state"], np.float32)
        r = client.post(f"/sessions/{info['id']}/step", json={"steps": 3})
        assert r.status_code == 200, r.text
        body = r.json()
        for k in range(3):  # the torch policy's controls for the state each super-step starts from
            with torch.no_grad():
                want = result.policy(torch.as_tensor(state[None]), torch.zeros(1, 0))[0].numpy()
            np.testing.assert_allclose(body["controls"][k], want, rtol=1e-4, atol=1e-5)
            state = emulator.step(state[None], np.asarray(body["controls"][k], np.float32)[None])[0]
            np.testing.assert_allclose(body["states"][k], state, rtol=1e-4, atol=1e-4)
        # a goal this policy does not take is refused, naming its size
        r = client.post(f"/sessions/{info['id']}/step", json={"goal": [0.1]})
        assert r.status_code == 422 and r.json()["field"] == "goal", r.text
        # a session of the model without the policy runs its latest version, not the policy's own
        r = client.post("/sessions", json={"model": "point_mass", "seed": 3})
        assert r.status_code == 201 and r.json()["version"] == path.name, r.text


def test_a_suite_policy_job_stopped_before_its_first_check_stores_nothing(
    artifacts: Path, tmp_path: Path
) -> None:
    done = run_policy_job(TASK.name, registry.Roots(tmp_path, artifacts), QUICK, should_stop=lambda: True)
    assert (
        done.folder is None
        and done.result.stop == "cancelled"
        and "before its first check" in done.stored_reason
    )
    with pytest.raises(PolicyJobError, match="RewardSettings"):
        run_policy_job(TASK.name, registry.Roots(tmp_path, artifacts), PolicySettings(seconds=5))


def test_a_training_whose_states_leave_the_emulators_envelope_fails_saying_how_often(
    artifacts: Path, tmp_path: Path
) -> None:
    """An emulator whose envelope the policy's emulated states leave more than ``max_outside`` of the
    time is not trusted: the job stops and fails with the share, nothing is stored."""
    import json
    import shutil

    root = tmp_path / "narrow"
    shutil.copytree(artifacts, root, symlinks=True)
    path = registry.resolve(root, "point_mass", substeps=TASK.substeps)
    manifest = json.loads((path / "manifest.json").read_text())
    for env in manifest["envelope"]:  # an envelope no state is inside
        env["low"] = [None if v is None else 1e6 for v in env["low"]]
        env["high"] = [None if v is None else 1e6 + 1 for v in env["high"]]
    (path / "manifest.json").write_text(json.dumps(manifest))
    settings = replace(QUICK, seconds=6.0, max_iterations=None, eval_every=0.1)
    with pytest.raises(PolicyJobError, match=r"outside its training envelope 100 % of the time"):
        run_policy_job(TASK.name, root, settings)
    assert not (root / "policies").exists()


def test_neuro_policy_trains_a_reward_task_written_as_json(
    artifacts: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """``neuro policy task.json``: a user's reward task (as ``POST /policies`` takes it) on their model,
    trained (two seeds side by side) and stored under its name; a file that is not one, or names a
    model without an emulator, is an error saying so."""
    from neuroanimator.cli import main as neuro

    task = {"kind": "reward", "model": "point_mass", "name": "keep-still", "episode_s": 1, "starts": "rest",
            "terms": [{"kind": "still", "margin": 0.1}, {"kind": "small_control"}]}  # fmt: skip
    path = tmp_path / "keep-still.json"
    path.write_text(json.dumps(task))
    args = [
        "policy",
        str(path),
        "--seconds",
        "8",
        "--no-refine",
        "--seeds",
        "2",
        "--artifacts",
        str(artifacts),
    ]
    assert neuro([*args, "--json"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["task"] == "keep-still" and 0 <= row["return_physics"] <= 50  # 1 s at 20 ms
    # its terms are closures: each seed's process built the task again from the file's spec
    assert len(row["seed_returns"]) == 2 and row["return_physics"] == max(row["seed_returns"])
    stored = read_policy(Path(row["policy"]))
    assert (stored.model, stored.name) == ("point_mass", "keep-still")
    path.write_text(json.dumps({**task, "terms": [{"kind": "height"}]}))
    assert neuro(["policy", str(path), "--artifacts", str(artifacts)]) == 2
    assert "a height term needs at_least" in caplog.text
    path.write_text(json.dumps({**task, "model": "cartpole"}))
    caplog.clear()
    assert neuro(["policy", str(path), "--artifacts", str(artifacts)]) == 2
    assert "cartpole" in caplog.text


QUICK_PLANNER = PlannerSettings(horizon_s=0.6, samples=32, iterations=2)
SHORT = replace(TASK, episode_steps=120)  # 60 super-steps: the planner searches at every one


def test_the_planner_drives_the_point_mass_to_its_target_on_mujoco(artifacts: Path) -> None:
    """The sampling planner, searching the emulator's futures every super-step, carries the mass to its
    target on MuJoCo, and acts inside the controls' ranges."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    trainer = RewardTrainer(SHORT, path, QUICK)
    planner = SamplingPlanner(
        trainer.step,
        SHORT,
        trainer.ctx,
        trainer.low,
        trainer.high,
        trainer.manifest.super_timestep,
        QUICK_PLANNER,
    )
    assert planner.horizon == round(0.6 / trainer.manifest.super_timestep)
    starts, params = draw_starts(SHORT, trainer.physical, np.random.default_rng(7), 3)
    at_rest = np.zeros((3, trainer.physical.num_controls))
    still = run_on_mujoco(SHORT, trainer.physical, trainer.ctx, lambda s, p: at_rest, starts, params)
    planned = run_on_mujoco(SHORT, trainer.physical, trainer.ctx, planner.act, starts, params)
    # the mass (its position the state's first two columns) is carried to the target at the origin
    start = np.linalg.norm(starts[:, :2], axis=1)
    end = np.linalg.norm(planned.states[:, -1, :2], axis=1)
    assert np.all(end < 0.5 * start), (start, end)
    assert planned.returns.sum() > still.returns.sum()
    assert np.all(planned.controls >= trainer.low - 1e-9) and np.all(planned.controls <= trainer.high + 1e-9)
    # its noise is unit-variance along the horizon, slow (neighbours correlated), one stream a control
    noise = planner.noise(512)
    assert noise.shape == (512, planner.horizon, trainer.physical.num_controls)
    assert float(noise.std()) == pytest.approx(1.0, rel=0.1)
    lag1 = float((noise[:, 1:] * noise[:, :-1]).mean())
    assert lag1 > 0.5


def test_a_policy_copied_from_the_planner_learns_what_it_did_and_counts_its_mujoco_steps(
    artifacts: Path,
) -> None:
    """``teacher="planner"``: rounds of episodes on MuJoCo, the planner driving the first and the copy
    the others, every state labelled with what the planner would do; the copy fits those examples,
    and every MuJoCo step (the rounds', the checks', the final episodes') is counted."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    settings = replace(
        QUICK, teacher="planner", max_iterations=2,
        copying=CopySettings(episodes=2, epochs=20, planner=QUICK_PLANNER),
    )  # fmt: skip
    trainer = RewardTrainer(SHORT, path, settings)
    copier = PlannerCopy(trainer)
    untrained = copy.deepcopy(trainer.policy)
    _, history, rounds, stop = copier.train()
    assert rounds == 2 and stop == "budget" and [r for r, _, _ in history] == [1, 2]
    assert copier.examples.count == 2 * 2 * SHORT.policy_steps
    episodes = 2 * 2 + settings.eval_episodes * 2
    assert trainer.mujoco_steps == episodes * SHORT.episode_steps * SHORT.control_substeps
    # the copy does what the planner did, far closer than the untrained network
    s = torch.as_tensor(np.concatenate(copier.examples.states), dtype=torch.float32)
    p = torch.zeros(len(s), 0)
    planned = torch.as_tensor(np.concatenate(copier.examples.controls), dtype=torch.float32)
    with torch.no_grad():
        after = float(((trainer.policy(s, p) - planned) ** 2).mean())
        before = float(((untrained(s, p) - planned) ** 2).mean())
    assert after < 0.5 * before, (after, before)


def test_after_its_rounds_of_copying_the_actor_critic_goes_on_from_the_copy(artifacts: Path) -> None:
    """``CopySettings.rounds``: one round copied, then the actor-critic's iterations, restarting where
    the planner's run went (its states in the restart pool), all within one history."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    settings = replace(
        QUICK, teacher="planner", max_iterations=4,
        copying=CopySettings(episodes=2, epochs=5, planner=QUICK_PLANNER, rounds=1),
    )  # fmt: skip
    trainer = RewardTrainer(SHORT, path, settings)
    result = trainer.train()
    assert result.iterations == 4 and len(result.returns_physics) == settings.final_episodes
    checks = [r for r, _, _ in result.return_history]  # the round's check, then the actor-critic's last
    assert checks[0] == 1 and checks[-1] == 4 and len(checks) >= 2
    planned = trainer.visited[0][0]
    assert planned.shape == (2 * SHORT.policy_steps, trainer.manifest.state_size)


def test_a_copy_cancelled_mid_round_stops_and_a_teacher_unknown_is_refused(artifacts: Path) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    calls = []

    def should_stop() -> bool:
        calls.append(1)
        return len(calls) > 5  # within the first round's episodes

    settings = replace(
        QUICK, teacher="planner", copying=CopySettings(episodes=2, epochs=2, planner=QUICK_PLANNER)
    )
    trainer = RewardTrainer(SHORT, path, settings, should_stop=should_stop)
    result = trainer.train()
    assert result.stop == "cancelled" and result.return_history == []
    # the dropped round's steps are not counted: only the final episodes ran to their end
    assert result.mujoco_steps == settings.final_episodes * SHORT.episode_steps * SHORT.control_substeps
    with pytest.raises(ValueError, match="teacher is one of none, planner, not 'oracle'"):
        RewardSettings(teacher="oracle")


def test_the_planner_bench_reports_the_planner_on_the_held_out_episodes(artifacts: Path) -> None:
    lines, row = run_bench(
        "bench/planner.py", "--quick", "--task", "point_mass-easy", "--artifacts", str(artifacts)
    )
    assert row["task"] == "point_mass-easy" and row["planner"]["settings"]["samples"] == 16
    assert len(row["planner"]["returns"]) == 2 and row["planner"]["return_physics"] >= 0
    assert row["copy"] is None and any(line.startswith("planner") for line in lines)


def test_step_agreement_compares_the_emulators_step_with_mujocos_at_a_policy(artifacts: Path) -> None:
    """``step_agreement``: ARS's step at a policy from the emulator's returns against MuJoCo's, from the
    same starts and across two batches; MuJoCo in the emulator's place agrees with itself exactly
    from the same starts, less across them, and the emulator less than that from the same ones."""
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    trainer = RewardTrainer(TASK, path, QUICK)
    size = flat_weights(trainer.policy.net).numel()
    set_weights(trainer.policy.net, 0.3 * torch.randn(size, generator=torch.Generator().manual_seed(2)))
    near = replace(TASK, reward=lambda ctx, s, u, p, smooth: torch.exp(-(s[:, :2] ** 2).sum(dim=1) / 0.02))
    args = (near, trainer.physical, trainer.ctx, TASK.substeps)
    ours = step_agreement(
        *args, FastStep(trainer.emu), trainer.policy, 3, directions=8, episodes=2, noise=0.1
    )
    itself = step_agreement(*args, held_on_mujoco(trainer.physical, TASK.substeps), trainer.policy, 3,
                            directions=8, episodes=2, noise=0.1)  # fmt: skip
    assert ours is not None and itself is not None
    assert math.isclose(itself.cosine, 1.0, rel_tol=1e-9) and itself.same_sign == 1.0
    assert itself.cosine_across_starts == itself.mujoco_across_starts < 1.0 - 1e-6  # other starts, other step
    assert itself.return_emulator == itself.return_mujoco == ours.return_mujoco > 0
    assert -1.0 <= ours.cosine < 1.0 - 1e-6 and -1.0 <= ours.cosine_across_starts <= 1.0
    assert ours.mujoco_across_starts == itself.mujoco_across_starts  # MuJoCo's alone
    # MuJoCo's steps counted as they were taken: two batches of 16 policies from 2 starts each
    assert ours.mujoco_steps == itself.mujoco_steps == 2 * 16 * 2 * TASK.policy_steps * TASK.substeps
    # the tried policies' returns are the policy's own where they barely differ from it
    tiny = step_agreement(
        *args, FastStep(trainer.emu), trainer.policy, 3, directions=2, episodes=2, noise=1e-7
    )
    starts, params = draw_starts(near, trainer.physical, np.random.default_rng(3), 4)
    trainer.task = near
    assert tiny is not None and math.isclose(
        tiny.return_emulator, trainer.emulated_return(starts[:2], params[:2]), rel_tol=1e-3
    )
    # where every tried policy earns the same, there is no step to agree with
    flat = replace(TASK, reward=lambda ctx, s, u, p, smooth: torch.ones(len(s)))
    none = step_agreement(flat, *args[1:], FastStep(trainer.emu), trainer.policy, 3, directions=2, episodes=1)
    assert none is not None and math.isnan(none.cosine) and math.isnan(none.same_sign)
    # a policy choosing among candidates has no weights to perturb into a neighbour
    choice = ChoicePolicy(trainer.policy.features, candidate_controls(trainer.low, trainer.high, 3,
                          np.random.default_rng(0)), (8,))  # fmt: skip
    assert step_agreement(*args, FastStep(trainer.emu), choice, 3) is None
    with pytest.raises(ValueError, match="at least a direction and a start"):
        step_agreement(*args, FastStep(trainer.emu), trainer.policy, 3, episodes=0)


def test_the_step_agreements_cosine_reads_a_step_that_is_missing_as_none_agreeing() -> None:
    reference = torch.tensor([1.0, 0.0])
    assert cosine(torch.tensor([2.0, 0.0]), reference) == 1.0 and cosine(-reference, reference) == -1.0
    assert cosine(torch.zeros(2), reference) == 0.0  # the emulator's returns all the same: no agreement
    assert math.isnan(cosine(reference, torch.zeros(2)))  # MuJoCo's all the same: nothing to agree with


def test_random_search_tries_its_policies_through_the_emulator_and_keeps_the_best_on_mujoco(
    artifacts: Path,
) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    how = RandomSearch(directions=8, top=4, episodes=3, step=0.1, noise=0.1)
    settings = replace(QUICK, max_iterations=40, eval_every=0.02, random_search=how)
    trainer = RewardTrainer(TASK, path, settings)
    # a linear map of the features, from the controls' centres
    learner = SearchLearner(trainer, how)
    assert [type(m) for m in learner.net] == [torch.nn.Linear]
    assert learner.steps == TASK.policy_steps and not learner.theta.any()
    # every tried policy's return is its own emulated episodes' from the same starts
    theta = 0.5 * torch.randn(learner.theta.numel(), generator=torch.Generator().manual_seed(3))
    starts, params = draw_starts(TASK, trainer.physical, np.random.default_rng(5), 3)
    s, p = torch.as_tensor(starts, dtype=torch.float32), torch.as_tensor(params, dtype=torch.float32)
    got = learner.returns(torch.stack([theta, torch.zeros_like(theta), theta]), s, p)
    set_weights(trainer.policy.net, theta)
    assert got[0] == got[2] and math.isclose(float(got[0]), trainer.emulated_return(s, p), rel_tol=1e-4)
    set_weights(trainer.policy.net, torch.zeros_like(theta))
    assert math.isclose(float(got[1]), trainer.emulated_return(s, p), rel_tol=1e-4, abs_tol=1e-3)
    # ... and on MuJoCo (``on="mujoco"``), the same search on the physics, every step counted
    on_mujoco = SearchLearner(trainer, replace(how, on="mujoco"))
    before, emulated = trainer.mujoco_steps, trainer.emulated_steps
    got = on_mujoco.returns(torch.stack([theta, theta]), s, p)
    assert trainer.mujoco_steps - before == 2 * 3 * TASK.policy_steps * TASK.substeps
    assert trainer.emulated_steps == emulated  # the envelope's share is the emulator's alone
    set_weights(trainer.policy.net, theta)
    trainer.step = on_mujoco.physics_step  # type: ignore[assignment]
    assert got[0] == got[1] and math.isclose(float(got[0]), trainer.emulated_return(s, p), rel_tol=1e-4)
    with pytest.raises(ValueError, match="runs its episodes on one of emulator, mujoco"):
        RandomSearch(on="gpu")
    # staying inside the envelope (``stay_inside``): an episode that leaves it earns nothing from then on
    trainer.step = FastStep(trainer.emu)
    inside = SearchLearner(trainer, replace(how, stay_inside=True))
    paid = inside.returns(theta[None], s, p)
    assert math.isclose(float(paid[0]), trainer.emulated_return(s, p), rel_tol=1e-4)  # it never leaves
    trainer.env_high = s.amin(dim=0) - 1.0  # every state outside from the first step
    assert float(inside.returns(theta[None], s, p)[0]) == 0.0 < float(learner.returns(theta[None], s, p)[0])
    # a training (of episodes 3 s long, paid more the nearer the mass is to the middle: the suite's
    # reward pays only on the target, too rarely for forty steps): the policies it tries earn more on
    # the emulator as it goes, and the one it keeps more on MuJoCo than the policy it began from
    settings = replace(settings, random_search=replace(how, seconds=3.0, tried_runs=2))
    seen: list[RewardProgress] = []
    near = replace(TASK, reward=lambda ctx, s, u, p, smooth: torch.exp(-(s[:, :2] ** 2).sum(dim=1) / 0.02))
    trainer = RewardTrainer(near, path, settings, on_progress=seen.append)
    standing = trainer.evaluate(settings.final_episodes, settings.judged_on)[0].mean
    trainer.mujoco_steps = 0
    result = trainer.train()
    assert result.iterations == 40 and result.return_history and result.stop == "budget"
    # every check ran the policy and two of the latest tried ones on MuJoCo, all kept for refining
    assert len(trainer.runs) == 3 * len(result.return_history)
    assert sorted(len(r.returns) for r in trainer.runs) == [1] * 2 * len(result.return_history) + [
        settings.eval_episodes
    ] * len(result.return_history)
    tried = [-float(x["loss"]) for x in seen if x["loss"] is not None]
    assert len(tried) == 40 and np.mean(tried[-5:]) > np.mean(tried[:5]) + 1.0, tried
    assert result.return_physics > standing, (result.return_physics, standing)
    # the linear policy it found is served as any other: its graph acts as torch does
    import onnxruntime as ort

    from neuroanimator.export.policy import policy_to_onnx

    graph = policy_to_onnx(result.policy, trainer.manifest.state_size, 0, False, reads_time=False)
    x = torch.as_tensor(trainer.box_states(32), dtype=torch.float32)
    with torch.no_grad():
        want = result.policy(x, torch.zeros(32, 0)).numpy()
    got = ort.InferenceSession(graph).run(None, {"state": x.numpy(), "goal": np.zeros((32, 0), np.float32)})[
        0
    ]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
    assert 0 < result.outside_share < 1 or result.outside_share == 0
    episodes = settings.eval_episodes * len(result.return_history) + settings.final_episodes
    assert result.mujoco_steps >= episodes * TASK.episode_steps * TASK.control_substeps
    # a learner of its own: not beside value iteration
    with pytest.raises(ValueError, match="learner of its own"):
        RewardTrainer(TASK, path, replace(settings, value_iteration=ValueIteration()))
