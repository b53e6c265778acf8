"""dm_control's suite tasks as reward tasks: how an episode starts and what it earns, written in torch
on the emulator's state so that a policy can be learned through the emulator with the suite's own
reward, and run on MuJoCo with the same reward to be judged.

Each task follows its domain's ``initialize_episode`` (``reset``) and ``get_reward`` (``reward``) in
``dm_control/suite/*.py``: the same bodies, sites and geoms, the same ``tolerance`` bounds, margins
and sigmoids (``tolerance`` below is the suite's ``rewards.tolerance``). A reward with a hard bound
(the pendulum within 8° of upright, the fingertip on a 1.5 cm target, the ball in the cup) pays
nothing until it is met, which leaves a gradient nothing to follow: with ``smooth`` it is given a
margin over which it falls off as the suite's own smooth rewards do (``shaped``: half of it over a
broad margin, for the way there, half over a narrow one, so that being just outside the bound costs
enough to be corrected). The policy is judged with ``smooth`` off, the suite's reward exactly.

An episode is ``episode_steps`` of the suite's control steps (``control_substeps`` physical steps
each); the policy acts every ``substeps`` physical steps, its controls held in between (an action
repeat), and earns the reward of every control step.

Shapes: B batch, S state, U controls, P the task's parameters (the reacher's target).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import mujoco
import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from neuroanimator.catalog.suite import SUITE_TASK_INFO, SuiteTaskInfo
from neuroanimator.control.exploring_runs import ExploringRuns
from neuroanimator.control.kinematics import Kinematics
from neuroanimator.control.random_search import RandomSearch
from neuroanimator.control.value_iteration import ValueIteration
from neuroanimator.core.state import LayoutGroup

FloatArray = NDArray[np.float64]
DEFAULT_VALUE_AT_MARGIN = 0.1  # the suite's ``rewards._DEFAULT_VALUE_AT_MARGIN``


def tolerance(
    x: Tensor,
    lower: float,
    upper: float,
    margin: float = 0.0,
    sigmoid: str = "gaussian",
    value_at_margin: float = DEFAULT_VALUE_AT_MARGIN,
) -> Tensor:
    """1 where ``lower ≤ x ≤ upper``; outside, a sigmoid of the distance to the bounds in units of
    ``margin`` worth ``value_at_margin`` one margin out (0 everywhere outside when ``margin`` is 0)."""
    inside = (x >= lower) & (x <= upper)
    if margin <= 0:
        return inside.to(x.dtype)
    # the distance to the bounds, 0 inside (an infinite bound adds nothing: no inf in any gradient)
    d = torch.zeros_like(x)
    if math.isfinite(lower):
        d = d + (lower - x).clamp_min(0)
    if math.isfinite(upper):
        d = d + (x - upper).clamp_min(0)
    d = d / margin
    if sigmoid == "gaussian":
        scale = math.sqrt(-2 * math.log(value_at_margin))
        out = torch.exp(-0.5 * (d * scale) ** 2)
    elif sigmoid == "quadratic":
        scaled = d * math.sqrt(1 - value_at_margin)
        out = torch.where(scaled.abs() < 1, 1 - scaled**2, torch.zeros_like(scaled))
    elif sigmoid == "linear":
        scaled = d * (1 - value_at_margin)
        out = torch.where(scaled.abs() < 1, 1 - scaled, torch.zeros_like(scaled))
    else:
        raise ValueError(f"unknown sigmoid {sigmoid!r}")
    return torch.where(inside, torch.ones_like(out), out)


def shaped(x: Tensor, lower: float, upper: float, broad: float, narrow: float) -> Tensor:
    """A hard bound made smooth for learning: the mean of ``tolerance`` over a ``broad`` margin (a
    gradient from far away) and over a ``narrow`` one (a gradient just outside the bound, where the
    broad one is nearly flat: a fingertip resting 1 cm off a 1.5 cm target earns nothing)."""
    return (tolerance(x, lower, upper, broad) + tolerance(x, lower, upper, narrow)) / 2


class Context:
    """What a task's reward reads besides the state: the model's kinematics and named places."""

    def __init__(self, m: mujoco.MjModel, layout: list[LayoutGroup]) -> None:
        self.m = m
        self.kin = Kinematics(m, layout)
        self.layout = layout

    def column(self, group: str) -> int:
        """The state column of a named layout group's first value (``slider.pos``, ``hinge.rate``)."""
        for g in self.layout:
            if g.name == group:
                return g.offset
        raise KeyError(f"the state has no group {group!r}")

    def geom_size(self, name: str) -> float:
        return float(self.m.geom_size[mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_GEOM, name), 0])

    def site_size(self, name: str) -> FloatArray:
        return np.asarray(self.m.site_size[mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_SITE, name)])


