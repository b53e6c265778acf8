"""Policies that maximise a reward, learned through the emulator: short-horizon actor-critic with
analytic gradients (SHAC, Xu et al. 2022), the simulator replaced by the learned emulator as
SuperTrack and ControlVAE replace theirs.

A goal-reaching task (``policy.PolicyTrainer``) knows where each run must end; a reward task (the
suite's ``cartpole-swingup``, ``reacher-hard``, ...) only pays for every step, over episodes much
longer than a gradient survives through a learned model. So, as SHAC does:

1. ``envs`` episodes run side by side through the frozen emulator under the policy (its controls
   lightly perturbed); every iteration advances them ``horizon`` super-steps, and the policy's loss is
   minus the discounted reward of those steps plus the critic's value of where they end, its gradient
   through the emulator's rollout (clipped in norm);
2. the critic ``V(state, params)`` learns the discounted return by TD(λ) from the same steps;
3. an episode that has run ``branch_s`` (a few seconds, as MBPO's and Dreamer's model rollouts are
   short: continued for the task's whole episode, a pendulum that fell spins on and the policy learns
   a constant torque from it), leaves the states the emulator knows or diverges starts again: from the
   task's own starts, or (``mujoco_share``) from a state the policy reached on MuJoCo, so that the
   emulator's short rollouts branch from where the policy really goes (MBPO's branching), or
   (``explore_share``) from anywhere in the emulator's envelope (the states of its training data),
   so that the critic learns the worth of states the policy does not reach yet (a pendulum already
   swinging fast: the way up is there before the policy has found it), some of those (a task's
   ``Restarts.rewarded``) where the reward is paid: a reverse curriculum, the pole balanced upright
   before it is swung up (the pendulum found its swing-up in 250 s this way, and never without);
4. every ``eval_every`` of the budget the policy runs its episodes on MuJoCo with the exact reward:
   the best policy so far is kept, the states join the start pool, and (``refine``) when the
   emulator's return from the same starts is off MuJoCo's by more than ``refine_gap``, the emulator
   is fine-tuned on all the policy's MuJoCo runs so far, so the model is right where the policy goes
   (a model already right there is left alone: its seconds go to the policy).

With ``rollouts="mujoco"`` the training rollouts run on MuJoCo and only their gradient through the
emulator (decoupled backpropagation, as first-order model-based RL through a learned model does
where the simulator has no derivatives): each super-step's value is MuJoCo's, its Jacobian the
emulator's at the state MuJoCo reached, so that a model's errors bend the gradient but never carry
the episode somewhere the physics does not go, and the critic learns MuJoCo's returns.

Shapes: B episodes, H horizon, S state, U controls, P task parameters.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TypedDict

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.control.bptt import FastStep
from neuroanimator.control.exploring_runs import ExploringRuns, random_runs
from neuroanimator.control.planner_copy import PLANNER, TEACHERS, CopySettings, PlannerCopy
from neuroanimator.control.random_search import RandomSearch, SearchLearner
from neuroanimator.control.suite_tasks import Context, Restarts, SuiteTask
from neuroanimator.control.value_iteration import ValueFitter, ValueIteration, candidate_controls
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim import sampling
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.train import fine_tune_on_runs

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
FEATURE_LIMIT = 8.0  # a state this many spreads from the typical motion has left what the emulator knows
FINISH_MARGIN = 1.25  # the final judging's cost over its episodes' on MuJoCo (``RewardTrainer.deadline``)
DRIFT_S = 1.0  # seconds into an episode at which the emulator's root is compared with MuJoCo's
REFINE_WINDOW = 8  # super-steps of each window the emulator is refined on
EXPLORE_SHARE = 0.25  # of the budget the exploring runs' fine-tuning may take at most (``explore``)
# checks whose failing episodes restarts are drawn from (``Restarts.failing``): the policy's latest
# failures, not those of the policies it has left behind
FAILING_CHECKS = 4
FINAL_SEED_OFFSET = 1_000_003  # the final episodes' seed, apart from the training's draws
# where the actor-critic's training rollouts run (``RewardSettings.rollouts``)
ROLLOUTS = ("emulator", "mujoco")
OUTSIDE = "outside_envelope"  # a training's stop: its emulated states left the emulator's envelope too often


@dataclass(frozen=True)
class RewardSettings:
    """How a reward policy is trained; ``seconds`` is the whole training's wall-clock budget, its final
    judging on MuJoCo included (``RewardTrainer.deadline``)."""

    seconds: float = 1500.0
    max_iterations: int | None = None
    envs: int = 256  # the steps are small: more episodes per update cost little (64 → 256: 1.4× the time)
    # super-steps per iteration: the gradient's path through the emulator (None: the task's,
    # ``SuiteTask.horizon``: 32, 8 for a body on the ground)
    horizon: int | None = None
    actor_lr: float = 2e-3  # cosine-annealed to a tenth over the actor-critic's span (``actor_rate``)
    critic_lr: float = 2e-3
    critic_steps: int = 8  # critic updates per iteration, each on a random half of the iteration's steps
    lam: float = 0.95
    target_tau: float = 0.2  # the target critic moves this share towards the critic each iteration
    noise: float = 0.2  # control noise (share of each control's half range) in the training rollouts
    hidden: tuple[int, ...] = (64, 64)
    critic_hidden: tuple[int, ...] = (128, 128)
    grad_clip: float = 1.0
    eval_every: float = 0.1  # share of the budget between runs on MuJoCo
    eval_episodes: int = 8
    branch_s: float = 4.0  # an emulated episode restarts after this long: long ones drift into
    # states where the gradient vanishes (a pendulum spun up, the policy learning a constant torque)
    # where restarts begin (None: as the task says, ``Restarts``): states the policy reached on
    # MuJoCo, anywhere in the emulator's envelope, and the share of those at the best-paid of
    # ``tournament`` draws (the rest from the task's own starts)
    mujoco_share: float | None = None
    explore_share: float | None = None
    rewarded_share: float | None = None
    explore_from: str | None = None  # "box" or "motion" (``Restarts.explore_from``; None: the task's)
    failing_share: float | None = None  # ``Restarts.failing`` (None: the task's)
    tournament: int = 8
    refine: bool = True
    refine_gap: float = 0.02  # refine when the returns on the emulator and on MuJoCo differ by more
    # than this share of the most an episode can earn (the suite's rewards are at most 1 a step)
    refine_seconds: float = 15.0
    # windows of the typical motion the emulator was trained on, learned beside the policy's runs
    # when it is refined, so that it is not forgotten (0: the policy's runs alone; None: the task's,
    # ``SuiteTask.refine_keep``: 1,024 for a body on the ground, 0 for the others, measured so)
    refine_keep: int | None = None
    final_episodes: int = 10
    # the MuJoCo episodes the final policy is judged on are drawn from this seed (None: ``seed`` +
    # ``FINAL_SEED_OFFSET``): policies trained from several seeds are judged on the same episodes
    final_seed: int | None = None
    # a training whose emulated states lie outside the emulator's training envelope more than this
    # share of the time (measured from a quarter of the budget on) stops and fails: its policy would
    # be learnt from what the emulator never saw
    max_outside: float = 0.5
    seed: int = 0
    # torch threads of a seed trained alone (None: the task's ``SuiteTask.threads``, at most the
    # machine's cores; ``seed_race.thread_count``); seeds side by side take one core each
    threads: int | None = None
    # policies trained from this many seeds side by side, one process and core each, the best on
    # MuJoCo kept (``seed_race``; None: the task's ``SuiteTask.seeds``, at most the machine's cores)
    seeds: int | None = None
    # seeds side by side meet once, at the first check past this share of the budget: those behind
    # take the best one's policy and critic and train on from their own draws (population-based
    # training's exploit step; ``seed_race``). None: they never meet
    meet_at: float | None = None
    # "planner": the policy copies the sampling planner through the emulator (``planner_copy``)
    # before (``CopySettings.rounds``) or instead of the actor-critic; None or "none": the actor-critic
    # alone. Not a default: on the acrobot the planner earns 373 and its copies 29-34 (measured,
    # docs/experiments/policies.md)
    teacher: str | None = None
    # how the planner is copied, when it is the teacher
    copying: CopySettings = field(default_factory=CopySettings)
    # instead of the actor-critic: a value fitted by value iteration through the emulator over its
    # envelope, and the policy that is greedy over it copied into the network (``value_iteration``);
    # None: as the task says (``SuiteTask.value_iteration``), "off": the actor-critic whatever it says
    value_iteration: ValueIteration | str | None = None
    # before learning, the emulator fine-tuned on random runs from the task's starts
    # (``exploring_runs``); None: as the task says (``SuiteTask.exploring``)
    exploring: ExploringRuns | None = None
    # where the actor-critic's training rollouts run: "emulator", or "mujoco": each super-step's
    # state MuJoCo's, its gradient the emulator's at that state (decoupled backpropagation: the
    # model's errors do not compound along the path, the critic learns from MuJoCo's returns; its
    # steps counted in ``mujoco_steps``)
    rollouts: str = "emulator"
    # instead of the actor-critic: augmented random search over the policy's weights, every tried
    # policy's return measured on emulated episodes (``random_search``); None: as the task says
    # (``SuiteTask.random_search``), "off": the actor-critic whatever it says
    random_search: RandomSearch | str | None = None

    def __post_init__(self) -> None:
        if self.teacher is not None and self.teacher not in TEACHERS:
            raise ValueError(f"teacher is one of {', '.join(TEACHERS)}, not {self.teacher!r}")
        if self.rollouts not in ROLLOUTS:
            raise ValueError(f"rollouts run on one of {', '.join(ROLLOUTS)}, not {self.rollouts!r}")
        if isinstance(self.value_iteration, str) and self.value_iteration != "off":
            raise ValueError(f"value_iteration is settings, None or 'off', not {self.value_iteration!r}")
        if isinstance(self.random_search, str) and self.random_search != "off":
            raise ValueError(f"random_search is settings, None or 'off', not {self.random_search!r}")

    @property
    def judged_on(self) -> int:
        """The seed of the final MuJoCo episodes (``final_seed``)."""
        return self.seed + FINAL_SEED_OFFSET if self.final_seed is None else self.final_seed


class RewardProgress(TypedDict):
    iteration: int
    loss: float | None
    return_physics: float | None
    mujoco_steps: int
    elapsed_s: float


class Features(nn.Module):
    """States (B, S) and parameters (B, P) → features: angles as sine and cosine, every other
    variable centred and scaled by its spread, clamped to ±``FEATURE_LIMIT``, the parameters, and the
    task's own observations (``SuiteTask.observe``, as the suite's ``get_observation`` gives them:
    the reacher's fingertip-to-target vector), which spare the network learning the kinematics."""

    angles: Tensor
    plain: Tensor
    mean: Tensor
    scale: Tensor

    def __init__(
        self,
        angles: list[int],
        plain: list[int],
        mean: FloatArray,
        scale: FloatArray,
        params: int,
        observe: Callable[[Tensor, Tensor], Tensor] | None = None,
        observed: int = 0,
    ) -> None:
        super().__init__()
        self.observe = observe
        self.register_buffer("angles", torch.tensor(angles, dtype=torch.long))
        self.register_buffer("plain", torch.tensor(plain, dtype=torch.long))
        self.register_buffer("mean", torch.tensor(mean[plain], dtype=torch.float32))
        self.register_buffer("scale", torch.tensor(scale[plain], dtype=torch.float32))
        self.size = 2 * len(angles) + len(plain) + params + observed

    def plain_z(self, state: Tensor) -> Tensor:
        return (state[:, self.plain] - self.mean) / self.scale

    def forward(self, state: Tensor, params: Tensor) -> Tensor:
        a = state[:, self.angles]
        z = self.plain_z(state).clamp(-FEATURE_LIMIT, FEATURE_LIMIT)
        extra = [self.observe(state, params)] if self.observe is not None else []
        return torch.cat([torch.sin(a), torch.cos(a), z, params * 5.0, *extra], dim=1)


