"""A policy task as a Gymnasium environment on MuJoCo itself, and Stable-Baselines3 trained on it for a
fixed wall time: the model-free baseline of ``bench/policies.py``.

The environment is the policy task as the emulator's policy sees it:

- one step is one control period: the task's ``substeps`` physical steps with the controls held;
- the observation is the trained policy's own input features (``policy_net.PolicyFeatures`` with its
  ``PolicyShape``: the state made scale-free, the goal's offset, its planar part in the heading's
  frame, and the time left for a timed task), as float32 (D,);
- the action (U,) in [-1, 1] is scaled to each control's useful range and clipped to its hard limits,
  as the policy's squashed output is;
- the reward of the step that ends in state s_k is minus the policy's loss at that step, times the
  run's K steps: ``−(K·w_k·d(s_k, target) + c·|a|²)`` (``TargetDistance``, the schedule's weights w,
  the task's ``control_weight`` c), plus ``HOLD_BONUS`` whenever the task's checks hold against the
  current goal and ``CHECK_BONUS`` more when they hold at a check step; a state that is no longer
  finite ends the episode with ``DIVERGED_PENALTY``;
- an episode is the task's ``episode_s``; its start from the task's start box and its goals (one per
  goal period, a moving one within the task's ``max_move`` of the last) from the same ``GoalPool``
  the emulator's policy was trained with, drawn as its training draws them.

Shapes: N runs, K super-steps, S state, G goal variables, P goals per run, U controls, D features.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np
import torch
from numpy.typing import NDArray
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback

from neuroanimator.control.policy import PolicyTrainer, TargetDistance
from neuroanimator.control.policy_data import GoalPool, sample_starts
from neuroanimator.control.policy_net import PolicyFeatures, PolicyShape
from neuroanimator.goals import criteria

log = logging.getLogger("bench.model_free")
FloatArray = NDArray[np.float64]
HOLD_BONUS = 1.0  # per step the checks hold
CHECK_BONUS = 10.0  # more at a step where the task judges them
DIVERGED_PENALTY = 100.0
ALGORITHMS = ("sac", "ppo")


class Controls:
    """Actions (N, U) in [-1, 1] → controls (N, U): the policy's useful range, then its hard limits."""

    def __init__(self, shape: PolicyShape) -> None:
        low, high = np.asarray(shape.low), np.asarray(shape.high)
        self.centre, self.span = 0.5 * (low + high), 0.5 * (high - low)
        self.limit_low, self.limit_high = np.asarray(shape.limit_low), np.asarray(shape.limit_high)

    def __call__(self, actions: NDArray[Any]) -> FloatArray:
        a = np.clip(np.nan_to_num(np.asarray(actions, dtype=np.float64)), -1.0, 1.0)
        return np.clip(self.centre + self.span * a, self.limit_low, self.limit_high)


class Observer:
    """States (N, S), goals (N, G) and the super-step k → the policy's features (N, D) as float32."""

    def __init__(self, shape: PolicyShape, judge: PolicyTrainer) -> None:
        self.features = PolicyFeatures(shape)
        self.schedule = judge.schedule
        self.size = shape.num_features

    @torch.no_grad()
    def __call__(self, states: FloatArray, goals: FloatArray, k: int) -> NDArray[np.float32]:
        n = len(states)
        left = torch.full((n, 1), self.schedule.time_left(k))
        s = torch.as_tensor(np.nan_to_num(states), dtype=torch.float32)
        g = torch.as_tensor(goals, dtype=torch.float32)
        out: NDArray[np.float32] = self.features(s, g, left).numpy()
        return np.nan_to_num(out, posinf=0.0, neginf=0.0)


