"""A value fitted by value iteration through the emulator, and the policy greedy over it copied into
the network: a learner for tasks whose actor-critic never finds the reward.

The actor-critic's critic learns by TD(λ) from where the policy goes. On a task whose reward needs a
pumped swing first (the acrobot) the early policy never goes where the reward is, the critic never
learns what a swing is worth, and the policy's gradient through it never asks for one (30-41 held
out, measured). Fitted value iteration needs no policy: over states drawn anywhere in the emulator's
envelope it backs up

    V(s) ← max_u [ r(s′) + γ V̄(s′) ],  s′ = emulator(s, u),

u over a few candidate controls, V̄ a copy of V taken at each iteration's start, so that the value of
the upright pose spreads back over every swing that reaches it, whether or not a policy has found it
(Bellman's backup, as in fitted Q and value iteration; the model in place of the simulator). Half
the states each iteration are uniform in the envelope's box, half where ε-greedy walkers under the
greedy policy have gone, so that V is fitted closely where the swing-up really passes. V̄ is held
between the least and the most reward seen over 1 − γ: unbounded, the max over the candidates
picks whatever V extrapolates highest and the fit diverged (the acrobot's loss 0.15 → 6 × 10⁷ in
860 iterations, held out 32; bounded, it stays near 2, held out 77: measured, docs/experiments).
The critic makes four passes over each iteration's targets, not one: a backup costs ten times a
pass, and one pass left V far from its targets (the acrobot's loss 1.9 against 0.5 with four, the
greedy policy's emulated return 100-140 against 130-165). Every 50 iterations the greedy policy is
run on the emulator from 64 of the task's starts, and the V that earned most is the one kept: V's
greedy policy swings from one iteration to the next. ``critics`` > 1 fits several values to the
same targets and backs up the least of them (``LeastValue``).

Each candidate is held for ``hold`` super-steps in the backup, its rewards summed on the way, before
V is read: in one super-step (the acrobot's 50 ms) a control moves the state so little that the
candidates' values differ by less than V's error, and the greedy choice between them is noise. Held
three (150 ms, as an action repeat), the acrobot's greedy policy earned 191 and 177 held out (two
seeds) against 158 held one on the same emulator, its copy 145 and 122 against 114 (measured,
docs/experiments). V is then the value of choosing a control every ``hold`` super-steps; the walkers
and the greedy policy still choose every super-step, each time the best held control from there.

Then the policy greedy over V (the best candidate held, its rewards plus the discounted V after) is
copied into the network by DAgger: emulated episodes, every state the network drives to labelled
with each candidate's backed-up value. Copied, not trained through V by its gradient: on the acrobot
a network trained against the same V, held fixed, earned 36-50, its copy 88-117 (measured,
docs/experiments). The network learns to choose (``copy_as="choice"``, a ``ChoicePolicy`` over the
same candidates): cross-entropy with the values' softmax at ``temperature``, so that candidates
within a near tie are taught as one and a wide gap as a sure choice. Where the greedy control flips
from one end of the range to the other (the acrobot's pumping), a regression onto it averages the
two into a torque that does neither: over the same two values the choice earned 130 and 160 held
out, the regression 101 and 91 (the greedy policy itself 158 and 162; measured, docs/experiments).
Each state's cross-entropy is weighed by its stakes, the gap between its best and worst candidates'
values (``stakes``): the copy follows the greedy policy in 75-87 % of the states it drives to
whatever else was changed, so what matters is which states it gets wrong; weighed, the acrobot's
copies earned 283 and 187 held out over two saved values where unweighed ones earned 206 and 158
(measured, docs/experiments). The copy is small, two layers of 64 ReLUs (``policy_hidden``,
``ChoicePolicy``): it is served beside the emulator every super-step, where 256 ELUs wide (twice the
acrobot's emulator's weights) it made a driven step up to 3.56 times an undriven one, 64 ReLUs wide
1.33 (the bar is 1.5); its rounds take half the time, and over the same two saved values it earned
228 and 277 held out where the 256-wide copies earned 224 and 177 (measured, docs/experiments).

Through a contact emulator the greedy policy finds where the model is wrong: the hopper's stood on
the emulator (322) and lay on MuJoCo (8.4). With ``refine_every`` it is run on MuJoCo every so many
iterations, its runs kept (the walkers restart from their states, as the actor-critic's episodes
restart from its checks'), the emulator fine-tuned on all of them where its return there is off
MuJoCo's, and the V kept is the one whose greedy policy earned most on MuJoCo, not on the emulator:
over 30 minutes the hopper's emulated and MuJoCo returns came within a few points of each other
(13.9 and 14.2, 4.4 and 4.1), and one of two seeds stood (252 held out; measured, docs/experiments).

The corners the hopper's greedy policy chooses among rise; they balance on one foot as a series of
kicks, and it fell seconds after it stood. With ``actor_critic`` the actor-critic trains on from the
best copy for the last share of the budget, the fitted V its critic's start: the policy's gradient
through the emulator's super-steps and V after them, on continuous controls (a blending copy's
scores take it). Where V was good (its greedy policy had earned 346 on MuJoCo) a copy of 8.4 held
out stood in 10 minutes, 564; where it was poor (66) the actor-critic fell to 4 and the copy was
kept (measured, docs/experiments): the actor-critic alone never found what standing is worth.

The candidates are a grid (k per control, kᵁ in all) or, for a count that is no such power, random
draws: made for models of few controls (a grid over many is exponential, random draws thin).

Shapes: B states, C candidate controls, S state, U controls, P task parameters.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from neuroanimator.control.reward_policy import RewardTrainer

log = logging.getLogger(__name__)
COPY_AS = ("choice", "control")  # what the network learns from the greedy policy (``ValueIteration``)
# rows a backup steps through the emulator at once: a contact emulator's clearance is many small
# matrix products whose (rows, 9) to (rows, 4G) intermediates outgrow the cache over the backup's
# 262,144 rows (16,384 states, 16 candidates); in pieces of 8,192 the hopper's step took 1.37 s
# against 3.42 s, the same results to the bit, and an iteration 6.4-7.7 s against 13.6 (one core,
# measured)
BACKUP_ROWS = 8192


@dataclass(frozen=True)
class ValueIteration:
    """How the value is fitted by value iteration and its greedy policy copied (module doc)."""

    share: float = 0.8  # of the training's budget spent fitting V; the policy learns in the rest
    states: int = 16_384  # states backed up per iteration
    # controls tried from each state: a grid when kᵁ, else random draws (``candidate_controls``)
    candidates: int = 11
    hold: int = 3  # super-steps each candidate is held in the backup before V is read (module doc)
    walkers: float = 0.5  # share of the states where ε-greedy walkers are; the rest uniform in the box
    epsilon: float = 0.2  # share of the walkers' steps under a random candidate
    smooth_weight: float = 0.3  # the reward backed up: the exact one plus this much of its smooth form
    batch: int = 1024
    fit_epochs: int = 4  # passes of the critic over each iteration's states and targets
    critics: int = 1  # values fitted side by side to the same targets, the least of them backed up
    lr: float = 1e-3
    hidden: tuple[int, ...] = (256, 256)  # the critic's layers
    policy_hidden: tuple[int, ...] = (64, 64)  # the policy's, in place of ``RewardSettings.hidden``
    iterations: int | None = None  # the most iterations (None: as many as its share of the budget allows)
    # every ``check_every`` iterations the greedy policy over V is run on the emulator from
    # ``check_episodes`` of the task's starts (always the same ones) and the V that earned most is
    # kept (0: the last V)
    check_every: int = 50
    check_episodes: int = 64
    # copying the greedy policy into the network (DAgger): emulated episodes a round from the task's
    # starts, driven by the greedy policy in the first rounds and by the network more and more after
    # (all of it from round ``teacher_rounds`` on), every state labelled with the greedy control
    episodes: int = 256
    teacher_rounds: int = 3
    epochs: int = 3  # passes over the labels so far each round
    max_labels: int = 1_000_000  # the most recent labels kept
    # what the network learns: "choice", which candidate to take (``ChoicePolicy``), by cross-entropy
    # with the candidates' backed-up values softened by ``temperature`` (a near tie taught as one);
    # "control", the greedy control itself, by least squares
    copy_as: str = "choice"
    temperature: float = 0.3
    # how the copy acts on what it learned: None, the best-scored candidate; a temperature, the
    # candidates averaged by its scores' softmax over it (``ChoicePolicy.blend``)
    blend: float | None = None
    # each state's cross-entropy weighed by what its choice is worth: the gap between its best and
    # worst candidates' values, over the batch's mean (a near tie taught lightly, a swing's decisive
    # push firmly); False: every state alike
    stakes: bool = True
    # each round of copying checked on MuJoCo from the same this many starts, drawn once: the rounds
    # compared on one set of starts rather than each on new ones, whose returns swing more from the
    # draw than from the round (the acrobot's 8 new starts a round: 37-350 over one training);
    # None: ``RewardSettings.eval_episodes`` new starts a round
    fixed_checks: int | None = None
    # every ``refine_every`` iterations the greedy policy over V runs ``refine_episodes`` episodes on
    # MuJoCo from the task's starts (counted), the emulator is fine-tuned on all of them so far where
    # its return there and on the emulator differ (``RewardSettings.refine_gap``), and the V kept is
    # the one whose greedy policy earned most on MuJoCo, not on the emulator: a greedy policy finds
    # where the emulator is wrong (the hopper's stood on it, 322, and lay on MuJoCo, 8.4), and the
    # model must be right where that policy goes. 0: never (the V kept by its emulated return)
    refine_every: int = 0
    refine_episodes: int = 8
    # the last this share of the budget: the actor-critic trains on from the copy (``RewardTrainer.learn``),
    # the fitted V its critic's start, so that the policy's gradient through the emulator polishes
    # what the few candidates could only approximate (a hopper standing on one foot is no series of
    # full-torque kicks); the copy's rounds end where it begins, and its actor's learning rate is
    # annealed over that share alone (``reward_policy.actor_rate``). 0: the copy is the policy
    actor_critic: float = 0.0
    # seeds trained side by side (``seed_race``) meet once their values are fitted: each brings its
    # V's best check on MuJoCo (its greedy policy's return, ``refine_every``, which it needs: an
    # emulated return favours the seed whose emulator flatters most), and those behind take the best
    # one's V and copy it through their own emulator, from their own draws; the actor-critic cannot
    # mend a poor V (the hopper's: greedy 66 on MuJoCo, the actor-critic 4)
    meet: bool = False

    def __post_init__(self) -> None:
        if not 0.0 < self.share < 1.0:
            raise ValueError(f"value iteration's share of the budget is in (0, 1), not {self.share}")
        if self.candidates < 2 or self.states < 2:
            raise ValueError("value iteration needs at least 2 candidate controls and 2 states")
        if not 0.0 <= self.walkers <= 1.0 or not 0.0 <= self.epsilon <= 1.0:
            raise ValueError("value iteration's walkers and epsilon are shares in [0, 1]")
        if self.hold < 1:
            raise ValueError(f"value iteration holds each candidate at least one super-step, not {self.hold}")
        if self.fit_epochs < 1 or self.critics < 1:
            raise ValueError("value iteration needs at least one value and one pass over its targets")
        if self.check_every < 0 or (self.check_every and self.check_episodes < 1):
            raise ValueError("value iteration's checks are every n ≥ 0 iterations over at least one start")
        if self.copy_as not in COPY_AS:
            raise ValueError(f"value iteration copies as one of {', '.join(COPY_AS)}, not {self.copy_as!r}")
        if self.fixed_checks is not None and self.fixed_checks < 1:
            raise ValueError(
                f"value iteration's fixed checks are at least one start or None, not {self.fixed_checks}"
            )
        if self.refine_every < 0 or (self.refine_every and self.refine_episodes < 1):
            raise ValueError(
                "value iteration's runs on MuJoCo are every n ≥ 0 iterations over at least one start"
            )
        if not 0.0 <= self.actor_critic < 1.0 - self.share:
            raise ValueError(
                f"value iteration's actor-critic share is in [0, 1 − share), not {self.actor_critic}"
            )
        if self.actor_critic and self.copy_as == "choice" and self.blend is None:
            raise ValueError(
                "value iteration's actor-critic needs a copy its gradient reaches: a blend, or copy_as 'control'"
            )
        if self.meet and not self.refine_every:
            raise ValueError(
                "value iteration's seeds meet on their values' checks on MuJoCo: refine_every > 0"
            )
        if not self.temperature > 0.0:
            raise ValueError(f"value iteration's temperature is above 0, not {self.temperature}")
        if self.blend is not None and not self.blend > 0.0:
            raise ValueError(f"value iteration's blend is a temperature above 0 or None, not {self.blend}")


def candidate_controls(low: np.ndarray, high: np.ndarray, count: int, rng: np.random.Generator) -> Tensor:
    """(C, U) controls to try from every state: ``count`` evenly over the range of a single control;
    for U controls and a ``count`` of kᵁ, the grid of k evenly over each control's range (the
    corners are where bang-bang control lies); else the centre, then uniform draws in the box."""
    per = round(count ** (1.0 / len(low)))
    if per >= 2 and per ** len(low) == count:
        axes = [torch.linspace(float(lo), float(hi), per) for lo, hi in zip(low, high, strict=True)]
        return torch.cartesian_prod(*axes).reshape(count, len(low))
    draws = rng.uniform(low, high, (count - 1, len(low)))
    return torch.as_tensor(np.vstack([(low + high) / 2, draws]), dtype=torch.float32)


class LeastValue(torch.nn.Module):
    """The least of several values (clipped double Q, Fujimoto et al. 2018): where they disagree, a
    state's value is the one least likely an error the max over the candidates picked."""

    def __init__(self, values: list[torch.nn.Module]) -> None:
        super().__init__()
        self.values = torch.nn.ModuleList(values)

    def forward(self, state: Tensor, params: Tensor) -> Tensor:
        return torch.stack([v(state, params) for v in self.values]).min(dim=0).values