@dataclass(frozen=True)
class Restarts:
    """Where a reward policy's emulated episodes begin (``reward_policy``), as shares of restarts:
    ``mujoco`` from states the policy reached on MuJoCo, ``explore`` anywhere in the emulator's
    envelope, ``rewarded`` of those the best paid of a few draws; the rest from the task's starts.
    ``explore_from`` says where the exploring ones are drawn: ``box``, each variable uniform in the
    envelope's box (a pendulum's angle and speed are free of each other), or ``motion``, the states of
    runs of the typical motion on MuJoCo (a body on the ground: its feet, height and pitch are bound
    by the floor, and a box's draw puts a foot under it). ``failing``: of those from MuJoCo, the
    share drawn from the episodes of the latest checks that earned under half their check's best
    (where there are any): the starts the policy does not yet rise from are practised more often than
    their share of the runs would have them (a prioritised replay of its failures)."""

    mujoco: float = 0.5
    explore: float = 0.25
    rewarded: float = 0.0
    explore_from: str = "box"
    failing: float = 0.0

    def __post_init__(self) -> None:
        if self.explore_from not in ("box", "motion"):
            raise ValueError(f"explore_from is 'box' or 'motion', not {self.explore_from!r}")
        if not 0.0 <= self.failing <= 1.0:
            raise ValueError(f"the failing share of restarts from MuJoCo is in [0, 1], not {self.failing}")


# a task whose reward lies where its starts and early policies never go (a pole upright, a swing
# needed to get there; a ball in its cup, a throw needed to get it there): half the restarts in the
# envelope, half of those where the reward is paid, so the policy learns to stay there first and the
# critic learns what being there is worth
REVERSE_CURRICULUM = Restarts(mujoco=0.25, explore=0.5, rewarded=0.5)


@dataclass(frozen=True)
class Fall:
    """When a body has fallen: its ``level`` (a function of the states (B, S) → (B,): a torso's height
    in metres, or how upright it is) drops below ``below`` after having reached ``above`` in the
    episode (a walker that never got up has not fallen; one that stood and lies again has). Being up
    counts from ``settle_s`` into the episode: a start drawn with the torso high drops before any
    policy could have held it, and that drop is the start's, not a fall."""

    level: Callable[[Context, Tensor], Tensor]
    above: float
    below: float
    settle_s: float = 1.0

    def levels(self, ctx: Context, states: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, K, S) episodes' states → (N, K) their level."""
        n, k, width = states.shape
        with torch.no_grad():
            return self.level(ctx, torch.as_tensor(states.reshape(n * k, width))).reshape(n, k).numpy()

    def first(self, ctx: Context, states: NDArray[np.float64], settle: int = 0) -> NDArray[np.int64]:
        """(N, K, S) episodes' states → (N,) the index of each one's first fallen state, -1 for none;
        states before index ``settle`` do not count as having been up."""
        level = self.levels(ctx, states)
        up = level >= self.above
        up[:, :settle] = False
        been_up = np.maximum.accumulate(up, axis=1)
        down = been_up & (level < self.below)
        return np.where(down.any(axis=1), down.argmax(axis=1), -1)

    def up_again(
        self, ctx: Context, states: NDArray[np.float64], fallen: NDArray[np.int64]
    ) -> NDArray[np.int64]:
        """(N, K, S) episodes' states and (N,) their falls' indices (``first``, -1 for none) → (N,)
        the index from which each was up again for good: back at ``above`` or higher after its last
        state under ``below``; -1 for none (it lay at the end, or fell again and stayed down). A
        hopper that crouches to the floor and stands for the rest of the episode has recovered."""
        level = self.levels(ctx, states)
        k = level.shape[1]
        at = np.arange(k)[None]
        down = (level < self.below) & (at >= fallen[:, None]) & (fallen[:, None] >= 0)
        last_down = np.where(down.any(axis=1), k - 1 - down[:, ::-1].argmax(axis=1), k)
        up = (level >= self.above) & (at > last_down[:, None])
        return np.where(up.any(axis=1), up.argmax(axis=1), -1)


