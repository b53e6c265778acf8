"""The runner's learned running policy: ``π(state, speed) → servo targets``, a network that reads the
emulated state every super-step and the commanded speed, learned through the runner's emulator from
its hand-written running controller (thesis 7.2.3: a network controller in place of a hand-written
one; the data gathered as DAgger gathers it, Ross, Gordon and Bagnell 2011).

1. ``collect``: the controller drives the emulator from perturbed running starts at commands drawn
   over the task's range, each run pushed once, and its targets are the first examples.
2. The policy is fit to the examples; then it drives the emulator itself while the controller, its
   state machine stepping on the same states, says what it would have done there. Those states are
   where a copy's own errors take it, which the controller's runs never visit: they are added, and
   the policy fit again (``DistillSettings.rounds`` times). The first rounds mix the two (the policy
   acts in a growing share of the super-steps), so that early runs still resemble the gait. Every
   other round (``mujoco_every``) gathers the policy's own runs on MuJoCo instead
   (``collect_on_mujoco``), labelled the same way: under a policy that is not quite the controller
   the emulator errs where the controller's runs never took it, and those are the states the judged
   runs reach. Of the rounds the policy drove alone, the one that fell least keeps its policy.
3. ``judge``: on MuJoCo, the share of pushed runs of 30 s that stay up (the pelvis above 0.55 m) and
   run within 10 % of the command over their last 20 s.

The policy is a ``RewardPolicy`` whose parameter is the speed (``RUNNER_RUN``), exported and served
as a reward policy is.

Shapes: B runs, T super-steps, S the emulator's state, U = 29 servo targets.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

import mujoco
import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from neuroanimator.artifacts import registry
from neuroanimator.catalog.runner import gait as rc
from neuroanimator.control.reward_policy import Features, RewardPolicy, mlp
from neuroanimator.control.suite_tasks import Context, Fall, SuiteTask, tolerance
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
Step = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]

FALL_HEIGHT = 0.55  # metres of the pelvis: below it a run has fallen (``gait.run``'s)
PUSH_N = 250.0  # newtons on the torso for ``PUSH_S`` seconds, as the runner's benches push
PUSH_S = 0.2
SPEED_TOLERANCE = 0.1  # a run meets its command within this share of it


# ------------------------------------------------------------------------------------ the task
def _pelvis_height(ctx: Context, s: torch.Tensor) -> torch.Tensor:
    return s[:, ctx.column("root.pos") + 2]


def _reset(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A running start at a command drawn over the task's range, its velocities perturbed."""
    speed = float(rng.uniform(*SPEED_RANGE))
    full = rc.perturbed_starts(m, speed, 1, rng)[0]
    return full[1 : 1 + m.nq].copy(), full[1 + m.nq : 1 + m.nq + m.nv].copy(), np.array([speed])


def _reward(ctx: Context, s: torch.Tensor, u: torch.Tensor, p: torch.Tensor, smooth: bool) -> torch.Tensor:
    """Up (the pelvis above ``FALL_HEIGHT``) and the forward speed within ``SPEED_TOLERANCE`` of the
    command, falling off linearly over half the command."""
    vx = s[:, ctx.column("root.vel")]
    speed = p[:, 0]
    up = (_pelvis_height(ctx, s) > FALL_HEIGHT).to(s.dtype)
    off = (vx - speed).abs() / speed.clamp_min(0.1)
    return up * tolerance(off, 0.0, SPEED_TOLERANCE, 0.5, "linear", 0.0)


SPEED_RANGE = (1.8, 2.2)
RUNNER_RUN = SuiteTask(
    name="runner-run",
    domain="runner",
    substeps=6,
    control_substeps=6,
    params=("speed",),
    param_low=(SPEED_RANGE[0],),
    param_high=(SPEED_RANGE[1],),
    episode_steps=round(30.0 / (6 * 0.0027)),
    reset=_reset,
    reward=_reward,
    fall=Fall(_pelvis_height, above=FALL_HEIGHT + 0.2, below=FALL_HEIGHT, settle_s=0.0),
    summary="run at the commanded speed (m/s) and stay up, pushed now and then",
)