class ValueFitter:
    """Value iteration on ``trainer``'s emulator, reward and critic (module doc)."""

    def __init__(self, trainer: RewardTrainer, how: ValueIteration) -> None:
        self.trainer, self.how = trainer, how
        self.rng = np.random.default_rng(trainer.settings.seed + 31)
        self.walker_count = round(how.states * how.walkers)
        self.age = np.zeros(self.walker_count, dtype=np.int64)
        s, p = trainer.restart(self.walker_count)
        self.walk_s = torch.as_tensor(s, dtype=torch.float32)
        self.walk_p = torch.as_tensor(p, dtype=torch.float32)
        self.iterations = 0
        # the least and most reward a step has paid in the backups so far: V lies within them over
        # 1 − γ, and its targets are held there (a bootstrapped value unbounded diverged: the max over
        # the candidates picks whatever V extrapolates highest, measured to a loss of 10⁷)
        self.reward_low, self.reward_high = math.inf, -math.inf
        # the greedy policy's candidates: a choosing policy's own choices (``ChoicePolicy``)
        choices = getattr(trainer.policy, "choices", None)
        self.grid = (
            choices
            if isinstance(choices, Tensor)
            else candidate_controls(trainer.low, trainer.high, how.candidates, self.rng)
        )
        # the trainer's critic and its twins (``critics``), each of its own first weights
        twins = [
            type(trainer.critic)(copy.deepcopy(trainer.critic.features), how.hidden)
            for _ in range(how.critics - 1)
        ]
        self.value = LeastValue([trainer.critic, *twins])
        # (states (L, S), parameters (L, P), the grid's candidates' backed-up values (L, C))
        self.labels: list[tuple[Tensor, Tensor, Tensor]] = []
        pick = self.rng.integers(len(trainer.start_states), size=how.check_episodes)
        self.check_starts = torch.as_tensor(trainer.start_states[pick], dtype=torch.float32)
        self.check_params = torch.as_tensor(trainer.start_params[pick], dtype=torch.float32)
        self.checks: list[tuple[int, float]] = []  # (iteration, the greedy policy's emulated return)
        self.mujoco_checks: list[tuple[int, float]] = []  # (iteration, its return on MuJoCo)
        # the kept V's check: its greedy policy's return on MuJoCo (``refine_every``), else on the
        # emulator, once fitted (-inf without checks)
        self.value_check = -math.inf
        # seconds an emulated episode labelled by the greedy policy took in the latest round of
        # copying: ``follows`` runs ``check_episodes`` such episodes (``follows_s``)
        self.labelled_episode_s = 0.0

    def score(self, nxt: Tensor, u: Tensor, p: Tensor) -> Tensor:
        """(B,) the reward backed up for arriving at ``nxt`` (B, S) under ``u`` (B, U): the exact one
        plus ``smooth_weight`` of its smooth form (which pays, a little, on the way to the exact one)."""
        task, ctx = self.trainer.task, self.trainer.ctx
        r = task.reward(ctx, nxt, u, p, False)
        if self.how.smooth_weight:
            r = r + self.how.smooth_weight * task.reward(ctx, nxt, u, p, True)
        return torch.nan_to_num(r)

    @torch.no_grad()
    def candidate_values(
        self, s: Tensor, p: Tensor, target: torch.nn.Module, cands: Tensor
    ) -> tuple[Tensor, Tensor]:
        """For states (B, S), parameters (B, P) and candidate controls (C, U): every candidate's
        backed-up value (C, B) and next state (C, B, S), one super-step on. Each candidate is held
        ``hold`` super-steps, its discounted rewards summed and the discounted V where it ends added."""
        c, b = len(cands), len(s)
        x, p_rep, u = s.repeat(c, 1), p.repeat(c, 1), cands.repeat_interleave(b, dim=0)
        # stepped in pieces (``BACKUP_ROWS``), V read once every piece's rewards have set its bounds
        pieces = [
            self.held_steps(*piece)
            for piece in zip(
                x.split(BACKUP_ROWS), p_rep.split(BACKUP_ROWS), u.split(BACKUP_ROWS), strict=True
            )
        ]
        paid, took, end, nxt = (torch.cat(part) for part in zip(*pieces, strict=True))
        return self.value_after(paid, took, end, p_rep, target).reshape(c, b), nxt.reshape(c, b, -1)

    @torch.no_grad()
    def held_values(
        self, x: Tensor, p_rep: Tensor, u: Tensor, target: torch.nn.Module
    ) -> tuple[Tensor, Tensor]:
        """States (N, S), parameters (N, P) and each state's control (N, U), held ``hold`` super-steps:
        the backed-up values (N,) and the states one super-step on (N, S) (``candidate_values``)."""
        paid, took, end, nxt = self.held_steps(x, p_rep, u)
        return self.value_after(paid, took, end, p_rep, target), nxt

    @torch.no_grad()
    def held_steps(self, x: Tensor, p_rep: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """States (N, S), parameters (N, P) and each state's control (N, U), held ``hold`` super-steps
        on the emulator: the discounted rewards paid (N,), whether the emulator took every step (N,),
        where the hold ends (N, S) and the states one super-step on (N, S). The least and most reward
        seen are widened by the steps taken."""
        tr = self.trainer
        paid = torch.zeros(len(x))
        took = torch.ones(len(x), dtype=torch.bool)
        discount = 1.0
        nxt = x = tr.step(x, u)  # the next states the walkers move to; the held steps go on from them
        for step in range(self.how.hold):
            if step:
                x = tr.step(x, u)
            r = self.score(x, u, p_rep)
            ok = torch.isfinite(x).all(dim=1)
            if ok.any():  # only steps the emulator took say what a reward can be
                self.reward_low = min(self.reward_low, float(r[ok].min()))
                self.reward_high = max(self.reward_high, float(r[ok].max()))
            took &= ok
            paid = paid + discount * r
            discount *= tr.gamma
        return paid, took, x, nxt

    @torch.no_grad()
    def value_after(
        self, paid: Tensor, took: Tensor, end: Tensor, p_rep: Tensor, target: torch.nn.Module
    ) -> Tensor:
        """(N,) the backed-up values of holds that paid ``paid`` (N,) and ended at ``end`` (N, S) under
        parameters (N, P): the discounted V there, held within the rewards' bounds, added; 0 where the
        emulator did not take every step (``took`` (N,))."""
        low, high = self.value_bounds()
        v = torch.cat(
            [target(e, p) for e, p in zip(end.split(BACKUP_ROWS), p_rep.split(BACKUP_ROWS), strict=True)]
        )
        q = paid + self.trainer.gamma**self.how.hold * torch.nan_to_num(v, nan=0.0).clamp(low, high)
        # a step the emulator could not take is worth nothing (a state far out is clamped by the features)
        return torch.where(took, torch.nan_to_num(q), torch.zeros_like(q))

    def backup(
        self, s: Tensor, p: Tensor, target: torch.nn.Module, cands: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The backed-up values (B,), the best candidate's index (B,) and every candidate's next
        state (C, B, S) (``candidate_values``)."""
        q, nxt = self.candidate_values(s, p, target, cands)
        best, pick = q.max(dim=0)
        return best, pick, nxt

    def value_bounds(self) -> tuple[float, float]:
        """The least and most any state's value can be: the least and most reward seen over 1 − γ."""
        horizon = 1.0 / (1.0 - self.trainer.gamma)
        return self.reward_low * horizon, self.reward_high * horizon

    def box(self, n: int) -> tuple[Tensor, Tensor]:
        """(n, S) states uniform in the emulator's envelope's box and (n, P) the task's parameters."""
        tr = self.trainer
        idx = self.rng.integers(len(tr.start_params), size=n)
        return (
            torch.as_tensor(tr.box_states(n), dtype=torch.float32),
            torch.as_tensor(tr.start_params[idx], dtype=torch.float32),
        )

    def iterate(self, opt: torch.optim.Optimizer) -> float:
        """One backup of ``states`` states and ``fit_epochs`` passes of the values over them; the last
        pass's mean squared error."""
        tr, how = self.trainer, self.how
        target = copy.deepcopy(self.value).requires_grad_(False)
        bs, bp = self.box(how.states - self.walker_count)
        s, p = torch.cat([bs, self.walk_s]), torch.cat([bp, self.walk_p])
        cands = candidate_controls(tr.low, tr.high, how.candidates, self.rng)
        y, pick, nxt = self.backup(s, p, target, cands)
        self.walk(pick[len(bs) :], nxt[:, len(bs) :])
        total = 0.0
        for _ in range(how.fit_epochs):
            order = torch.randperm(len(s))
            total = 0.0
            for i in range(0, len(s), how.batch):
                at = order[i : i + how.batch]
                loss = sum(((v(s[at], p[at]) - y[at]) ** 2).mean() for v in self.value.values) / how.critics
                opt.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.value.parameters(), 1.0)
                opt.step()
                total += float(loss.detach()) * len(at)
        self.iterations += 1
        return total / len(s)

    def walk(self, pick: Tensor, nxt: Tensor) -> None:
        """Move the walkers (their best candidates (W,), every candidate's next state (C, W, S)) one
        step, a random candidate for ``epsilon`` of them; restart those past an episode or lost."""
        w = len(pick)
        if not w:
            return
        tr = self.trainer
        explore = torch.as_tensor(self.rng.random(w) < self.how.epsilon)
        rand = torch.as_tensor(self.rng.integers(nxt.shape[0], size=w))
        chosen = torch.where(explore, rand, pick)
        self.walk_s = nxt[chosen, torch.arange(w)]
        self.age += 1
        again = (self.age >= tr.task.policy_steps) | tr.lost(self.walk_s).numpy()
        if again.any():
            ns, npar = tr.restart(int(again.sum()))
            mask = torch.as_tensor(again)
            self.walk_s[mask] = torch.as_tensor(ns, dtype=torch.float32)
            self.walk_p[mask] = torch.as_tensor(npar, dtype=torch.float32)
            self.age[again] = 0

    def fit(self, seconds: float) -> int:
        """Iterate for ``seconds`` (at least once, and not past a stop the trainer is asked for); the
        iterations run."""
        tr, how = self.trainer, self.how
        opt = torch.optim.Adam(self.value.parameters(), lr=how.lr)
        t0 = time.perf_counter()
        loss = float("nan")
        most = how.iterations
        best = (-math.inf, copy.deepcopy(self.value.state_dict()))
        while self.iterations == 0 or (
            time.perf_counter() - t0 < seconds and (most is None or self.iterations < most)
        ):
            if tr.should_stop is not None and tr.should_stop():
                break
            loss = self.iterate(opt)
            tr.report(self.iterations, loss, None)
            if how.check_every and self.iterations % how.check_every == 0:
                earned = self.emulated_return()
                self.checks.append((self.iterations, earned))
                if earned >= best[0] and not how.refine_every:
                    best = (earned, copy.deepcopy(self.value.state_dict()))
            if how.refine_every and self.iterations % how.refine_every == 0:
                earned = self.on_mujoco()
                if earned >= best[0]:
                    best = (earned, copy.deepcopy(self.value.state_dict()))
            if self.iterations % 50 == 0:
                log.info(
                    "%s: value iteration %d, loss %.4g, %.0f s",
                    tr.task.name, self.iterations, loss, time.perf_counter() - t0,
                )  # fmt: skip
        last = -math.inf
        if how.refine_every:
            # the last V's return on MuJoCo: its check's, when the last iteration had one
            checked = self.mujoco_checks and self.mujoco_checks[-1][0] == self.iterations
            last = self.mujoco_checks[-1][1] if checked else self.on_mujoco()
        elif how.check_every:
            last = self.emulated_return()
        if last < best[0]:
            self.value.load_state_dict(best[1])
        self.value_check = max(last, best[0])
        tr.target_critic.load_state_dict(tr.critic.state_dict())
        log.info(
            "%s: value fitted in %d iterations (loss %.4g); its greedy policy's emulated returns %s, "
            "on MuJoCo %s",
            tr.task.name, self.iterations, loss, [round(r, 1) for _, r in self.checks],
            [round(r, 1) for _, r in self.mujoco_checks],
        )  # fmt: skip
        return self.iterations

    def act(self, states: np.ndarray, params: np.ndarray) -> np.ndarray:
        """The greedy policy on MuJoCo's states (N, S) and parameters (N, P): its controls (N, U)."""
        s = torch.as_tensor(states, dtype=torch.float32)
        return self.greedy(s, torch.as_tensor(params, dtype=torch.float32)).double().numpy()

    def on_mujoco(self) -> float:
        """The greedy policy run on MuJoCo from ``refine_episodes`` of the task's starts (``refine_every``):
        its runs kept as the actor-critic keeps its checks' (restarts begin from their states, and
        the emulator learns them), the emulator fine-tuned on all of them where its return from the
        same starts is off MuJoCo's by more than ``refine_gap``. The mean return on MuJoCo."""
        tr = self.trainer
        runs = tr.episodes(self.act, self.how.refine_episodes, self.rng)
        emulated = tr.emulated_return(runs.states[:, 0], runs.params, self.greedy)
        self.mujoco_checks.append((self.iterations, runs.mean))
        refined = tr.keep_runs(runs, emulated)
        log.info(
            "%s: value iteration %d, its greedy policy's return on MuJoCo %.1f, on the emulator %.1f%s",
            tr.task.name, self.iterations, runs.mean, emulated, " (the emulator refined)" if refined else "",
        )  # fmt: skip
        return runs.mean

    def emulated_return(self) -> float:
        """The mean return of the greedy policy over V on the emulator from the check's starts."""
        return self.trainer.emulated_return(self.check_starts, self.check_params, self.greedy)

    @torch.no_grad()
    def greedy(self, s: Tensor, p: Tensor) -> Tensor:
        """(B, U) the control greedy over the fitted V from states (B, S): the best of the candidates."""
        _, pick, _ = self.backup(s, p, self.value, self.grid)
        return self.grid[pick]

    def follows_s(self) -> float:
        """The seconds ``follows`` will take, at the pace of the latest round's labelling."""
        return self.how.check_episodes * self.labelled_episode_s

    @torch.no_grad()
    def follows(self) -> tuple[float, float]:
        """How closely the trainer's policy follows the greedy policy over V where the policy itself
        goes: emulated episodes from the check's starts, the policy driving. The share of their states
        where its control is the greedy one, and the mean backed-up value its control loses against the
        greedy one's (≥ 0, the return's units: what the copy costs a decision, 0 where they agree)."""
        tr = self.trainer
        s, p = self.check_starts, self.check_params
        same, lost, n = 0.0, 0.0, 0
        for _ in range(tr.task.policy_steps):
            q, _ = self.candidate_values(s, p, self.value, self.grid)
            best, pick = q.max(dim=0)
            u = tr.policy(s, p)
            own, _ = self.held_values(s, p, u, self.value)
            # a choosing policy follows where its best-scored candidate is the greedy one (its control
            # may blend candidates: ``ChoicePolicy.blend``)
            choice = getattr(tr.policy, "choice", None)
            agree = (
                choice(s, p) == pick if choice is not None else torch.isclose(u, self.grid[pick]).all(dim=1)
            )
            same += float(agree.sum())
            lost += float((best - own).clamp(min=0.0).sum())
            n += len(s)
            s = torch.nan_to_num(tr.step(s, u))
        return same / n, lost / n

    def copy_round(self, round_index: int, opt: torch.optim.Optimizer) -> float:
        """One round of copying the greedy policy into the trainer's policy (DAgger, Ross et al. 2011):
        ``episodes`` emulated episodes from the task's starts, the greedy policy driving a share
        ``1 − round/teacher_rounds`` of the steps and the network the rest, every state labelled with
        its candidates' backed-up values; then ``epochs`` passes over the labels so far (``copy_as``).
        The last batch's loss."""
        tr, how = self.trainer, self.how
        pick = self.rng.integers(len(tr.start_states), size=how.episodes)
        s = torch.as_tensor(tr.start_states[pick], dtype=torch.float32)
        p = torch.as_tensor(tr.start_params[pick], dtype=torch.float32)
        teacher = max(0.0, 1.0 - round_index / max(1, how.teacher_rounds))
        began = time.perf_counter()
        with torch.no_grad():
            for _ in range(tr.task.policy_steps):
                q, _ = self.candidate_values(s, p, self.value, self.grid)
                self.labels.append((s, p, q.T))
                own = torch.as_tensor(self.rng.random(len(s)) >= teacher)[:, None]
                s = tr.step(s, torch.where(own, tr.policy(s, p), self.grid[q.argmax(dim=0)]))
                lost = tr.lost(s)
                if lost.any():  # a state the emulator does not know: a new start in its place
                    ns, npar = tr.restart(int(lost.sum()))
                    s, p = s.clone(), p.clone()
                    s[lost] = torch.as_tensor(ns, dtype=torch.float32)
                    p[lost] = torch.as_tensor(npar, dtype=torch.float32)
        self.labelled_episode_s = (time.perf_counter() - began) / how.episodes
        x, xp, values = (torch.cat(part) for part in zip(*self.labels, strict=True))
        if len(x) > how.max_labels:  # the oldest go: they were labelled where early policies went
            x, xp, values = x[-how.max_labels :], xp[-how.max_labels :], values[-how.max_labels :]
        self.labels = [(x, xp, values)]
        loss = torch.zeros(())
        for _ in range(how.epochs):
            order = torch.randperm(len(x))
            for i in range(0, len(x), how.batch):
                at = order[i : i + how.batch]
                loss = self.copy_loss(x[at], xp[at], values[at])
                opt.zero_grad()
                loss.backward()
                opt.step()
        return float(loss.detach())

    def copy_loss(self, s: Tensor, p: Tensor, values: Tensor) -> Tensor:
        """The copy's loss on states (B, S), parameters (B, P) and their candidates' values (B, C):
        cross-entropy of the policy's scores with the values' softmax at ``temperature``, each state's
        weighed by its stakes (``stakes``; a choosing policy), or the squared error of its controls
        from the best candidate's (``copy_as`` "control", or a policy that copied the planner first
        and chooses nothing)."""
        policy, how = self.trainer.policy, self.how
        scores = getattr(policy, "scores", None)
        if how.copy_as == "choice" and scores is not None:
            best = values.max(dim=1, keepdim=True).values
            soft = torch.softmax((values - best) / how.temperature, dim=1)
            each = torch.nn.functional.cross_entropy(scores(s, p), soft, reduction="none")
            if not how.stakes:
                return each.mean()
            stake = best[:, 0] - values.min(dim=1).values
            return (each * stake).sum() / stake.sum().clamp(min=1e-9)
        return ((policy(s, p) - self.grid[values.argmax(dim=1)]) ** 2).mean()