class PolicyTaskEnv(gymnasium.Env[NDArray[np.float32], NDArray[np.float32]]):
    """One run of the policy task on MuJoCo at a time (module doc)."""

    def __init__(self, judge: PolicyTrainer, shape: PolicyShape, pool: GoalPool) -> None:
        super().__init__()
        self.judge, self.pool = judge, pool
        self.task, self.schedule = judge.task, judge.schedule
        self.observe, self.controls = Observer(shape, judge), Controls(shape)
        self.distance = TargetDistance(judge.manifest, self.task.state_weights)
        self.labels = judge.manifest.state_labels
        self.checks = set(self.schedule.check_steps())
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (self.observe.size,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (shape.num_controls,), np.float32)
        self.state = np.zeros(len(self.labels))
        self.goals = np.zeros((self.schedule.goals, len(self.task.goal.variables)))
        self.k = 0
        self.steps = 0  # every env step taken, over all episodes

    def _goal(self, k: int) -> FloatArray:
        """The goal (G,) in force during super-step k (the last one's after the run)."""
        return self.goals[min(self.schedule.goal_index(k), len(self.goals) - 1)]

    def _obs(self) -> NDArray[np.float32]:
        return self.observe(self.state[None], self._goal(self.k)[None], self.k)[0]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        self.state = sample_starts(self.judge.physical, self.task, self.np_random, 1)[0]
        self.goals = self.pool.draw_moving(self.np_random, 1, self.schedule.goals, self.task.goal.max_move)[0]
        self.k = 0
        return self._obs(), {}

    def step(
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        sch, k = self.schedule, self.k
        u = self.controls(action[None])
        goal = self._goal(k)
        self.state = self.judge.physical.step_held(self.state[None], u, None, self.judge.substeps)[0]
        self.k, self.steps = k + 1, self.steps + 1
        truncated = self.k >= sch.steps
        if not np.all(np.isfinite(self.state)):
            self.state = np.zeros_like(self.state)
            return self._obs(), -DIVERGED_PENALTY, True, False, {"diverged": True}
        target = np.asarray(self.task.target_with(goal.tolist()), dtype=np.float64)
        with torch.no_grad():
            d = float(
                self.distance(
                    torch.as_tensor(self.state[None], dtype=torch.float32),
                    torch.as_tensor(target[None], dtype=torch.float32),
                )[0]
            )
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        reward = -(sch.steps * float(sch.weights[k]) * d + self.task.control_weight * float(a @ a))
        if criteria.evaluate(self.task.success, self.state, target, self.labels)[0]:
            reward += HOLD_BONUS + (CHECK_BONUS if self.k in self.checks else 0.0)
        return self._obs(), reward, False, truncated, {}


class Deadline(BaseCallback):
    """Stops learning once ``until`` (``time.perf_counter``) has passed."""

    def __init__(self, until: float) -> None:
        super().__init__()
        self.until = until

    def _on_step(self) -> bool:
        return time.perf_counter() < self.until


def make_agent(algorithm: str, env: PolicyTaskEnv, seed: int, quick: bool) -> BaseAlgorithm:
    """SAC (off-policy, one update per step) or PPO with Stable-Baselines3's defaults on the CPU (a
    replay buffer of 300,000 steps, more than any budget here fills); ``quick`` shrinks the batches
    for a smoke test."""
    if algorithm == "sac":
        return SAC(
            "MlpPolicy",
            env,
            seed=seed,
            device="cpu",
            buffer_size=300_000,
            learning_starts=50 if quick else 100,
            batch_size=64 if quick else 256,
            verbose=0,
        )
    if algorithm == "ppo":
        return PPO(
            "MlpPolicy",
            env,
            seed=seed,
            device="cpu",
            n_steps=128 if quick else 2048,
            batch_size=32 if quick else 64,
            verbose=0,
        )
    raise ValueError(f"algorithm: expected one of {ALGORITHMS}, got {algorithm!r}")


@dataclass
class ModelFree:
    """An agent trained on MuJoCo: how long it ran, its env steps (each ``substeps`` MuJoCo steps)
    and episodes."""

    agent: BaseAlgorithm
    algorithm: str
    wall_s: float
    env_steps: int
    episodes: int


def train_model_free(
    algorithm: str, judge: PolicyTrainer, shape: PolicyShape, seconds: float, seed: int, quick: bool
) -> ModelFree:
    """Train ``algorithm`` on the task's MuJoCo environment for ``seconds`` of wall time (the agent's
    construction included), on the torch threads already set."""
    t0 = time.perf_counter()
    env = PolicyTaskEnv(judge, shape, judge.pool)
    agent = make_agent(algorithm, env, seed, quick)
    agent.learn(total_timesteps=10**9, callback=Deadline(t0 + seconds))
    wall = time.perf_counter() - t0
    episodes = env.steps // judge.schedule.steps  # whole runs' worth of steps (divergence ends some early)
    log.info("%s: %s, %d env steps in %.1f s", judge.task.name, algorithm, env.steps, wall)
    return ModelFree(agent, algorithm, wall, env.steps, episodes)


def run_agent(
    agent: BaseAlgorithm, judge: PolicyTrainer, shape: PolicyShape, starts: FloatArray, goals: FloatArray
) -> FloatArray:
    """The agent's deterministic policy closed around MuJoCo from starts (N, S) towards goals (N, P, G):
    the states (N, K+1, S)."""
    sch = judge.schedule
    observe, controls = Observer(shape, judge), Controls(shape)
    states = np.zeros((len(starts), sch.steps + 1, starts.shape[1]))
    s = np.asarray(starts, dtype=np.float64)
    states[:, 0] = s
    for k in range(sch.steps):
        obs = observe(s, goals[:, sch.goal_index(k)], k)
        actions, _ = agent.predict(obs, deterministic=True)
        s = judge.physical.step_held(s, controls(actions), None, judge.substeps)
        states[:, k + 1] = s
    return states