def mlp(
    inputs: int, hidden: tuple[int, ...], outputs: int, activation: type[nn.Module] = nn.ELU
) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(inputs, width), activation()]
        inputs = width
    layers.append(nn.Linear(inputs, outputs))
    return nn.Sequential(*layers)


class RewardPolicy(nn.Module):
    """π(state (B,S), params (B,P)) → controls (B,U) inside the controls' ranges."""

    centre: Tensor
    half_range: Tensor
    spread: Tensor

    def __init__(
        self, features: Features, low: FloatArray, high: FloatArray, hidden: tuple[int, ...]
    ) -> None:
        super().__init__()
        self.features = features
        self.net: nn.Module = mlp(features.size, hidden, len(low))
        self.register_buffer("centre", torch.tensor((low + high) / 2, dtype=torch.float32))
        self.register_buffer("half_range", torch.tensor((high - low) / 2, dtype=torch.float32))
        self.register_buffer("spread", torch.diag(self.half_range), persistent=False)  # (U, U)

    def forward(self, state: Tensor, params: Tensor) -> Tensor:
        # c + h·tanh(a) as one product with a bias: one Gemm in the served graph (``policy_net``)
        a = torch.tanh(self.net(self.features(state, params)))
        return nn.functional.linear(a, self.spread, self.centre)

    def act(self, states: FloatArray, params: FloatArray) -> FloatArray:
        """(N, S) states and (N, P) parameters → (N, U) controls, in NumPy (``run_on_mujoco``'s act)."""
        with torch.no_grad():
            u = self(
                torch.as_tensor(states, dtype=torch.float32), torch.as_tensor(params, dtype=torch.float32)
            )
        return u.double().numpy()

    def output_range(self) -> tuple[list[float], list[float]]:
        """(U,) lows and highs the controls never leave."""
        c, h = self.centre.tolist(), self.half_range.tolist()
        return [a - b for a, b in zip(c, h, strict=True)], [a + b for a, b in zip(c, h, strict=True)]


class ChoicePolicy(RewardPolicy):
    """π(state (B,S), params (B,P)) → the best-scored of C candidate controls (C, U): the network
    scores every candidate (``scores``) and the best is taken. The copy of a policy greedy over a
    few candidates (``value_iteration``): near where the greedy choice flips (the acrobot's full
    torque one way or the other) a regression onto its controls averages the two sides into a
    torque that does neither, a choice keeps one (module doc of ``value_iteration``, measured).

    Its units are ReLUs, not the other policies' ELUs: served beside the emulator every super-step, the
    policy must cost little next to it, and ONNX Runtime takes three times as long over ELUs (614
    against 197 µs for 1,024 rows of a 64-wide network, measured); a choice needs no smooth output.

    ``blend`` > 0 serves the candidates averaged by the softmax of the scores over ``blend`` instead
    of the best one (Softmax and MatMul in the served graph): where the network is sure, its choice;
    where candidates are near ties, a control between them. For the ball in the cup, whose nine
    candidates are the corners, edges and centre of its two controls' box, copies read so earned
    966-970 held out where the same copies' best-scored candidates earned 947 and 889 (measured,
    docs/experiments); for the acrobot's pumping the full torque one way or the other is the point,
    and it stays a choice (a copy of 241 held out, read blended, 196-216)."""

    choices: Tensor

    def __init__(
        self, features: Features, choices: Tensor, hidden: tuple[int, ...], blend: float | None = None
    ) -> None:
        low = choices.min(dim=0).values.double().numpy()
        high = choices.max(dim=0).values.double().numpy()
        super().__init__(features, low, high, hidden)
        self.net = mlp(features.size, hidden, len(choices), nn.ReLU)
        self.register_buffer("choices", choices.float().clone())
        self.blend = blend

    def scores(self, state: Tensor, params: Tensor) -> Tensor:
        """(B, C) each candidate's score: the higher, the likelier the greedy policy's choice."""
        out: Tensor = self.net(self.features(state, params))
        return out

    def choice(self, state: Tensor, params: Tensor) -> Tensor:
        """(B,) the index of the best-scored candidate."""
        return self.scores(state, params).argmax(dim=1)

    def forward(self, state: Tensor, params: Tensor) -> Tensor:
        if self.blend:  # Softmax and MatMul in the served graph: a convex mix, inside the range
            weights = torch.softmax(self.scores(state, params) / self.blend, dim=1)
            return weights @ self.choices
        # ArgMax and Gather in the served graph
        return self.choices[self.choice(state, params)]