RewardFn = Callable[[Context, Tensor, Tensor, Tensor, bool], Tensor]
ObserveFn = Callable[[Context, Tensor, Tensor], Tensor]
ResetFn = Callable[[mujoco.MjModel, np.random.Generator], tuple[FloatArray, FloatArray, FloatArray]]


@dataclass(frozen=True, kw_only=True)
class SuiteTask(SuiteTaskInfo):
    """One of the suite's tasks (``SuiteTaskInfo``: its domain, control period, episode and
    parameters) with how its episodes start (``reset``), what they earn (``reward``) and how its
    policy is learned: the discount's time scale, the suite's own observations beyond the state
    (``observe``) and where emulated episodes restart (``restarts``)."""

    reset: ResetFn
    reward: RewardFn
    discount_s: float = 2.0  # seconds over which the training's discount falls to 1/e
    observe: ObserveFn | None = None  # the suite's own observations beyond the state (B, k), for the policy
    restarts: Restarts = Restarts()
    # state groups the policy does not read, as the suite's observations omit them (how far a walker
    # has walked: a policy that read it would meet values it never saw by walking on)
    unobserved: tuple[str, ...] = ()
    fall: Fall | None = None  # when its body has fallen (reported with the time and state of each fall)
    # super-steps of each gradient path through the emulator (``RewardSettings.horizon``), and windows
    # of typical motion kept beside the policy's runs when its emulator is refined (``refine_keep``)
    horizon: int = 32
    refine_keep: int = 0
    # policies trained side by side from this many seeds, the best kept (``RewardSettings.seeds``)
    seeds: int = 1
    # torch threads of its training when it trains from one seed (``RewardSettings.threads``)
    threads: int = 1
    # instead of the actor-critic: a value by value iteration over the envelope, its greedy policy
    # copied into the network (``RewardSettings.value_iteration``); None: the actor-critic
    value_iteration: ValueIteration | None = None
    # instead of the actor-critic: augmented random search through the emulator
    # (``RewardSettings.random_search``); None: another learner
    random_search: RandomSearch | None = None
    # before learning, the emulator fine-tuned on random runs from the task's starts
    # (``RewardSettings.exploring``; ``exploring_runs``)
    exploring: ExploringRuns = field(default_factory=ExploringRuns)
    # how another process builds this task when it does not pickle (a user's task, made of closures):
    # a picklable call that returns it (``seed_race``)
    rebuild: Callable[[], SuiteTask] | None = field(default=None, repr=False, compare=False)

    @property
    def repeat(self) -> int:
        """The suite's control steps per policy step."""
        return max(1, self.substeps // self.control_substeps)

    @property
    def policy_steps(self) -> int:
        """Policy steps in an episode (the last holds its controls to the episode's end)."""
        return -(-self.episode_steps // self.repeat)


# ---------------------------------------------------------------------------------------- starts
def random_joints(m: mujoco.MjModel, rng: np.random.Generator, qpos: FloatArray) -> None:
    """The suite's ``randomize_limited_and_rotational_joints``: a limited hinge or slide uniform over
    its range, an unlimited hinge uniform over [-π, π), an unlimited ball joint's quaternion uniform
    on the sphere, a free joint's orientation drawn as the suite draws it (four uniform [0, 1)
    components, normalised: not uniform over rotations, but the suite's benchmarks were run so) and
    its position left where it was."""
    hinge, slide = mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE
    for j in range(m.njnt):
        adr, kind = int(m.jnt_qposadr[j]), int(m.jnt_type[j])
        if kind in (hinge, slide):
            if m.jnt_limited[j]:
                qpos[adr] = rng.uniform(*m.jnt_range[j])
            elif kind == hinge:
                qpos[adr] = rng.uniform(-np.pi, np.pi)
        elif kind == mujoco.mjtJoint.mjJNT_BALL and not m.jnt_limited[j]:
            quat = rng.standard_normal(4)
            qpos[adr : adr + 4] = quat / np.linalg.norm(quat)
        elif kind == mujoco.mjtJoint.mjJNT_FREE:
            quat = rng.uniform(0.0, 1.0, 4)
            qpos[adr + 3 : adr + 7] = quat / np.linalg.norm(quat)


def _qpos0(m: mujoco.MjModel) -> FloatArray:
    return np.array(m.qpos0, dtype=np.float64)


def reset_cartpole(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
    qpos = _qpos0(m)
    qpos[0] = 0.01 * rng.standard_normal()
    qpos[1] = np.pi + 0.01 * rng.standard_normal()
    qpos[2:] = 0.1 * rng.standard_normal(m.nv - 2)
    return qpos, 0.01 * rng.standard_normal(m.nv), np.zeros(0)


def reset_random_joints(
    m: mujoco.MjModel, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray, FloatArray]:
    qpos = _qpos0(m)
    random_joints(m, rng, qpos)
    return qpos, np.zeros(m.nv), np.zeros(0)


def reset_untouched(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``humanoid.Humanoid.initialize_episode``: random joints (``random_joints``) drawn again until
    no geoms touch (a body drawn through the floor or through itself would be thrown out of it)."""
    d = mujoco.MjData(m)
    while True:
        qpos = _qpos0(m)
        random_joints(m, rng, qpos)
        d.qpos[:] = qpos
        mujoco.mj_forward(m, d)
        if d.ncon == 0:
            return qpos, np.zeros(m.nv), np.zeros(0)


def reset_reacher(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
    qpos, qvel, _ = reset_random_joints(m, rng)
    angle, radius = rng.uniform(0, 2 * np.pi), rng.uniform(0.05, 0.20)
    return qpos, qvel, np.array([radius * np.sin(angle), radius * np.cos(angle)])


def reset_ball_in_cup(
    m: mujoco.MjModel, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray, FloatArray]:
    d = mujoco.MjData(m)
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)]
    bx, bz = (int(m.jnt_qposadr[names.index(n)]) for n in ("ball_x", "ball_z"))
    while True:  # a ball drawn inside the cup is drawn again
        d.qpos[:] = m.qpos0
        d.qpos[bx], d.qpos[bz] = rng.uniform(-0.2, 0.2), rng.uniform(0.2, 0.5)
        mujoco.mj_forward(m, d)
        if d.ncon == 0:
            return np.array(d.qpos), np.zeros(m.nv), np.zeros(0)


def reset_acrobot(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
    qpos = _qpos0(m)
    qpos[:2] = rng.uniform(-np.pi, np.pi, 2)
    return qpos, np.zeros(m.nv), np.zeros(0)


def reset_cheetah(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``cheetah.Cheetah.initialize_episode``: the limited joints uniform in their ranges, then 200
    physical steps at rest, so that the cheetah lies on the floor as it settled."""
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    limited = m.jnt_limited == 1
    adr = m.jnt_qposadr[limited]
    d.qpos[adr] = rng.uniform(m.jnt_range[limited, 0], m.jnt_range[limited, 1])
    mujoco.mj_step(m, d, 200)
    return np.array(d.qpos), np.array(d.qvel), np.zeros(0)


# --------------------------------------------------------------------------------------- rewards
def _small_control(controls: Tensor) -> Tensor:
    """(B,) the suite's ``(4 + tolerance(u, margin=1, value_at_margin=0, quadratic)) / 5`` (first control)."""
    return (4 + tolerance(controls[:, 0], 0.0, 0.0, 1.0, "quadratic", 0.0)) / 5


def reward_cartpole(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``cartpole.Balance._get_reward`` (not sparse): upright · small control · small velocity · centred."""
    places = ctx.kin.places(s)
    upright = (ctx.kin.locator("body", "pole_1").rotation(places)[:, 2, 2] + 1) / 2
    centered = (1 + tolerance(s[:, ctx.column("slider.pos")], 0.0, 0.0, 2.0)) / 2
    rate = ctx.column("hinge_1.rate")
    small_velocity = (1 + tolerance(s[:, rate], 0.0, 0.0, 5.0)) / 2
    return upright * _small_control(u) * small_velocity * centered


def reward_pendulum(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``pendulum.SwingUp.get_reward``: the pole within 8° of upright (its z axis' height)."""
    vertical = ctx.kin.locator("body", "pole").rotation(ctx.kin.places(s))[:, 2, 2]
    bound = math.cos(math.radians(8))
    if not smooth:
        return tolerance(vertical, bound, 1.0)
    # learning, a pole spinning round (in the cone 4 % of the time) is worth less than one stopped
    # upright: its smooth reward, half of it paid only as slowly as the cartpole's pole must move
    slow = (1 + tolerance(s[:, ctx.column("hinge.rate")], 0.0, 0.0, 5.0)) / 2
    return shaped(vertical, bound, 1.0, 2.0, 0.05) * slow


def reward_reacher(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``reacher.Reacher.get_reward`` (hard: a 1.5 cm target): the fingertip on the target."""
    finger = ctx.kin.locator("geom", "finger").position(ctx.kin.places(s))[:, :2]
    dist = torch.linalg.norm(p - finger, dim=1)
    radii = 0.015 + ctx.geom_size("finger")
    return shaped(dist, 0.0, radii, 0.2, 0.02) if smooth else tolerance(dist, 0.0, radii)


def observe_reacher(ctx: Context, s: Tensor, p: Tensor) -> Tensor:
    """``reacher``'s ``to_target`` observation: the target less the fingertip (x, y), in decimetres."""
    finger = ctx.kin.locator("geom", "finger").position(ctx.kin.places(s))[:, :2]
    return (p - finger) * 10.0


def reward_point_mass(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``point_mass.PointMass.get_reward``: near the target · small control (mean over controls)."""
    places = ctx.kin.places(s)
    mass = ctx.kin.locator("geom", "pointmass").position(places)
    target = ctx.kin.locator("geom", "target").position(places)
    size = ctx.geom_size("target")
    near = tolerance(torch.linalg.norm(target - mass, dim=1), 0.0, size, 0.3 if smooth else size)
    control = tolerance(u, 0.0, 0.0, 1.0, "quadratic", 0.0).mean(dim=1)
    return near * (control + 4) / 5


def reward_ball_in_cup(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``ball_in_cup.BallInCup.get_reward``: 1 with the ball inside the cup's target box (x and z)."""
    places = ctx.kin.places(s)
    target = ctx.kin.locator("site", "target").position(places)[:, [0, 2]]
    ball = ctx.kin.locator("body", "ball").position(places)[:, [0, 2]]
    room = torch.tensor(ctx.site_size("target")[[0, 2]] - ctx.geom_size("ball"), dtype=s.dtype)
    off = (target - ball).abs()
    inside = (off < room).all(dim=1).to(s.dtype)
    if not smooth:
        return inside
    # nearing the cup pays, over the string's length (0.3 m): the ball hangs that far below it
    near = tolerance(torch.linalg.norm(target - ball, dim=1), 0.0, float(room.min()), 0.3)
    return torch.maximum(inside, near)


def reward_acrobot(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``acrobot.Balance._get_reward`` (not sparse): the tip near the target, margin 1 (4 when smooth)."""
    places = ctx.kin.places(s)
    tip = ctx.kin.locator("site", "tip").position(places)
    target = ctx.kin.locator("site", "target").position(places)
    radius = float(ctx.site_size("target")[0])
    # the suite's margin (1 m) pays nothing to a tip hanging 4 m below: the gradient's reaches it
    return tolerance(torch.linalg.norm(target - tip, dim=1), 0.0, radius, 4.0 if smooth else 1.0)


def _torso_height(ctx: Context, s: Tensor) -> Tensor:
    return ctx.kin.locator("body", "torso").position(ctx.kin.places(s))[:, 2]


def _hopper_height(ctx: Context, s: Tensor) -> Tensor:
    places = ctx.kin.places(s)
    foot = ctx.kin.locator("inertial", "foot").position(places)[:, 2]
    return ctx.kin.locator("inertial", "torso").position(places)[:, 2] - foot


def _torso_upright(ctx: Context, s: Tensor) -> Tensor:
    return ctx.kin.locator("body", "torso").rotation(ctx.kin.places(s))[:, 2, 2]


def reward_hopper_stand(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``hopper.Hopper.get_reward`` (standing): the torso's centre of mass 0.6-2 m above the foot's ·
    small control (mean over controls)."""
    height = _hopper_height(ctx, s)
    standing = shaped(height, 0.6, 2.0, 0.5, 0.1) if smooth else tolerance(height, 0.6, 2.0)
    control = tolerance(u, 0.0, 0.0, 1.0, "quadratic", 0.0).mean(dim=1)
    return standing * (control + 4) / 5


def _walker(ctx: Context, s: Tensor, u: Tensor, speed: float) -> Tensor:
    """``walker.PlanarWalker.get_reward``: the torso above 1.2 m (margin 0.6) and upright, and with a
    ``speed``, the centre of mass moving forward at it or faster (linear, half worth at half speed)."""
    places = ctx.kin.places(s)
    height = ctx.kin.locator("body", "torso").position(places)[:, 2]
    upright = (1 + ctx.kin.locator("body", "torso").rotation(places)[:, 2, 2]) / 2
    stand = (3 * tolerance(height, 1.2, math.inf, 0.6) + upright) / 4
    if speed == 0:
        return stand
    vx = ctx.kin.subtree_velocity(s, "torso")[:, 0]
    move = tolerance(vx, speed, math.inf, speed / 2, "linear", 0.5)
    return stand * (5 * move + 1) / 6


def reward_walker_stand(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    return _walker(ctx, s, u, 0.0)


def reward_walker_walk(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    return _walker(ctx, s, u, 1.0)


def reward_cheetah_run(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``cheetah.Cheetah.get_reward``: the centre of mass's forward speed over 10 m/s (linear from 0)."""
    vx = ctx.kin.subtree_velocity(s, "torso")[:, 0]
    return tolerance(vx, 10.0, math.inf, 10.0, "linear", 0.0)


def _head_height(ctx: Context, s: Tensor) -> Tensor:
    return ctx.kin.locator("body", "head").position(ctx.kin.places(s))[:, 2]


def reward_humanoid_stand(ctx: Context, s: Tensor, u: Tensor, p: Tensor, smooth: bool) -> Tensor:
    """``humanoid.Humanoid.get_reward`` (standing, no speed): the head above 1.4 m (margin 0.35) ·
    the torso upright (linear to 0 at its z axis pointing down) · small control · not moving (the
    centre of mass's horizontal velocity, margin 2 m/s, mean over x and y)."""
    places = ctx.kin.places(s)
    head = ctx.kin.locator("body", "head").position(places)[:, 2]
    standing = tolerance(head, 1.4, math.inf, 1.4 / 4)
    up = ctx.kin.locator("body", "torso").rotation(places)[:, 2, 2]
    upright = tolerance(up, 0.9, math.inf, 1.9, "linear", 0.0)
    control = (tolerance(u, 0.0, 0.0, 1.0, "quadratic", 0.0).mean(dim=1) + 4) / 5
    still = tolerance(ctx.kin.subtree_velocity(s, "torso")[:, :2], 0.0, 0.0, 2.0).mean(dim=1)
    return control * standing * upright * still


# a walker down again after standing (its torso under 0.7 m, its stand is 1.2), a hopper's torso
# back under 0.3 m above its foot after 0.5, a cheetah on its back
WALKER_FALL = Fall(_torso_height, above=1.0, below=0.7)
HOPPER_FALL = Fall(_hopper_height, above=0.5, below=0.3)
CHEETAH_FALL = Fall(_torso_upright, above=0.0, below=-0.5)
HUMANOID_FALL = Fall(_head_height, above=1.2, below=0.6)  # (its head stands at 1.6 m)


GROUND_SEEDS = 2  # a body on the ground's policies: two seeds side by side (``seed_race``)


def _ground(fall: Fall, unobserved: tuple[str, ...] = ("rootx.pos",)) -> dict[str, Any]:
    """A body on the ground: its fall, and how far it has gone unread (the suite omits it; a free
    root's position holds its height too, and is read);
    gradient paths of 8 super-steps, not 32 (through contact a longer path is ill-conditioned: the
    cheetah's run 58 → 209 in 900 s), and its emulator refined with the typical motion kept beside the
    policy's runs (the policy goes where the random data never went, and the model must stay right
    where it was); two seeds side by side, as the same settings stand the walker in one seed and leave
    it on the floor in another (``seed_race``)."""
    return {"fall": fall, "unobserved": unobserved, "horizon": 8, "refine_keep": 1024, "seeds": GROUND_SEEDS}


def _task(name: str, reset: ResetFn, reward: RewardFn, **how: Any) -> SuiteTask:
    return SuiteTask(**asdict(SUITE_TASK_INFO[name]), reset=reset, reward=reward, **how)


SUITE_TASKS: dict[str, SuiteTask] = {
    t.name: t
    for t in (
        _task("cartpole-swingup", reset_cartpole, reward_cartpole),
        _task("pendulum-swingup", reset_random_joints, reward_pendulum, restarts=REVERSE_CURRICULUM),
        _task("reacher-hard", reset_reacher, reward_reacher, observe=observe_reacher),
        _task("point_mass-easy", reset_random_joints, reward_point_mass),
        # the actor-critic's checks swung between 0 and 900 (617 held out, SAC 961): a value by value
        # iteration over the nine corners, edges and centre of the two controls' box, its greedy policy
        # copied; first the emulator fine-tuned on random runs from the task's starts, without which it
        # let the ball fall out of the cup MuJoCo kept it in and the copy earned 99 (938 on the bench
        # with them, SAC 967); the exact reward backed up, not its smooth form beside it, which pays
        # for the ball near the cup as well as in it (copies 969 and 972 held out from two seeds, where
        # 937-968 with it; docs/experiments); the copy's control the candidates averaged by its
        # scores' softmax, not the best-scored one (the same copy 970 held out against 947)
        _task(
            "ball_in_cup-catch",
            reset_ball_in_cup,
            reward_ball_in_cup,
            restarts=REVERSE_CURRICULUM,
            value_iteration=ValueIteration(candidates=9, smooth_weight=0.0, blend=1.0),
            exploring=ExploringRuns(runs=4096, seconds=360.0),
        ),
        # its reward needs a pumped swing the actor-critic never finds (41 held out): a value by value
        # iteration over the envelope and its greedy policy copied as a choice, over 4 s; three
        # candidates (full torque either way, none), not eleven: its greedy policy pumps at the ends
        # of the range, and a third of the backup's cost is 2.7 times the iterations (the greedy
        # policy 267 held out against 173, the copy 211 against 124: docs/experiments); its copy's
        # rounds checked on the same 16 starts, not 8 new ones a round (161.5 → 267.8 and 212.9 →
        # 235.6 held out over two seeds: docs/experiments); two threads, not one: its backups are
        # wide matrices, and twice as fast they fit the value over 1,148 iterations where one fitted
        # 750 (the greedy policy 337 over 100 episodes against 279, the copy 304 against 271: docs/experiments)
        _task(
            "acrobot-swingup",
            reset_acrobot,
            reward_acrobot,
            discount_s=4.0,
            value_iteration=ValueIteration(candidates=3, fixed_checks=16),
            threads=2,
        ),
        # the actor-critic never stood it up (1.2 held out), nor value iteration alone (8.4: its greedy
        # policy stood on the emulator, 322, not on MuJoCo): value iteration over the 2⁴ corners of
        # its four controls, its greedy policy run on MuJoCo every 10 iterations and the emulator
        # fine-tuned on those runs, the value kept the one whose greedy policy earned most on MuJoCo
        # (252 held out in 30 minutes on one seed, 3.1 on the other: docs/experiments); then the
        # actor-critic from the copy for the last 30 % of the budget, the value its critic's start,
        # which balances where the corners kick (a copy of 8.4 held out → 563.8 in 10 minutes on one
        # seed; the other's 95.0 fell to 4.4 and its copy was kept: docs/experiments); its two seeds
        # meet once their values are fitted, the one whose greedy policy earned less on MuJoCo taking
        # the other's value, as the actor-critic cannot mend a poor one (the bench 279.3 → 669.2,
        # nine of ten held-out starts risen: docs/experiments); the actor-critic's learning rate
        # annealed over its own 30 %, not the whole budget's (it began at 0.29 of the rate): 787.6
        # and 817.0 on two benches (seeds 2 and 3, 0 and 1); half its restarts from MuJoCo drawn
        # from the episodes its latest checks failed (``Restarts.failing``) earned 781.9 and 531.7
        # before it: not kept (the tenth start it never rises from jams the leg in the torso)
        _task(
            "hopper-stand",
            reset_random_joints,
            reward_hopper_stand,
            value_iteration=ValueIteration(
                candidates=16, blend=1.0, refine_every=10, share=0.5, actor_critic=0.3, meet=True
            ),
            **_ground(HOPPER_FALL),
        ),
        _task("walker-stand", reset_random_joints, reward_walker_stand, **_ground(WALKER_FALL)),
        _task("walker-walk", reset_random_joints, reward_walker_walk, **_ground(WALKER_FALL)),
        _task("cheetah-run", reset_cheetah, reward_cheetah_run, **_ground(CHEETAH_FALL)),
        _task("humanoid-stand", reset_untouched, reward_humanoid_stand, **_ground(HUMANOID_FALL, ())),
    )
}