# ------------------------------------------------------------------------------ the emulator loop
@dataclass
class Runs:
    """Emulated runs: the states the policy (or the controller) acted in, what the controller would
    have done in each, and the runs' commands."""

    states: FloatArray  # (N, S) every super-step's state of every run while it was up
    labels: FloatArray  # (N, U) the controller's targets there
    speeds: FloatArray  # (N,) the command of the run each state is from
    fell: int  # runs that fell


def emulator_step(onnx: OnnxEmulator) -> Step:
    """The emulator as ``gait.Step``: (B, S) states, (B, U) targets, (B, F) forces → (B, S)."""

    def step(s: FloatArray, u: FloatArray, f: FloatArray) -> FloatArray:
        out = onnx.step(s.astype(np.float32), u.astype(np.float32), f.astype(np.float32), validate=False)
        return np.asarray(out, dtype=np.float64)

    return step


def session_starts(model: PhysicalModel, count: int = 8, seed: int = 0) -> FloatArray:
    """(count, S) running strides at the task's default command (the middle of its range), their
    velocities perturbed: where a served session driven by the policy starts (``PolicyManifest.starts``),
    as its runs did, not from the standing pose the model's own starts are."""
    speed = sum(SPEED_RANGE) / 2
    return np.asarray(
        model.from_physics(rc.perturbed_starts(model.mj_model, speed, count, np.random.default_rng(seed)))
    )


def random_pushes(runs: int, seconds: float, rng: np.random.Generator) -> rc.Push:
    """One push of each of ``runs`` runs of ``seconds``: ``PUSH_N`` for ``PUSH_S`` in a random
    direction in the plane, at a random time after the first second and before the last."""
    angle = rng.uniform(0, 2 * np.pi, runs)
    return rc.Push(
        force=np.stack([PUSH_N * np.cos(angle), PUSH_N * np.sin(angle), np.zeros(runs)], axis=1),
        start_s=rng.uniform(1.0, max(1.0, seconds - 1.0), runs),
        duration_s=PUSH_S,
    )


def collect(
    model: PhysicalModel,
    step: Step,
    substeps: int,
    speeds: FloatArray,
    seconds: float,
    rng: np.random.Generator,
    policy: RewardPolicy | None = None,
    mix: float = 1.0,
) -> Runs:
    """Runs on the emulator at ``speeds`` (B,) from perturbed running starts, each pushed once (a
    random direction in the plane, at a random time after the first second): the controller acts,
    or ``policy`` in a share ``mix`` of the super-steps; the controller's targets are recorded in
    every state either way. A run that falls (or leaves the finite numbers) stops being recorded."""
    m = model.mj_model
    b = len(speeds)
    full = np.concatenate([rc.perturbed_starts(m, float(v), 1, rng) for v in speeds])
    state = model.from_physics(full)
    ctl = rc.RunnerController(m)
    ctl.reset(b, speeds)
    observer = rc.KinematicSensors(m)
    dt = m.opt.timestep * substeps
    periods = round(seconds / dt)
    push = random_pushes(b, seconds, rng)
    qpos_cols = np.arange(1, 1 + m.nq)
    qvel_cols = np.arange(1 + m.nq, 1 + m.nq + m.nv)
    z_col = int(qpos_cols[2])
    up = np.ones(b, bool)
    states, labels, commands = [], [], []
    params = torch.as_tensor(speeds[:, None], dtype=torch.float32)
    for k in range(periods):
        full = model.to_physics(state)
        up &= full[:, z_col] >= FALL_HEIGHT
        if not up.any():
            break
        qpos, qvel = full[:, qpos_cols], full[:, qvel_cols]
        label = ctl.act(qpos, qvel, observer.read(qpos, qvel), dt)
        states.append(state[up])
        labels.append(label[up])
        commands.append(speeds[up])
        u = label
        if policy is not None:
            with torch.no_grad():
                own = policy(torch.as_tensor(state, dtype=torch.float32), params).double().numpy()
            u = np.where((rng.random(b) < mix)[:, None], own, label)
        forces = np.zeros((b, model.num_forces))
        pushed = push.active(k * dt, b)
        forces[pushed, :2] = np.asarray(push.force)[pushed, :2]
        nxt = step(state, u, forces)
        broken = ~np.isfinite(nxt).all(axis=1)
        up &= ~broken
        nxt[broken] = state[broken]
        state = nxt
    return Runs(np.concatenate(states), np.concatenate(labels), np.concatenate(commands), int((~up).sum()))