class Critic(nn.Module):
    """V(state (B,S), params (B,P)) → (B,) the discounted return from there."""

    def __init__(self, features: Features, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.features = features
        self.net = mlp(features.size, hidden, 1)

    def forward(self, state: Tensor, params: Tensor) -> Tensor:
        return self.net(self.features(state, params))[:, 0]


@dataclass
class Episodes:
    """Episodes run under a policy: returns (N,), states at every policy step (N, K+1, S), controls
    (N, K, U), parameters (N, P)."""

    returns: FloatArray
    states: FloatArray
    controls: FloatArray
    params: FloatArray

    @property
    def mean(self) -> float:
        return float(self.returns.mean()) if len(self.returns) else 0.0


@dataclass
class RewardResult:
    policy: RewardPolicy
    task: SuiteTask
    return_physics: float
    return_emulator: float
    returns_physics: list[float]
    mujoco_steps: int
    iterations: int
    wall_s: float
    refinements: int = 0
    # every check on MuJoCo: (iteration, elapsed s, the mean return of its episodes)
    return_history: list[tuple[int, float, float]] = field(default_factory=list)
    stop: str = "budget"  # or "cancelled", or OUTSIDE (the emulator's envelope left too often)
    params: FloatArray | None = None  # (N, P) the task's parameters it was trained for
    outside_share: float = 0.0  # the share of emulated states outside the emulator's training envelope
    falls: list[FallReport] = field(default_factory=list)  # the final episodes' falls on MuJoCo
    # metres between the root body on the emulator and on MuJoCo ``DRIFT_S`` into the final episodes
    # (each in its own closed loop under the policy; None for episodes shorter, or a fixed root)
    root_drift_m: float | None = None
    seed: int = 0  # the seed it was trained from
    # every seed's final return on the same MuJoCo episodes, when several were trained side by side
    # (``seed_race``; this result is the best of them)
    seed_returns: list[float] = field(default_factory=list)
    # beside them, the seed each of them took from when they met (None: its own kept)
    seed_took_from: list[int | None] = field(default_factory=list)
    # the seed whose policy and critic this one took when the seeds met (``RewardSettings.meet_at``),
    # or whose value (``ValueIteration.meet``)
    took_from: int | None = None
    # with value iteration (``ValueFitter.follows``): the share of the emulated states the kept policy
    # drives to where its control is the greedy policy's over the value, and the backed-up value its
    # control loses there a decision (the return's units); None for the actor-critic
    greedy_agreement: float | None = None
    greedy_regret: float | None = None
    # the emulator fine-tuned while it learned (exploring runs, refinements), the one it is served
    # with, and (S,) lows and highs of the states it was fine-tuned on; None: the stored one unchanged
    emulator: StructuredEmulator | None = None
    envelope: tuple[FloatArray, FloatArray] | None = None

    @property
    def evaluate_runs(self) -> int:
        return len(self.returns_physics)


class FallReport(TypedDict):
    """A fall in an episode on MuJoCo: which episode, when (seconds into it), the state it lay in and
    from when it was up again for good (``Fall.up_again``; None: it lay at the end)."""

    episode: int
    time_s: float
    state: list[float]
    up_again_s: float | None


def falls(task: SuiteTask, ctx: Context, runs: Episodes, policy_step_s: float) -> list[FallReport]:
    """The first fall of each episode (``SuiteTask.fall``) and whether it got up again for good after
    it, none for a task without one."""
    if task.fall is None:
        return []
    first = task.fall.first(ctx, runs.states, settle=math.ceil(task.fall.settle_s / policy_step_s - 1e-9))
    again = task.fall.up_again(ctx, runs.states, first)
    return [
        {
            "episode": i,
            "time_s": round(float(k * policy_step_s), 3),
            "state": runs.states[i, k].tolist(),
            "up_again_s": round(float(again[i] * policy_step_s), 3) if again[i] >= 0 else None,
        }
        for i, k in enumerate(first.tolist())
        if k >= 0
    ]


def draw_starts(
    task: SuiteTask, physical: PhysicalModel, rng: np.random.Generator, n: int
) -> tuple[FloatArray, FloatArray]:
    """(n, S) states and (n, P) parameters from the task's own ``reset``."""
    m = physical.mj_model
    states, params = [], []
    for _ in range(n):
        qpos, qvel, p = task.reset(m, rng)
        full = physical.to_physics(physical.rest_state()[None])
        full[0, physical.qpos_slice] = qpos
        at = physical.qpos_slice.stop
        full[0, at : at + m.nv] = qvel
        states.append(physical.from_physics(full)[0])
        params.append(p)
    return np.array(states), np.array(params).reshape(n, len(task.params))


def run_on_mujoco(
    task: SuiteTask,
    physical: PhysicalModel,
    ctx: Context,
    act: Callable[[FloatArray, FloatArray], FloatArray],
    starts: FloatArray,
    params: FloatArray,
) -> Episodes:
    """Episodes of the task on MuJoCo from starts (N, S), the policy acting every ``repeat`` control
    steps, the reward exact (``smooth`` off) after every control step, summed."""
    n, k = len(starts), task.policy_steps
    states = np.zeros((n, k + 1, starts.shape[1]))
    controls = np.zeros((n, k, physical.num_controls))
    returns = np.zeros(n)
    s = np.asarray(starts, dtype=np.float64)
    states[:, 0] = s
    p_t = torch.as_tensor(params, dtype=torch.float64)
    done = 0
    for i in range(k):
        u = act(s, params)
        controls[:, i] = u
        u_t = torch.as_tensor(u, dtype=torch.float64)
        for _ in range(min(task.repeat, task.episode_steps - done)):
            s = physical.step_held(s, u, None, task.control_substeps)
            with torch.no_grad():
                r = task.reward(ctx, torch.as_tensor(s), u_t, p_t, False).numpy()
            returns += np.where(np.isfinite(r), r, 0.0)
            done += 1
        states[:, i + 1] = s
    return Episodes(returns, states, controls, np.asarray(params))


@torch.no_grad()
def root_drift(
    step: Callable[[Tensor, Tensor], Tensor],
    policy: Callable[[Tensor, Tensor], Tensor],
    ctx: Context,
    episodes: Episodes,
    super_timestep: float,
    seconds: float = DRIFT_S,
) -> float | None:
    """The mean distance (m) between the root body (the first joint's) on the emulator ``step`` and in
    ``episodes`` run on MuJoCo, ``seconds`` after the same starts, each in its own closed loop under
    ``policy``: how far the model strays under the policy it taught (inf when every emulated episode
    diverged). None when the episodes are shorter or the model has no joint."""
    k = round(seconds / super_timestep)
    m = ctx.m
    if m.njnt == 0 or k > episodes.states.shape[1] - 1:
        return None
    root = int(m.jnt_bodyid[0])
    s = torch.as_tensor(episodes.states[:, 0], dtype=torch.float32)
    p = torch.as_tensor(episodes.params, dtype=torch.float32)
    for _ in range(k):
        s = step(s, policy(s, p))
    emulated = ctx.kin.places(s.double())[0][:, root]
    physical = ctx.kin.places(torch.as_tensor(episodes.states[:, k]))[0][:, root]
    gap = torch.linalg.vector_norm(emulated - physical, dim=1)
    return float(gap[torch.isfinite(gap)].mean()) if bool(torch.isfinite(gap).any()) else math.inf


def actor_rate(rate: float, elapsed: float, seconds: float, anneal_from: float = 0.0) -> float:
    """The actor's learning rate ``elapsed`` seconds into a budget of ``seconds``: ``rate`` until
    ``anneal_from``, then down a cosine to a tenth of it at the budget's end."""
    frac = min(1.0, max(0.0, elapsed - anneal_from) / max(1.0, seconds - anneal_from))
    return rate * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * frac)))


