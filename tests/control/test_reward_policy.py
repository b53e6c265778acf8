"""Reward policies learned through the emulator (SHAC-style, ``control.reward_policy``) on a suite
task, judged on MuJoCo with the suite's exact reward; and ``bench/policies.py`` on a suite task."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from dm_control import suite

from neuroanimator.artifacts import registry
from neuroanimator.control.reward_policy import RewardSettings, RewardTrainer, draw_starts, run_on_mujoco
from neuroanimator.control.suite_tasks import SUITE_TASKS
from tests.helpers import run_bench

TASK = SUITE_TASKS["point_mass-easy"]
# loading the model counts in the budget (seconds), and takes seconds of its own on a loaded machine
QUICK = RewardSettings(seconds=120.0, max_iterations=12, envs=16, horizon=8, critic_steps=2, eval_episodes=2,
                       final_episodes=2, refine_seconds=1.0, refine_gap=0.0)  # fmt: skip


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
    assert all(np.isfinite(r) and 0 <= r <= TASK.episode_steps for _, r in result.return_history)
    assert len(result.returns_physics) == QUICK.final_episodes
    assert 0 <= result.return_physics <= TASK.episode_steps and np.isfinite(result.return_emulator)
    # every MuJoCo episode is counted: the checks during training and the final ones
    episodes = QUICK.eval_episodes * len(result.return_history) + QUICK.final_episodes
    assert result.mujoco_steps == episodes * TASK.episode_steps * TASK.control_substeps
    assert result.refinements >= 1  # the emulator learned from the policy's MuJoCo runs (any gap)
    # the policy's controls stay in the actuators' range, on states far outside what it saw
    s = torch.randn(64, trainer.manifest.state_size) * 10
    u = trainer.policy(s, torch.zeros(64, 0))
    assert torch.all(u >= torch.tensor(trainer.low) - 1e-6) and torch.all(
        u <= torch.tensor(trainer.high) + 1e-6
    )


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


def test_an_emulator_at_another_control_period_is_refused(artifacts: Path) -> None:
    path = registry.resolve(artifacts, "point_mass", substeps=TASK.substeps)
    with pytest.raises(ValueError, match="acts every 5 physical steps"):
        RewardTrainer(replace(TASK, substeps=5), path, QUICK)


def test_bench_policies_runs_a_suite_task(artifacts: Path) -> None:
    lines, result = run_bench(
        "bench/policies.py", "--quick", "--tasks", "point_mass-easy", "--artifacts", str(artifacts)
    )
    (row,) = result["tasks"]
    assert row["task"] == "point_mass-easy" and row["substeps"] == TASK.substeps
    for key in ("return_physics", "return_emulator", "mujoco_steps", "wall_s"):
        assert isinstance(row[key], (int, float))
    # found in --artifacts, not trained again: its training's seconds count in the wall time all the same
    assert not row["emulator_trained_here"] and 0 < row["emulator_wall_s"] < row["wall_s"]
    assert row["model_free"]["algorithm"] == "sac" and row["model_free"]["env_steps"] > 0
    assert any(line.startswith("| point_mass-easy |") for line in lines)