# ---------------------------------------------------------------------------------- the policy
class Ensemble(nn.Module):
    """Networks side by side: (B, F) features → (B, U) the mean of their outputs (``members``)."""

    def __init__(self, members: list[nn.Module]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([m(x) for m in self.members]).mean(dim=0)


@dataclass(frozen=True)
class DistillSettings:
    """How the runner's policy is learned (module doc): ``runs`` emulated runs of ``seconds`` per
    round, ``rounds`` rounds after the controller's own, the policy acting in a share ``mix`` of the
    super-steps in the first, twice that in the second and so on up to all; each fit
    ``epochs`` passes over all the examples in batches of ``batch``."""

    runs: int = 32
    seconds: float = 20.0  # (10-s runs measured the policy too kindly: it fell later than that)
    rounds: int = 10
    mix: float = 0.25
    epochs: int = 8
    batch: int = 512
    lr: float = 1e-3
    hidden: tuple[int, ...] = (256, 256)
    # networks fit side by side to the same examples from their own initial weights, their outputs
    # averaged (before the squashing): where the examples are thin their errors differ and partly cancel
    members: int = 1
    seed: int = 0
    speeds: tuple[float, float] = (1.6, 2.4)  # commands the data is gathered at: beyond the task's range
    # every how many rounds one gathers the policy's own runs on MuJoCo instead (0: never; 2: every
    # other round): the states it reaches in the world it is judged in, where the emulator's small
    # errors under a policy that is not the controller would otherwise go unseen
    mujoco_every: int = 2


@dataclass
class DistillResult:
    policy: RewardPolicy
    rounds: list[dict[str, float]] = field(default_factory=list)  # per round: examples, fell, loss, ...
    emulated_steps: int = 0
    mujoco_steps: int = 0  # physical steps of the policy's own MuJoCo runs (``mujoco_every``)
    # the round whose runs the kept policy drove (1 the first after the controller's); 0: the last fit
    kept_round: int = 0
    wall_s: float = 0.0


FEET = ("left_foot", "left_toes", "right_foot", "right_toes")


def feet(ctx: Context) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """(B, S), (B, 1) → (B, 16): each foot's and toe's place from the pelvis (metres, world axes) and
    its height: which foot bears the body and how far into its stride it is, what the controller's
    state machine knows from its touch sensors and the network must otherwise work out."""
    ids = [mujoco.mj_name2id(ctx.m, mujoco.mjtObj.mjOBJ_BODY, name) for name in FEET]
    pelvis = mujoco.mj_name2id(ctx.m, mujoco.mjtObj.mjOBJ_BODY, "pelvis")

    def observe(state: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
        pos, _ = ctx.kin.places(state)
        at = pos[:, ids]  # (B, 4, 3)
        rel = (at - pos[:, pelvis : pelvis + 1]).flatten(1)  # (not reshape(len(state)): the batch varies)
        return torch.cat([rel, at[:, :, 2] * 10.0], dim=1)

    return observe


def _features(model: PhysicalModel, ctx: Context, states: FloatArray) -> Features:
    """The policy's input features, scaled by the controller's runs (angles as sine and cosine), and
    the feet's places (``feet``)."""
    angles = [g.offset + i for g in ctx.layout if g.kind == "angle" for i in range(g.size)]
    plain = [c for c in range(states.shape[1]) if c not in set(angles)]
    mean, scale = states.mean(axis=0), np.maximum(states.std(axis=0), 1e-2)
    observe = feet(ctx)
    return Features(angles, plain, mean, scale, 1, observe, 4 * len(FEET))


def fit(policy: RewardPolicy, data: Runs, settings: DistillSettings, rng: np.random.Generator) -> float:
    """``settings.epochs`` passes of Adam over the examples: the mean squared error of the targets in
    units of each control's half range (the last pass's mean). The features hold no weights, so
    they are computed once per fit and only the network behind them is trained on them."""
    opt = torch.optim.Adam(policy.net.parameters(), lr=settings.lr)
    nets = list(policy.net.members) if isinstance(policy.net, Ensemble) else [policy.net]
    with torch.no_grad():
        x = torch.cat(
            [
                policy.features(
                    torch.as_tensor(data.states[at : at + 8192], dtype=torch.float32),
                    torch.as_tensor(data.speeds[at : at + 8192, None], dtype=torch.float32),
                )
                for at in range(0, len(data.states), 8192)
            ]
        )
    # the targets as the network's output before its squashing: c + h·tanh(a) = y
    y = torch.as_tensor(data.labels, dtype=torch.float32)
    y = ((y - policy.centre) / policy.half_range).clamp(-1.0, 1.0)
    loss_sum = 0.0
    for _ in range(settings.epochs):
        order = torch.as_tensor(rng.permutation(len(x)))
        loss_sum, n = 0.0, 0
        for at in range(0, len(x), settings.batch):
            i = order[at : at + settings.batch]
            # each member fit on its own (an ensemble's mean is not what any member is taught)
            loss = torch.stack([((torch.tanh(net(x[i])) - y[i]) ** 2).mean() for net in nets]).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            loss_sum, n = loss_sum + loss.item() * len(i), n + len(i)
        loss_sum /= max(n, 1)
    return loss_sum


def _join(a: Runs, b: Runs) -> Runs:
    return Runs(
        np.concatenate([a.states, b.states]),
        np.concatenate([a.labels, b.labels]),
        np.concatenate([a.speeds, b.speeds]),
        a.fell + b.fell,
    )


def distill(path: Path, settings: DistillSettings | None = None) -> DistillResult:
    """The runner's policy learned through the emulator at ``path`` from its running controller."""
    settings = settings or DistillSettings()
    t0 = time.perf_counter()
    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    step = emulator_step(OnnxEmulator(path / registry.ONNX_FILE, threads=1))
    ctx = Context(model.mj_model, list(manifest.layout))

    def speeds() -> FloatArray:
        return rng.uniform(*settings.speeds, settings.runs)

    data = collect(model, step, manifest.substeps, speeds(), settings.seconds, rng)
    steps = len(data.states)
    low = np.array([c.low for c in manifest.controls])
    high = np.array([c.high for c in manifest.controls])
    features = _features(model, ctx, data.states)
    policy = RewardPolicy(features, low, high, settings.hidden)
    if settings.members > 1:
        policy.net = Ensemble(
            [mlp(features.size, settings.hidden, len(low)) for _ in range(settings.members)]
        )
    result = DistillResult(policy)
    loss = fit(policy, data, settings, rng)
    result.rounds.append({"examples": len(data.states), "fell": data.fell, "loss": loss})
    log.info("runner-run: the controller's runs: %d examples, %d fell; fit %.4f", steps, data.fell, loss)
    # DAgger's rounds do not improve steadily (of 64 pushed runs on MuJoCo, 3 fell in one round, 36
    # two rounds later): a round the policy drove alone measures the policy it ran, and the one that
    # fell least is kept; on MuJoCo's rounds when there are any, the world it is judged in
    best: tuple[int, int, dict[str, torch.Tensor]] | None = None  # (fell, round, weights)
    for r in range(settings.rounds):
        mix = min(1.0, settings.mix * (r + 1))
        on_mujoco = settings.mujoco_every > 0 and (r + 1) % settings.mujoco_every == 0
        measures = mix >= 1.0 and (on_mujoco or settings.mujoco_every == 0)
        weights = {k: v.clone() for k, v in policy.state_dict().items()} if measures else {}
        if on_mujoco:
            own = collect_on_mujoco(model, manifest.substeps, speeds(), settings.seconds, rng, policy, mix)
            result.mujoco_steps += len(own.states) * manifest.substeps
        else:
            own = collect(model, step, manifest.substeps, speeds(), settings.seconds, rng, policy, mix)
            steps += len(own.states)
        if measures and (best is None or own.fell < best[0]):
            best = (own.fell, r, weights)
        data = _join(data, own)
        loss = fit(policy, data, settings, rng)
        where = "MuJoCo" if on_mujoco else "the emulator"
        result.rounds.append(
            {
                "examples": len(data.states),
                "fell": own.fell,
                "loss": loss,
                "mix": mix,
                "on_mujoco": float(on_mujoco),
            }
        )
        log.info(
            "runner-run: round %d on %s (the policy in %.0f%% of steps): %d of %d runs fell; %d examples; fit %.4f",
            r + 1, where, 100 * mix, own.fell, settings.runs, len(data.states), loss,
        )  # fmt: skip
    if best is not None:
        policy.load_state_dict(best[2])
        result.kept_round = best[1] + 1
        log.info(
            "runner-run: kept the policy that drove round %d (%d of %d runs fell)",
            best[1] + 1,
            best[0],
            settings.runs,
        )
    result.emulated_steps = steps
    result.wall_s = time.perf_counter() - t0
    return result


# ------------------------------------------------------------------------------- judged on MuJoCo
class PolicyController:
    """A runner policy in ``gait.run``'s controller's place: it reads the state, not the sensors."""

    def __init__(self, model: PhysicalModel, policy: RewardPolicy, speeds: FloatArray) -> None:
        self.model, self.policy = model, policy
        m = model.mj_model
        self.nq, self.nv = m.nq, m.nv
        self.params = torch.as_tensor(np.asarray(speeds, float)[:, None], dtype=torch.float32)
        self.low, self.high = np.full(m.nu, -np.inf), np.full(m.nu, np.inf)
        self.ctrl_ids = rc.RunnerController(m).ctrl_ids

    def state(self, qpos: FloatArray, qvel: FloatArray) -> FloatArray:
        """(B, nq), (B, nv) → (B, S) the emulator's state of those positions and velocities."""
        full = self.model.to_physics(self.model.rest_state()[None].repeat(len(qpos), axis=0))
        full[:, 1 : 1 + self.nq] = qpos
        full[:, 1 + self.nq : 1 + self.nq + self.nv] = qvel
        return np.asarray(self.model.from_physics(full))

    def act(self, qpos: FloatArray, qvel: FloatArray, sensordata: FloatArray, dt: float) -> FloatArray:
        with torch.no_grad():
            s = torch.as_tensor(self.state(qpos, qvel), dtype=torch.float32)
            return self.policy(s, self.params).double().numpy()


class LabelledPolicy(PolicyController):
    """The policy acting on MuJoCo (in a share ``mix`` of the control periods, the controller in the
    rest) while the controller, its state machine stepping on the same states, records what it would
    have done: the policy's own MuJoCo runs as examples (``collect_on_mujoco``)."""

    def __init__(
        self,
        model: PhysicalModel,
        policy: RewardPolicy,
        speeds: FloatArray,
        mix: float,
        rng: np.random.Generator,
    ) -> None:
        super().__init__(model, policy, speeds)
        self.expert = rc.RunnerController(model.mj_model)
        self.expert.reset(len(speeds), speeds)
        self.mix, self.rng = mix, rng
        self.states: list[FloatArray] = []
        self.labels: list[FloatArray] = []

    def act(self, qpos: FloatArray, qvel: FloatArray, sensordata: FloatArray, dt: float) -> FloatArray:
        label = self.expert.act(qpos, qvel, sensordata, dt)
        s = self.state(qpos, qvel)
        self.states.append(s)
        self.labels.append(label)
        with torch.no_grad():
            own = self.policy(torch.as_tensor(s, dtype=torch.float32), self.params).double().numpy()
        return np.where((self.rng.random(len(s)) < self.mix)[:, None], own, label)


def collect_on_mujoco(
    model: PhysicalModel,
    substeps: int,
    speeds: FloatArray,
    seconds: float,
    rng: np.random.Generator,
    policy: RewardPolicy,
    mix: float = 1.0,
) -> Runs:
    """``collect``'s runs on MuJoCo instead of the emulator (the controller on ``KinematicSensors``,
    as on the emulator): the states the policy reaches in the world it is judged in."""
    m = model.mj_model
    b = len(speeds)
    starts = np.concatenate([rc.perturbed_starts(m, float(v), 1, rng) for v in speeds])
    push = random_pushes(b, seconds, rng)
    ctl = LabelledPolicy(model, policy, speeds, mix, rng)
    res = rc.run(
        m, starts, speeds, seconds, control_every=substeps, push=push, kinematic=True, threads=1,
        record=False, controller=ctl,
    )  # fmt: skip
    states, labels = np.stack(ctl.states, axis=1), np.stack(ctl.labels, axis=1)  # (B, T, ·)
    t = np.arange(states.shape[1]) * res.dt
    keep = t[None, :] < res.fell_at[:, None]  # (B, T): while each run was up
    return Runs(
        states[keep],
        labels[keep],
        np.repeat(speeds[:, None], states.shape[1], axis=1)[keep],
        int(res.fell.sum()),
    )


def root_drift(
    model: PhysicalModel,
    step: Step,
    substeps: int,
    policy: RewardPolicy,
    speed: float = 2.0,
    runs: int = 10,
    seconds: float = 1.0,
    seed: int = 0,
) -> float:
    """The mean distance (m) between the pelvis on the emulator ``step`` and on MuJoCo ``seconds``
    after the same ``runs`` perturbed running starts at ``speed``, each in its own closed loop under
    ``policy`` (unpushed): how far the emulator strays from MuJoCo under the policy it taught (inf
    when every emulated run left the finite numbers)."""
    m = model.mj_model
    starts = rc.perturbed_starts(m, speed, runs, np.random.default_rng(seed))
    speeds = np.full(runs, speed)
    res = rc.run(
        m, starts, speeds, seconds, control_every=substeps, kinematic=True, threads=1, record=False,
        controller=PolicyController(model, policy, speeds),
    )  # fmt: skip
    state = model.from_physics(starts)
    params = torch.as_tensor(speeds[:, None], dtype=torch.float32)
    for _ in range(round(seconds / (m.opt.timestep * substeps))):
        with torch.no_grad():
            u = policy(torch.as_tensor(state, dtype=torch.float32), params).double().numpy()
        state = step(state, u, np.zeros((runs, model.num_forces)))
    emulated = model.to_physics(state)[:, 1:4]  # the pelvis's x, y, z (the free joint's first)
    gap = np.linalg.norm(emulated - res.final_qpos[:, :3], axis=1)
    return float(gap[np.isfinite(gap)].mean()) if np.isfinite(gap).any() else float("inf")


class Judged(TypedDict):
    """``judge``'s row: a command's runs, how many stayed up, how many met the command, their mean
    speed over the last two thirds (None when none stayed up) and the wall time."""

    speed: float
    runs: int
    up: int
    met: int
    mean_speed: float | None
    wall_s: float


def judge(
    model: PhysicalModel,
    substeps: int,
    policy: RewardPolicy | None,
    speed: float,
    runs: int = 16,
    seconds: float = 30.0,
    seed: int = 0,
) -> Judged:
    """``runs`` pushed runs on MuJoCo at the command ``speed`` (the policy every super-step; None: the
    hand-written controller), pushed with ``PUSH_N`` for ``PUSH_S`` at 5 s, forward, backward, left
    and right in turn: how many stayed up for ``seconds``, how many also ran within
    ``SPEED_TOLERANCE`` of the command over the last two thirds, and their mean speed there."""
    m = model.mj_model
    rng = np.random.default_rng(seed)
    starts = rc.perturbed_starts(m, speed, runs, rng)
    directions = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], float)[np.arange(runs) % 4]
    push = rc.Push(
        force=np.concatenate([PUSH_N * directions, np.zeros((runs, 1))], axis=1),
        start_s=5.0,
        duration_s=PUSH_S,
    )
    controller = None if policy is None else PolicyController(model, policy, np.full(runs, speed))
    res = rc.run(
        m, starts, speed, seconds, control_every=substeps, push=push, kinematic=True, threads=1,
        controller=controller,
    )  # fmt: skip
    qvel_x = 1 + m.nq  # the root's forward speed in a full-physics state
    later = res.states[:, res.states.shape[1] // 3 :, qvel_x]
    mean_speed = later.mean(axis=1)
    up = ~res.fell
    within = up & (np.abs(mean_speed - speed) <= SPEED_TOLERANCE * speed)
    return {
        "speed": speed,
        "runs": runs,
        "up": int(up.sum()),
        "met": int(within.sum()),
        "mean_speed": round(float(mean_speed[up].mean()), 3) if up.any() else None,
        "wall_s": round(res.wall_s, 1),
    }