def every_state(states: FloatArray, params: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Episodes' states (N, K+1, S) and parameters (N, P) → every state (N·(K+1), S) beside its
    episode's parameters (N·(K+1), P): restarts' pools."""
    n, k1, width = states.shape
    return states.reshape(-1, width), np.repeat(params, k1, axis=0).reshape(n * k1, -1)


def value_iteration_of(task: SuiteTask, settings: RewardSettings) -> ValueIteration | None:
    """How the value is fitted by value iteration: the settings', else the task's; None for the
    actor-critic alone (``RewardSettings.value_iteration``)."""
    how = task.value_iteration if settings.value_iteration is None else settings.value_iteration
    return how if isinstance(how, ValueIteration) else None


def random_search_of(task: SuiteTask, settings: RewardSettings) -> RandomSearch | None:
    """How the policy is found by random search: the settings', else the task's; None for another
    learner (``RewardSettings.random_search``)."""
    how = task.random_search if settings.random_search is None else settings.random_search
    return how if isinstance(how, RandomSearch) else None


def seeds_meet(task: SuiteTask, settings: RewardSettings) -> bool:
    """Whether seeds side by side meet (once): at a check past ``RewardSettings.meet_at``, or when
    their values are fitted (``ValueIteration.meet``)."""
    how = value_iteration_of(task, settings)
    return settings.meet_at is not None or (how is not None and how.meet)


@dataclass
class Meeting:
    """What a seed brings to the meeting of seeds trained side by side (``RewardSettings.meet_at``):
    its best return on MuJoCo's checks so far, the policy that earned it and its critics; or, met
    when their values are fitted (``ValueIteration.meet``), its value's check and the value."""

    seed: int
    best_return: float
    policy: dict[str, Tensor]
    critic: dict[str, Tensor]
    target_critic: dict[str, Tensor]


class RewardTrainer:
    """One reward policy being trained through an emulator artifact (module doc)."""

    def __init__(
        self,
        task: SuiteTask,
        path: Path,
        settings: RewardSettings,
        on_progress: Callable[[RewardProgress], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        meet: Callable[[Meeting], Meeting | None] | None = None,
    ) -> None:
        self.t0 = time.perf_counter()
        self.task, self.settings, self.path = task, settings, path
        self.on_progress, self.should_stop = on_progress, should_stop
        # the other seeds, met once (``RewardSettings.meet_at``, or ``ValueIteration.meet``): given
        # this seed's best so far, the best seed's to take instead, or None to keep its own
        self.meet = meet
        self.took_from: int | None = None
        self.manifest = registry.read_manifest(path)
        if self.manifest.substeps != task.substeps:
            raise ValueError(
                f"{task.name} acts every {task.substeps} physical steps; the emulator at {path} steps "
                f"{self.manifest.substeps}"
            )
        self.physical = registry.load_physical_model(path, self.manifest)
        emu = artifacts.load_emulator(path)
        if not isinstance(emu, StructuredEmulator):
            raise ValueError(f"{task.name}: a reward policy needs a single-network emulator")
        self.emu: StructuredEmulator = emu
        self.step = FastStep(emu)
        self.ctx = Context(self.physical.mj_model, list(self.manifest.layout))
        self.rng = np.random.default_rng(settings.seed)
        torch.manual_seed(settings.seed)
        self.gamma = math.exp(-self.manifest.super_timestep / task.discount_s)
        self.horizon = settings.horizon or task.horizon
        self.refine_keep = task.refine_keep if settings.refine_keep is None else settings.refine_keep
        self.restarts = Restarts(
            task.restarts.mujoco if settings.mujoco_share is None else settings.mujoco_share,
            task.restarts.explore if settings.explore_share is None else settings.explore_share,
            task.restarts.rewarded if settings.rewarded_share is None else settings.rewarded_share,
            task.restarts.explore_from if settings.explore_from is None else settings.explore_from,
            task.restarts.failing if settings.failing_share is None else settings.failing_share,
        )
        self.mujoco_steps = 0
        # seconds one episode of the latest check on MuJoCo took: what the final judging will cost
        # (``deadline``), 0 until a check has run
        self.episode_check_s = 0.0
        self.refinements = 0
        self.kept: sampling.Sequences | None = None  # the typical motion (``typical_motion``), once drawn
        self.env_low, self.env_high = self._envelope()
        self.outside_steps = 0
        self.emulated_steps = 0
        self.start_states, self.start_params = draw_starts(task, self.physical, self.rng, 2048)
        self.visited: list[tuple[FloatArray, FloatArray]] = []
        # the states (N, S) and parameters (N, P) of the latest checks' failing episodes (``Restarts.failing``)
        self.failed: deque[tuple[FloatArray, FloatArray]] = deque(maxlen=FAILING_CHECKS)
        self.runs: list[Episodes] = []
        self.low = np.array([c.low for c in self.manifest.controls])
        self.high = np.array([c.high for c in self.manifest.controls])
        self.exploring = task.exploring if settings.exploring is None else settings.exploring
        vi = self.value_iteration = value_iteration_of(task, settings)
        if vi is not None and vi.meet and settings.meet_at is not None:
            raise ValueError(
                f"{task.name}: the seeds meet once, when their values are fitted (value iteration's meet) "
                "or at meet_at, not both"
            )
        rs = self.random_search = random_search_of(task, settings)
        if rs is not None and (vi is not None or settings.teacher == PLANNER):
            raise ValueError(
                f"{task.name}: random search is a learner of its own, not beside value iteration or a teacher"
            )
        self.value_fitter: ValueFitter | None = None  # its value and labels, once ``learn_from_value`` ran
        # the kept policy beside the greedy one over the value (``ValueFitter.follows``), once copied
        self.greedy_follow: tuple[float, float] | None = None
        # seconds of measuring kept for after learning, before the final judging (``deadline``)
        self.measure_after_s = 0.0
        features = self._features()
        self.policy: RewardPolicy
        if vi is not None and vi.copy_as == "choice" and settings.teacher != PLANNER:
            # the candidates the value is backed up over, the policy's choices too (drawn apart from
            # the training's own draws, so that choosing leaves them as they were); a policy that
            # copies the planner first regresses onto its controls, and then onto the greedy ones
            grid = candidate_controls(
                self.low, self.high, vi.candidates, np.random.default_rng(settings.seed + 37)
            )
            self.policy = ChoicePolicy(features, grid, vi.policy_hidden, vi.blend)
        else:
            hidden = vi.policy_hidden if vi else rs.hidden if rs else settings.hidden
            self.policy = RewardPolicy(features, self.low, self.high, hidden)
        self.critic = Critic(copy.deepcopy(features), vi.hidden if vi else settings.critic_hidden)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)

    def _features(self) -> Features:
        """Angles and plain columns from the layout (less the task's ``unobserved`` groups); centres
        and spreads from emulated runs of random held controls from the task's starts (no MuJoCo
        steps)."""
        angles: list[int] = []
        plain: list[int] = []
        for g in self.manifest.layout:
            if g.name in self.task.unobserved:
                continue
            cols = list(range(g.offset, g.offset + g.size))
            (angles if g.kind in ("angle", "heading") else plain).extend(cols)
        idx = self.rng.integers(len(self.start_states), size=256)
        s = torch.as_tensor(self.start_states[idx], dtype=torch.float32)
        seen = [s]
        with torch.no_grad():
            for _ in range(self.task.policy_steps // 4):
                u = torch.as_tensor(
                    self.rng.uniform(self.low, self.high, (len(s), len(self.low))), dtype=torch.float32
                )
                s = self.step(s, u)
                s = torch.where(torch.isfinite(s), s, seen[0])
                seen.append(s)
        allv = torch.cat(seen).double().numpy()
        mean = allv.mean(axis=0)
        scale = np.maximum(allv.std(axis=0), 1e-2)
        observe = None
        observed = 0
        if self.task.observe is not None:
            task_observe, ctx = self.task.observe, self.ctx

            def observe(state: Tensor, params: Tensor) -> Tensor:
                return task_observe(ctx, state, params)

            observed = int(observe(s[:1].float(), torch.as_tensor(self.start_params[:1]).float()).shape[1])
        return Features(angles, plain, mean, scale, len(self.task.params), observe, observed)

    def _envelope(self) -> tuple[Tensor, Tensor]:
        """(S,) lows and highs of the emulator's training envelope (``Manifest.envelope``), infinite
        where it is indifferent to a value or records none."""
        low = np.full(self.manifest.state_size, -np.inf)
        high = np.full(self.manifest.state_size, np.inf)
        offsets = {g.name: g.offset for g in self.manifest.layout}
        for env in self.manifest.envelope or []:
            at = offsets[env.group]
            for i, (lo, hi) in enumerate(zip(env.low, env.high, strict=True)):
                low[at + i] = -np.inf if lo is None else lo
                high[at + i] = np.inf if hi is None else hi
        return torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)

    @property
    def outside_share(self) -> float:
        """The share of the emulated states so far outside the emulator's training envelope."""
        return self.outside_steps / self.emulated_steps if self.emulated_steps else 0.0

    # ------------------------------------------------------------------ episodes
    def envelope_box(self) -> tuple[FloatArray, FloatArray]:
        """(S,) lows and highs of the emulator's envelope; an angle it is indifferent to spans a turn,
        any other such value its typical spread (``Features``) about its centre."""
        features = self.policy.features
        low = np.full(self.manifest.state_size, -np.pi)
        high = np.full(self.manifest.state_size, np.pi)
        plain = features.plain.numpy()
        low[plain] = features.mean.numpy() - 2 * features.scale.numpy()
        high[plain] = features.mean.numpy() + 2 * features.scale.numpy()
        bounded = np.isfinite(self.env_low.numpy()) & np.isfinite(self.env_high.numpy())
        low[bounded] = self.env_low.numpy()[bounded]
        high[bounded] = self.env_high.numpy()[bounded]
        return low, high

    def restart(self, n: int) -> tuple[FloatArray, FloatArray]:
        """n new starting states and parameters: the task's starts, states reached on MuJoCo, or
        states anywhere in the emulator's envelope (``Restarts``)."""
        draw = self.rng.random(n)
        idx = self.rng.integers(len(self.start_states), size=n)
        states, params = self.start_states[idx].copy(), self.start_params[idx].copy()
        shares = self.restarts
        explore = draw < shares.explore
        if explore.any():
            states[explore] = self.envelope_states(params[explore])
        from_mujoco = (draw >= shares.explore) & (draw < shares.explore + shares.mujoco)
        if not self.visited:
            from_mujoco[:] = False
        # drawn only where asked for: a training without it draws the same restarts as before it
        failing = np.zeros(n, bool)
        if shares.failing > 0 and self.failed:
            failing = from_mujoco & (self.rng.random(n) < shares.failing)
        for chosen, pool in ((from_mujoco & ~failing, self.visited), (failing, self.failed)):
            if chosen.any():
                vs = np.concatenate([v[0] for v in pool])
                vp = np.concatenate([v[1] for v in pool])
                pick = self.rng.integers(len(vs), size=int(chosen.sum()))
                states[chosen], params[chosen] = vs[pick], vp[pick]
        return states, params

    def envelope_states(self, params: FloatArray) -> FloatArray:
        """(n, S) states anywhere in the emulator's envelope for episodes of parameters (n, P): each
        uniform in its box, or (the ``rewarded`` share) the best paid (the smooth reward, controls at
        rest) of ``tournament`` such draws: a reverse curriculum (Florensa et al. 2017) whose episodes
        begin where the reward is, so that the policy learns to stay there, and the critic what being
        there is worth, before it knows the way (a pole upright: balanced before it is swung up)."""
        n, t = len(params), self.settings.tournament
        draw = self.box_states if self.restarts.explore_from == "box" else self._motion_states
        states = draw(n)
        best = self.rng.random(n) < self.restarts.rewarded
        k = int(best.sum())
        if k and t > 1:
            cand = draw(k * t)
            p = np.repeat(params[best], t, axis=0)
            u = torch.as_tensor(np.repeat((self.low + self.high)[None] / 2, k * t, axis=0))
            with torch.no_grad():
                r = self.task.reward(self.ctx, torch.as_tensor(cand), u, torch.as_tensor(p), True)
            pick = torch.nan_to_num(r, nan=-1.0).reshape(k, t).argmax(dim=1).numpy()
            states[best] = cand.reshape(k, t, -1)[np.arange(k), pick]
        return states

    def box_states(self, n: int) -> FloatArray:
        """(n, S) states each variable uniform in the envelope's box."""
        low, high = self.envelope_box()
        return self.rng.uniform(low, high, (n, len(low)))

    def _motion_states(self, n: int) -> FloatArray:
        """(n, S) states of the typical motion on MuJoCo (``typical_motion``)."""
        pool = self.typical_motion().states
        flat = pool.reshape(-1, pool.shape[2])
        return flat[self.rng.integers(len(flat), size=n)].copy()

    def typical_motion(self) -> sampling.Sequences:
        """Windows of the typical motion the emulator was trained on, sampled on MuJoCo once (its
        steps counted): kept beside the policy's runs when refining, and drawn from when exploring."""
        if self.kept is None:
            count = self.refine_keep or 256
            self.kept = sampling.generate_sequences(
                self.physical, self.manifest.substeps, count, REFINE_WINDOW, self.settings.seed + 17,
                progress=False,
            )  # fmt: skip
            lead = sampling.lead_steps(self.physical, self.manifest.substeps)
            self.mujoco_steps += count * (lead + REFINE_WINDOW * self.manifest.substeps)
        return self.kept

    def act(self, states: FloatArray, params: FloatArray) -> FloatArray:
        return self.policy.act(states, params)

    def episodes(
        self, act: Callable[[FloatArray, FloatArray], FloatArray], n: int, rng: np.random.Generator
    ) -> Episodes:
        """n episodes on MuJoCo from the task's starts drawn from rng, ``act`` driving (counted)."""
        starts, params = draw_starts(self.task, self.physical, rng, n)
        runs = run_on_mujoco(self.task, self.physical, self.ctx, act, starts, params)
        self.mujoco_steps += n * self.task.episode_steps * self.task.control_substeps
        return runs

    def evaluate(self, n: int, seed: int) -> tuple[Episodes, float]:
        """The policy on MuJoCo over n episodes of new starts (their returns), and on the emulator
        from the same starts (the mean return)."""
        t = time.perf_counter()
        phys = self.episodes(self.act, n, np.random.default_rng(seed))
        starts, params = draw_starts(self.task, self.physical, np.random.default_rng(seed), n)
        emulated = self.emulated_return(starts, params)
        self.episode_check_s = (time.perf_counter() - t) / max(1, n)
        return phys, emulated

    @torch.no_grad()
    def emulated_return(
        self,
        starts: FloatArray | Tensor,
        params: FloatArray | Tensor,
        act: Callable[[Tensor, Tensor], Tensor] | None = None,
    ) -> float:
        """Mean return of episodes on the emulator (the reward at every super-step, times its control
        steps), ``act`` (states (B, S), parameters (B, P)) → (B, U) driving, the policy if None."""
        s = torch.as_tensor(starts, dtype=torch.float32)
        p = torch.as_tensor(params, dtype=torch.float32)
        drive = self.policy if act is None else act
        total = torch.zeros(len(s))
        for _ in range(self.task.policy_steps):
            u = drive(s, p)
            s = self.step(s, u)
            r = self.task.reward(self.ctx, s, u, p, False)
            total += torch.nan_to_num(r) * self.task.repeat
        return float(total.mean())

    # ------------------------------------------------------------------ one iteration
    def iterate(
        self, s: Tensor, p: Tensor, opt_actor: torch.optim.Optimizer, opt_critic: torch.optim.Optimizer
    ) -> tuple[Tensor, float]:
        """Advance the episodes (B, S) one horizon, update actor and critic; the states reached and the loss."""
        cfg, task = self.settings, self.task
        h_steps, gamma = self.horizon, self.gamma
        half = self.policy.half_range
        states, rewards = [s], []
        loss = torch.zeros(())
        disc = 1.0
        x = s
        for _ in range(h_steps):
            u = self.policy(x, p)
            if cfg.noise > 0:
                u = u + cfg.noise * half * torch.randn_like(u)
            u = torch.maximum(torch.minimum(u, self.policy.centre + half), self.policy.centre - half)
            x = self.step(x, u) if cfg.rollouts == "emulator" else self.step_on_mujoco(x, u)
            r = task.reward(self.ctx, x, u, p, True)
            r = torch.nan_to_num(r)
            loss = loss - disc * r.mean()
            disc *= gamma
            states.append(x.detach())
            rewards.append(r.detach())
        reached = torch.stack(states[1:])  # (H, B, S)
        outside = (reached < self.env_low) | (reached > self.env_high)
        self.outside_steps += int(outside.any(dim=2).sum())
        self.emulated_steps += reached.shape[0] * reached.shape[1]
        end_value = self.critic(x, p)
        loss = (loss - disc * end_value.mean()) / h_steps
        opt_actor.zero_grad()
        if torch.isfinite(loss):
            loss.backward()
            if all(q.grad is None or bool(torch.isfinite(q.grad).all()) for q in self.policy.parameters()):
                nn.utils.clip_grad_norm_(self.policy.parameters(), cfg.grad_clip)
                opt_actor.step()
        self.critic.zero_grad()  # the actor's loss reached the critic's weights; they learn below
        self.update_critic(torch.stack(states), torch.stack(rewards), p, opt_critic)
        return x.detach(), float(loss.detach())

    def step_on_mujoco(self, x: Tensor, u: Tensor) -> Tensor:
        """One super-step from states (B, S) under controls (B, U) whose value is MuJoCo's and whose
        gradient is the emulator's at ``x`` (``RewardSettings.rollouts``): MuJoCo's state plus the
        emulator's prediction less itself detached, so that the path follows the physics and the
        chain rule the model's Jacobians along it."""
        predicted = self.step(x, u)
        with torch.no_grad():
            real = self.physical.step_held(
                x.detach().double().numpy(),
                u.detach().double().numpy(),
                None,
                self.manifest.substeps,
                threads=torch.get_num_threads(),
            )
        self.mujoco_steps += len(real) * self.manifest.substeps
        return torch.as_tensor(real, dtype=predicted.dtype) + predicted - predicted.detach()

    def update_critic(self, states: Tensor, rewards: Tensor, p: Tensor, opt: torch.optim.Optimizer) -> None:
        """TD(λ) targets from the horizon's states (H+1, B, S) and rewards (H, B), with the target critic."""
        cfg, gamma = self.settings, self.gamma
        h, b = rewards.shape
        with torch.no_grad():
            values = self.target_critic(states.reshape(-1, states.shape[-1]), p.repeat(h + 1, 1)).reshape(
                h + 1, b
            )
            values = torch.nan_to_num(values)
            targets = torch.zeros(h, b)
            ret = values[-1]
            for t in reversed(range(h)):
                ret = rewards[t] + gamma * ((1 - cfg.lam) * values[t + 1] + cfg.lam * ret)
                targets[t] = ret
        x = states[:-1].reshape(-1, states.shape[-1])
        pp = p.repeat(h, 1)
        y = targets.reshape(-1)
        ok = torch.isfinite(x).all(dim=1) & torch.isfinite(y)
        x, pp, y = x[ok], pp[ok], y[ok]
        for _ in range(cfg.critic_steps):
            pick = torch.randint(len(x), (max(1, len(x) // 2),))
            err = self.critic(x[pick], pp[pick]) - y[pick]
            opt.zero_grad()
            (err**2).mean().backward()
            nn.utils.clip_grad_norm_(self.critic.parameters(), 1.0)
            opt.step()
        with torch.no_grad():
            for tp, cp in zip(self.target_critic.parameters(), self.critic.parameters(), strict=True):
                tp.mul_(1 - cfg.target_tau).add_(cfg.target_tau * cp)

    def lost(self, s: Tensor) -> Tensor:
        """(B,) episodes whose state diverged or left the states the emulator knows."""
        z = self.policy.features.plain_z(s)
        return ~torch.isfinite(s).all(dim=1) | (z.abs() > FEATURE_LIMIT).any(dim=1)

    # ------------------------------------------------------------------ refinement
    def keep_runs(self, runs: Episodes, emulated: float, may_refine: bool = True) -> bool:
        """Keep a check's MuJoCo ``runs`` (restarts begin from their states; the emulator learns them)
        and, where ``may_refine``, refine the emulator when their mean return is off the ``emulated``
        one from the same starts by more than ``refine_gap`` of an episode. Whether it was refined."""
        cfg = self.settings
        self.runs.append(runs)
        n = len(runs.returns)
        self.visited.append(every_state(runs.states, runs.params))
        top = float(runs.returns.max()) if n else 0.0
        failing = runs.returns < 0.5 * top if top > 0 and self.restarts.failing > 0 else np.zeros(n, bool)
        if failing.any():
            self.failed.append(every_state(runs.states[failing], runs.params[failing]))
        gap = abs(emulated - runs.mean) / self.task.episode_steps
        refined = cfg.refine and may_refine and gap > cfg.refine_gap
        if refined:
            self.refine()
        return refined

    def refine(self) -> None:
        """Fine-tune the emulator on every MuJoCo run of the policy so far (windows of
        ``REFINE_WINDOW`` super-steps) and on ``refine_keep`` windows of the typical motion it was
        trained on (drawn once), so that it stays right where it was; the runs' states widen the
        envelope the emulated states are measured against."""
        fine_tune_on_runs(
            self.emu,
            np.concatenate([r.states for r in self.runs]),
            np.concatenate([r.controls for r in self.runs]),
            self.manifest.train_config,
            self.settings.refine_seconds,
            int(self.rng.integers(1 << 30)),
            window=REFINE_WINDOW,
            keep=self.typical_motion() if self.refine_keep > 0 else None,
            should_stop=self.should_stop,
        )
        self.step = FastStep(self.emu)
        self.refinements += 1
        # the emulator has now learnt the policy's runs: their states join its envelope
        self.widen_envelope(np.concatenate([r.states.reshape(-1, r.states.shape[2]) for r in self.runs]))

    def widen_envelope(self, states: FloatArray) -> None:
        """The envelope the emulated states are measured against, widened to hold ``states`` (N, S)."""
        seen = torch.as_tensor(states[np.isfinite(states).all(axis=1)], dtype=torch.float32)
        if len(seen):
            self.env_low = torch.minimum(self.env_low, seen.amin(dim=0))
            self.env_high = torch.maximum(self.env_high, seen.amax(dim=0))

    def explore(self) -> None:
        """Before learning: the emulator fine-tuned on ``exploring.runs`` random runs from the task's
        starts (``exploring_runs``; their MuJoCo steps counted), the typical motion kept beside them;
        their states join its envelope. A budget too small for the runs' fine-tuning to take at most
        ``EXPLORE_SHARE`` of it makes fewer runs, fine-tuned on for less, in proportion."""
        how = self.exploring
        scale = min(1.0, EXPLORE_SHARE * self.settings.seconds / max(how.seconds, 1e-9))
        if scale < 1.0:
            how = replace(how, runs=max(1, round(how.runs * scale)), seconds=how.seconds * scale)
        t0 = time.perf_counter()
        pick = self.rng.integers(len(self.start_states), size=how.runs)
        states, controls = random_runs(
            self.physical, self.start_states[pick], self.manifest.substeps, self.low, self.high, how, self.rng
        )
        self.mujoco_steps += how.runs * how.steps * self.manifest.substeps
        fitted = fine_tune_on_runs(
            self.emu, states, controls, self.manifest.train_config, how.seconds,
            int(self.rng.integers(1 << 30)), window=REFINE_WINDOW, keep=self.typical_motion(),
            should_stop=self.should_stop,
        )  # fmt: skip
        self.step = FastStep(self.emu)
        self.refinements += 1
        self.widen_envelope(states.reshape(-1, states.shape[2]))
        log.info(
            "%s: the emulator fine-tuned on %d random runs from the task's starts (rollout loss %.3g -> %.3g), %.0f s",
            self.task.name, how.runs, fitted.get("rollout_loss_before", math.nan), fitted.get("rollout_loss_after", math.nan),
            time.perf_counter() - t0,
        )  # fmt: skip

    def _meet(self, score: float, policy: dict[str, Tensor], critic: dict[str, Tensor]) -> Meeting | None:
        """Meet the other seeds, once: bring this seed's ``score`` with its policy, critic and target
        critic (copies); the best seed's to take instead, or None to keep its own."""
        meet, self.meet = self.meet, None  # once
        assert meet is not None
        other = meet(
            Meeting(
                self.settings.seed,
                score,
                copy.deepcopy(policy),
                copy.deepcopy(critic),
                copy.deepcopy(self.target_critic.state_dict()),
            )
        )
        return None if other is None or other.seed == self.settings.seed else other

    def meet_the_seeds(self, best: tuple[float, dict[str, Tensor]]) -> tuple[float, dict[str, Tensor]]:
        """Meet the other seeds once (``RewardSettings.meet_at``): a seed behind takes the best one's
        best policy (as its own best so far and as the policy it trains on) and its critics; its
        optimisers then start afresh. Returns the best so far."""
        other = self._meet(best[0], best[1], self.critic.state_dict())
        if other is None:
            return best
        log.info(
            "%s: seed %d (best %.1f) takes seed %d's policy (best %.1f)",
            self.task.name, self.settings.seed, best[0], other.seed, other.best_return,
        )  # fmt: skip
        self.policy.load_state_dict(other.policy)
        self.critic.load_state_dict(other.critic)
        self.target_critic.load_state_dict(other.target_critic)
        self.took_from = other.seed
        return other.best_return, copy.deepcopy(other.policy)

    def meet_over_values(self, fitter: ValueFitter) -> None:
        """Meet the other seeds once their values are fitted (``ValueIteration.meet``): a seed whose
        V's check (``ValueFitter.value_check``) is behind the best one's takes that V (all its
        critics) and copies it from its own draws."""
        other = self._meet(fitter.value_check, self.policy.state_dict(), fitter.value.state_dict())
        if other is None:
            return
        log.info(
            "%s: seed %d (its value's check %.1f) takes seed %d's value (%.1f)",
            self.task.name, self.settings.seed, fitter.value_check, other.seed, other.best_return,
        )  # fmt: skip
        # the value alone: this seed's emulator, refined on its own runs, is the one it copies through
        fitter.value.load_state_dict(other.critic)
        self.target_critic.load_state_dict(self.critic.state_dict())
        self.took_from = other.seed

    # ------------------------------------------------------------------ the loop
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def deadline(self, checks: int = 0) -> float:
        """The elapsed seconds by which learning stops, so that the training ends within ``seconds``
        judged: the budget less the final episodes (``final_episodes``) and ``checks`` more on MuJoCo
        at the latest check's pace, a quarter on top for the rest of ``finish`` (the root's drift, the
        emulated return), and the seconds kept for measuring after learning (``measure_after_s``). A
        budget is the whole training's, its final judging included."""
        episodes = self.settings.final_episodes + checks
        return self.settings.seconds - FINISH_MARGIN * episodes * self.episode_check_s - self.measure_after_s

    def report(self, iteration: int, loss: float | None, return_physics: float | None) -> None:
        """Tell ``on_progress`` (when given) where the training is."""
        if self.on_progress is not None:
            self.on_progress(
                {
                    "iteration": iteration,
                    "loss": loss,
                    "return_physics": return_physics,
                    "mujoco_steps": self.mujoco_steps,
                    "elapsed_s": round(self.elapsed(), 3),
                }
            )

    def train(self) -> RewardResult:
        best = (-math.inf, copy.deepcopy(self.policy.state_dict()))
        history: list[tuple[int, float, float]] = []
        it = 0
        if self.exploring.runs:
            self.explore()
            if self.should_stop is not None and self.should_stop():  # cancelled while it explored
                return self.finish(best, history, it, "cancelled")
        if self.settings.teacher == PLANNER:
            copier = PlannerCopy(self)
            best, history, it, stop = copier.train()
            if stop != "budget" or self.settings.copying.rounds is None or self.elapsed() >= self.deadline():
                return self.finish(best, history, it, stop)
            # the actor-critic goes on from the copy, and restarts where the planner's runs went
            self.policy.load_state_dict(best[1])
            self.visited.append(copier.examples.joined())
        if self.random_search is not None:
            return self.finish(*SearchLearner(self, self.random_search).learn(best, history, it))
        if self.value_iteration is not None:
            return self.finish(*self.learn_from_value(self.value_iteration, best, history, it))
        return self.finish(*self.learn(best, history, it))

    def learn_from_value(
        self,
        how: ValueIteration,
        best: tuple[float, dict[str, Tensor]],
        history: list[tuple[int, float, float]],
        it: int,
    ) -> tuple[tuple[float, dict[str, Tensor]], list[tuple[int, float, float]], int, str]:
        """The critic by value iteration for ``how.share`` of the budget, then rounds of copying the
        policy greedy over it until the budget is spent, each checked on MuJoCo and the best kept
        (``value_iteration``), and with ``how.actor_critic`` the actor-critic from the best copy for
        that share of the budget; returns as ``learn`` does."""
        cfg = self.settings
        fitter = self.value_fitter = ValueFitter(self, how)
        fitter.fit(how.share * cfg.seconds - self.elapsed())
        if how.meet and self.meet is not None and not (self.should_stop is not None and self.should_stop()):
            self.meet_over_values(fitter)
        opt = torch.optim.Adam(self.policy.parameters(), lr=how.lr)
        stop, first, round_s, next_s = "budget", it, 0.0, 0.0
        # (episodes, seed) of the same starts every round (``fixed_checks``), drawn once
        fixed = None if how.fixed_checks is None else (how.fixed_checks, int(self.rng.integers(1 << 30)))
        # a round (its copying and its check) that would end past the deadline, less the measure of
        # how closely the kept policy follows the greedy one, is not begun; a round takes longer than
        # the one before it as its labels grow (the ball in the cup's 21 s to 30 s over 13 rounds,
        # 3.5 s more in its last: 4 s past its budget), so the next is foreseen as the last one and
        # its growth, a quarter on top as for the judging; the actor-critic's share (``actor_critic``)
        # comes after them
        reserved = how.actor_critic * cfg.seconds
        while (
            it == first
            or self.elapsed() + FINISH_MARGIN * (next_s + fitter.follows_s()) < self.deadline() - reserved
        ) and (cfg.max_iterations is None or it < cfg.max_iterations):
            if self.should_stop is not None and self.should_stop():
                stop = "cancelled"
                break
            began = time.perf_counter()
            loss = fitter.copy_round(it - first, opt)
            it += 1
            if fixed is not None:
                runs, emulated = self.evaluate(*fixed)
            else:
                runs, emulated = self.evaluate(cfg.eval_episodes, int(self.rng.integers(1 << 30)))
            history.append((it, round(self.elapsed(), 1), runs.mean))
            log.info(
                "%s: round %d of copying the greedy policy, fit %.4g, return on MuJoCo %.1f, on the emulator %.1f",
                self.task.name, it - first, loss, runs.mean, emulated,
            )  # fmt: skip
            if runs.mean >= best[0]:
                best = (runs.mean, copy.deepcopy(self.policy.state_dict()))
            self.report(it, loss, runs.mean)
            took = time.perf_counter() - began
            growth = max(0.0, took - round_s) if round_s else 0.0  # none known after the first round
            next_s, round_s = took + growth, took
        self.policy.load_state_dict(best[1])
        if how.actor_critic and stop == "budget":  # from the best copy, its critic the fitted V
            # its end leaves time for measuring how closely the policy follows the greedy one
            # (the hopper's bench ran 47 s past its hour without it)
            self.measure_after_s = FINISH_MARGIN * fitter.follows_s()
            # its learning rate annealed over its own share, not over the whole budget: from 70 %
            # in, the whole budget's schedule began it at 0.29 of the rate and ended it at 0.1
            best, history, it, stop = self.learn(best, history, it, anneal_from=self.elapsed())
            self.policy.load_state_dict(best[1])
        # how closely the kept policy follows the greedy one, where it goes itself
        self.greedy_follow = fitter.follows()
        log.info(
            "%s: the policy takes the greedy policy's control in %.1f %% of the states it drives to, "
            "its choice worth %.3g less a decision",
            self.task.name, 100 * self.greedy_follow[0], self.greedy_follow[1],
        )  # fmt: skip
        return best, history, it, stop

    def learn(
        self,
        best: tuple[float, dict[str, Tensor]],
        history: list[tuple[int, float, float]],
        it: int,
        anneal_from: float = 0.0,
    ) -> tuple[tuple[float, dict[str, Tensor]], list[tuple[int, float, float]], int, str]:
        """The actor-critic until the budget is spent (module doc), from ``it`` iterations and the
        checks' ``history`` so far: the best (return, weights), the history, the iterations and the stop.
        The actor's learning rate falls from ``actor_lr`` to a tenth of it on a cosine from
        ``anneal_from`` seconds into the budget to its end."""
        cfg, task = self.settings, self.task
        first = it
        opt_actor = torch.optim.Adam(self.policy.parameters(), lr=cfg.actor_lr)
        opt_critic = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr)
        starts, params = self.restart(cfg.envs)
        s = torch.as_tensor(starts, dtype=torch.float32)
        p = torch.as_tensor(params, dtype=torch.float32)
        # an emulated episode is a branch of at most ``branch_s`` (MBPO's short model rollouts):
        # ages staggered, so that restarts spread over the iterations
        branch = max(self.horizon, min(task.policy_steps, round(cfg.branch_s / self.manifest.super_timestep)))
        age = self.rng.integers(0, branch, cfg.envs) // self.horizon * self.horizon
        check_every = max(1.0, cfg.eval_every * cfg.seconds)
        next_check = check_every if first == 0 else self.elapsed() + check_every
        value, stop = None, "budget"
        last_return: float | None = None
        # at least one update, however much of the budget its setup took (on a busy machine)
        # its last check and the final judging within the budget
        while (it == first or self.elapsed() < self.deadline(cfg.eval_episodes)) and (
            cfg.max_iterations is None or it < cfg.max_iterations
        ):
            if self.should_stop is not None and self.should_stop():
                stop = "cancelled"
                break
            for group in opt_actor.param_groups:
                group["lr"] = actor_rate(cfg.actor_lr, self.elapsed(), cfg.seconds, anneal_from)
            s, value = self.iterate(s, p, opt_actor, opt_critic)
            it += 1
            age += self.horizon
            again = (age >= branch) | self.lost(s).numpy()
            if again.any():
                ns, npar = self.restart(int(again.sum()))
                s = s.clone()
                p = p.clone()
                s[torch.as_tensor(again)] = torch.as_tensor(ns, dtype=torch.float32)
                p[torch.as_tensor(again)] = torch.as_tensor(npar, dtype=torch.float32)
                age[again] = 0
            last = self.elapsed() >= self.deadline(cfg.eval_episodes) or (
                cfg.max_iterations is not None and it >= cfg.max_iterations
            )
            if self.elapsed() >= next_check or last:
                took_from = self.took_from
                best, runs, emulated = self.check(it, history, best)
                last_return = runs.mean
                log.info(
                    "%s: iteration %d, loss %.4g, return on MuJoCo %.1f, on the emulator %.1f, "
                    "emulated states outside the envelope %.1f %%",
                    task.name, it, value, last_return, emulated, 100 * self.outside_share,
                )  # fmt: skip
                if self.took_from != took_from:  # the optimisers' moments were the old weights'
                    opt_actor = torch.optim.Adam(self.policy.parameters(), lr=cfg.actor_lr)
                    opt_critic = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr)
                self.keep_runs(runs, emulated, may_refine=self.elapsed() < 0.9 * cfg.seconds)
                next_check = self.elapsed() + check_every
                if self.elapsed() >= 0.25 * cfg.seconds and self.outside_share > cfg.max_outside:
                    stop = OUTSIDE
                    break
            self.report(it, value, last_return)
        return best, history, it, stop

    def check(
        self, it: int, history: list[tuple[int, float, float]], best: tuple[float, dict[str, Tensor]]
    ) -> tuple[tuple[float, dict[str, Tensor]], Episodes, float]:
        """A check on MuJoCo after ``it`` iterations: the policy's ``eval_episodes`` there, their mean
        return added to ``history`` and the policy kept when it is the best so far, and past
        ``meet_at`` the seeds met once (``meet_the_seeds``). The best so far, the runs (for the
        caller to keep, ``keep_runs``) and the return on the emulator from the same starts."""
        cfg = self.settings
        runs, emulated = self.evaluate(cfg.eval_episodes, int(self.rng.integers(1 << 30)))
        history.append((it, round(self.elapsed(), 1), runs.mean))
        if runs.mean >= best[0]:
            best = (runs.mean, copy.deepcopy(self.policy.state_dict()))
        if self.meet is not None and cfg.meet_at is not None and self.elapsed() >= cfg.meet_at * cfg.seconds:
            best = self.meet_the_seeds(best)
        return best, runs, emulated

    def finish(
        self,
        best: tuple[float, dict[str, Tensor]],
        history: list[tuple[int, float, float]],
        it: int,
        stop: str,
    ) -> RewardResult:
        """The best policy kept, judged on the final MuJoCo episodes, its drift and falls reported."""
        cfg, task = self.settings, self.task
        if not history:  # stopped before its first check: nothing better to keep than what it has
            best = (-math.inf, copy.deepcopy(self.policy.state_dict()))
        self.policy.load_state_dict(best[1])
        final, _ = self.evaluate(cfg.final_episodes, cfg.judged_on)
        fell = falls(task, self.ctx, final, self.manifest.super_timestep)
        for f in fell:
            log.warning("%s: episode %d fell on MuJoCo after %.2f s", task.name, f["episode"], f["time_s"])
        # judged on the emulator it is served with: the fine-tuned one (stored beside it), else the stored one
        tuned = self.refinements > 0
        self.step = FastStep(self.emu if tuned else artifacts.load_emulator(self.path))  # type: ignore[arg-type]
        starts, params = draw_starts(
            task, self.physical, np.random.default_rng(cfg.judged_on), cfg.final_episodes
        )
        drift = root_drift(self.step, self.policy, self.ctx, final, self.manifest.super_timestep)
        return RewardResult(
            root_drift_m=drift,
            policy=self.policy,
            task=task,
            return_physics=final.mean,
            return_emulator=self.emulated_return(starts, params),
            returns_physics=[float(x) for x in final.returns],
            mujoco_steps=self.mujoco_steps,
            iterations=it,
            wall_s=self.elapsed(),
            refinements=self.refinements,
            return_history=history,
            stop=stop,
            params=self.start_params,
            outside_share=self.outside_share,
            falls=fell,
            seed=cfg.seed,
            took_from=self.took_from,
            greedy_agreement=None if self.greedy_follow is None else self.greedy_follow[0],
            greedy_regret=None if self.greedy_follow is None else self.greedy_follow[1],
            emulator=self.emu if tuned else None,
            envelope=(self.env_low.numpy(), self.env_high.numpy()) if tuned else None,
        )
