"""dm_control's suite tasks that policies are learned for, as the processes that never simulate read
them (the controller API, ``GET /policy-tasks``): torch-free, MuJoCo-free.

A suite task runs on its domain's MJCF (``dm_control/suite/<domain>.xml``), brought in as a user's
model (``neuro train --mjcf <domain>.xml --name <domain> --substeps n``): the model is named as the
domain and its emulator steps ``substeps`` physical steps, the control period the policy needs. How
an episode starts and what it earns (the suite's ``initialize_episode`` and ``get_reward`` in torch)
is ``neuroanimator.control.suite_tasks``, built on these.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from neuroanimator.core.train_config import DEFAULT_TIME_BUDGET

# a body on the ground: its emulator trained with 900 s, not 285 (``neuro train --time-budget 900``),
# three times the examples and the training
GROUND_EMULATOR_SECONDS = 900.0


@dataclass(frozen=True)
class SuiteTaskInfo:
    """One suite task: the domain (and model) it runs on, its control period (``substeps`` physical
    steps), the suite's own control step (``control_substeps``), its episode, the parameters drawn for
    each episode (``params``, each within ``param_low``..``param_high``: the reacher's target) and the
    return a learned policy must reach on MuJoCo (mean of 10 episodes)."""

    name: str
    domain: str
    substeps: int
    control_substeps: int = 1
    params: tuple[str, ...] = ()
    param_low: tuple[float, ...] = ()
    param_high: tuple[float, ...] = ()
    episode_steps: int = 1000
    target_return: float = 0.0  # 0: no target, its return is reported
    train_seconds: float = 1500.0
    # the budget its emulator is trained with (``neuro train --time-budget``): a body on the ground
    # needs more data than the default 285 s simulates (the walker's one-step error 0.048 → 0.036)
    emulator_seconds: float = DEFAULT_TIME_BUDGET
    summary: str = ""

    @property
    def model(self) -> str:
        """The model a task's policy is trained for: the one named as its domain."""
        return self.domain

    @property
    def mjcf(self) -> str:
        """The domain's MJCF, as dm_control ships it."""
        return f"dm_control/suite/{self.domain}.xml"

    @property
    def train_command(self) -> str:
        """The command that trains the emulator this task's policy is learned through."""
        cmd = f"neuro train --mjcf {self.mjcf} --name {self.domain} --substeps {self.substeps}"
        if self.emulator_seconds != DEFAULT_TIME_BUDGET:
            cmd += f" --time-budget {self.emulator_seconds:g}"
        return cmd

    @property
    def criterion(self) -> str:
        """What the task's policy is judged by, in words."""
        judged = (
            f"the return of {self.episode_steps} steps on MuJoCo with the suite's reward "
            "(mean of 10 episodes)"
        )
        if self.target_return > 0:
            return f"{judged} at least {self.target_return:g}"
        return f"none set: {judged} is reported"

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able data, for ``GET /policy-tasks`` (``kind`` ``reward``: judged by its return)."""
        return {
            "name": self.name,
            "model": self.model,
            "kind": "reward",
            "description": self.summary,
            "substeps": self.substeps,
            "episode_steps": self.episode_steps,
            "goal_variables": list(self.params),
            "goal_low": list(self.param_low),
            "goal_high": list(self.param_high),
            "target_return": self.target_return,
            "success_criterion": self.criterion,
            "mjcf": self.mjcf,
        }


SUITE_TASK_INFO: dict[str, SuiteTaskInfo] = {
    t.name: t
    for t in (
        SuiteTaskInfo(
            "cartpole-swingup",
            "cartpole",
            5,
            target_return=800,
            summary="swing the pole up from hanging and balance it, the cart near the centre",
        ),
        SuiteTaskInfo(
            "pendulum-swingup",
            "pendulum",
            2,
            target_return=750,
            summary="swing the pendulum up with too little torque to lift it directly; paid within 8° of upright",
        ),
        SuiteTaskInfo(
            "reacher-hard",
            "reacher",
            2,
            params=("target.x", "target.y"),
            param_low=(-0.2, -0.2),
            param_high=(0.2, 0.2),
            target_return=900,
            summary="put the two-link arm's fingertip on a small target (the goal: its x, y)",
        ),
        SuiteTaskInfo(
            "point_mass-easy",
            "point_mass",
            2,
            target_return=850,
            summary="bring the point mass to the centre and keep it there",
        ),
        SuiteTaskInfo(
            "ball_in_cup-catch",
            "ball_in_cup",
            20,
            10,
            target_return=900,
            summary="swing the ball on its string into the cup",
        ),
        SuiteTaskInfo(
            "acrobot-swingup",
            "acrobot",
            5,
            target_return=250,
            summary="swing the two-link acrobot's tip up with the elbow's torque alone",
        ),
        # (touching the ground: the policy acts at the suite's own control period, 20-40 ms)
        SuiteTaskInfo(
            "hopper-stand",
            "hopper",
            4,
            4,
            target_return=700,
            train_seconds=3300.0,
            emulator_seconds=GROUND_EMULATOR_SECONDS,
            summary="the one-legged hopper stands up from lying and balances, its torso 0.6 m above its foot",
        ),
        SuiteTaskInfo(
            "walker-stand",
            "walker",
            10,
            10,
            target_return=900,
            train_seconds=3300.0,
            emulator_seconds=GROUND_EMULATOR_SECONDS,
            summary="the planar biped stands up from lying and stays up, its torso above 1.2 m and upright",
        ),
        SuiteTaskInfo(
            "walker-walk",
            "walker",
            10,
            10,
            target_return=700,
            train_seconds=3300.0,
            emulator_seconds=GROUND_EMULATOR_SECONDS,
            summary="the planar biped gets up and walks forward at 1 m/s or faster, upright",
        ),
        SuiteTaskInfo(
            "cheetah-run",
            "cheetah",
            4,
            1,
            target_return=500,
            train_seconds=3300.0,
            emulator_seconds=GROUND_EMULATOR_SECONDS,
            summary="the planar cheetah runs forward, paid in proportion to its speed up to 10 m/s",
        ),
        SuiteTaskInfo(
            "humanoid-stand",
            "humanoid",
            5,
            5,
            train_seconds=3300.0,
            summary="the 21-joint humanoid gets up from wherever it fell and stands still, its head above 1.4 m",
        ),
    )
}

__all__ = ["SUITE_TASK_INFO", "SuiteTaskInfo"]
