"""Policies found by random search through the emulator: augmented random search (ARS V2-t, Mania,
Guy and Recht 2018) over the policy network's weights, every perturbation's return measured on
emulated episodes, run side by side as one batch.

Where a gradient through contact is of little use (the cheetah's actor-critic stalls at 190 from
its fifteenth minute while its emulator earns what MuJoCo does under the policy), the return of a
whole episode is still a reliable signal, and the emulator measures it for many policies at once:
each iteration draws ``directions`` random directions δ in weight space, runs the policy at θ ± νδ
from the same ``episodes`` starts through the emulator (2·directions·episodes episodes in one batch,
a super-step for all of them one call of the network), and moves θ along the directions of the
``top`` best pairs, their return differences scaled by the spread of those returns. The policy
reads the trainer's ``Features`` (the state centred and scaled by the emulator's typical motion, as
ARS normalises its observations), so that a linear map is already a gait controller.

A search this strong finds the emulator's errors as readily as the physics' gaits: on the cheetah
the tried policies earned 455 on the emulator and 105 on MuJoCo within two minutes. So an episode
can be paid only while it stays inside the emulator's envelope (``stay_inside``: MOReL's halting,
Kidambi et al. 2020), the states of its data widened by every MuJoCo run it is refined on, so that
the search runs only as far as the physics has been seen to go; and at every check a few of the
latest tried policies run on MuJoCo too (``tried_runs``), so that the emulator learns where the
search looks, not only where the policy is. ``on="mujoco"`` runs the same search on the physics,
the experiment that says what the emulator buys: on the cheetah, in 20 minutes of one core, 121.7
through the emulator with both, 331.8 on MuJoCo (docs/experiments/policies.md). Nor did the
emulator help as the search's guide on MuJoCo, ranking its directions or proposing its steps: both
did worse than MuJoCo alone (10.8 and 2, against 245.5). Not a default.

The checks on MuJoCo, the best policy kept, the emulator refined on the policy's runs where its
returns leave MuJoCo's: as for the actor-critic (``reward_policy.RewardTrainer``).

Shapes: K policies (2·directions), E episodes each, S state, U controls, P parameters, F features,
D the policy network's weights.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

if TYPE_CHECKING:
    from neuroanimator.control.reward_policy import RewardPolicy, RewardTrainer
    from neuroanimator.sim.model import PhysicalModel

log = logging.getLogger(__name__)
# an emulated episode this many spreads of the typical motion from it has diverged: it earns nothing
# more. Far beyond the actor-critic's restart (``FEATURE_LIMIT``, 8): a cheetah running at 5.6 m/s is
# 8 spreads of the random motion's speed from its mean, and the search must be paid for running
DIVERGED = 32.0
SEARCH_ON = ("emulator", "mujoco")  # where the tried policies' episodes run (``RandomSearch.on``)


@dataclass(frozen=True)
class RandomSearch:
    """How the policy is searched for (ARS's N, b, α, ν; its episodes through the emulator)."""

    directions: int = 32  # N: random directions a step, each tried both ways
    top: int = 16  # b: the directions whose better side earned most move the policy
    step: float = 0.02  # α
    noise: float = 0.03  # ν: how far along each direction the policy is tried
    episodes: int = 4  # starts every tried policy runs from, the same for all (common random numbers)
    # an emulated episode's length (None: the task's whole episode, from the task's starts); shorter
    # ones begin where the trainer's restarts do (``RewardTrainer.restart``: the task's starts,
    # states the policy reached on MuJoCo, the envelope), as the actor-critic's branches do
    seconds: float | None = None
    hidden: tuple[int, ...] = ()  # the policy's hidden layers: () a linear map of the features
    # at every check, this many of the latest step's tried policies (the best-earning on the
    # emulator) also run an episode each on MuJoCo, and the emulator learns those runs beside the
    # policy's own when it is refined: it must be right where the search looks, not only where the
    # policy is (0: the policy's runs alone)
    tried_runs: int = 0
    # where the tried policies' episodes run: "emulator", or "mujoco", the same search on the
    # physics itself (its steps counted): the experiment that says what the emulator buys
    on: str = "emulator"
    # an episode that leaves the emulator's envelope (the states of its data, widened by the runs it
    # was refined on) earns nothing from then on: the search is paid only where the emulator has
    # seen the physics (MOReL's halting), not for a gait that its errors alone allow
    stay_inside: bool = False

    def __post_init__(self) -> None:
        if self.directions < 1 or not 1 <= self.top <= self.directions:
            raise ValueError(
                f"random search takes 1 <= top <= directions, not {self.top} of {self.directions}"
            )
        if not 0 <= self.tried_runs <= 2 * self.directions:
            raise ValueError(
                f"random search runs 0 to {2 * self.directions} tried policies on MuJoCo, not {self.tried_runs}"
            )
        if self.on not in SEARCH_ON:
            raise ValueError(
                f"random search runs its episodes on one of {', '.join(SEARCH_ON)}, not {self.on!r}"
            )
        if self.stay_inside and self.on != "emulator":
            raise ValueError(
                "random search stays inside the emulator's envelope only on the emulator (on='emulator')"
            )
        if self.episodes < 1:
            raise ValueError(f"random search runs every policy from at least one start, not {self.episodes}")
        if not (self.step > 0 and self.noise > 0):
            raise ValueError(f"random search's step and noise are positive, not {self.step} and {self.noise}")


def flat_weights(net: nn.Module) -> Tensor:
    """(D,) the network's weights in ``parameters()`` order."""
    return nn.utils.parameters_to_vector(net.parameters()).detach().clone()


def set_weights(net: nn.Module, theta: Tensor) -> None:
    """Load (D,) weights (``flat_weights``' order) into the network."""
    nn.utils.vector_to_parameters(theta.to(next(net.parameters()).dtype), net.parameters())


def batched_forward(net: nn.Sequential, weights: Tensor, x: Tensor) -> Tensor:
    """The network ``net`` (linear layers and activations) under K sets of weights (K, D) at once:
    inputs (K, E, F) → outputs (K, E, out), the k-th set applied to the k-th inputs."""
    size = sum(q.numel() for q in net.parameters())
    if weights.shape[1] != size:
        raise ValueError(f"{weights.shape[1]} weights for a network of {size}")
    k, at = weights.shape[0], 0
    for layer in net:
        if isinstance(layer, nn.Linear):
            out, inp = layer.weight.shape
            w = weights[:, at : at + out * inp].reshape(k, out, inp)
            at += out * inp
            x = torch.einsum("kei,koi->keo", x, w)
            if layer.bias is not None:
                x = x + weights[:, at : at + out].unsqueeze(1)
                at += out
        else:
            x = layer(x)
    return x


def ars_update(theta: Tensor, deltas: Tensor, plus: Tensor, minus: Tensor, how: RandomSearch) -> Tensor:
    """One ARS V2-t step: weights (D,), directions (N, D), returns at θ+νδ and θ-νδ (N,) → new weights.
    The ``top`` directions by their better side's return, their differences over those returns' spread."""
    best = torch.maximum(plus, minus)
    top = torch.argsort(best, descending=True)[: how.top]
    spread = torch.cat([plus[top], minus[top]]).std()
    if not math.isfinite(float(spread)) or float(spread) < 1e-8:
        return theta  # every tried policy earned the same: no direction to prefer
    step = ((plus[top] - minus[top]).unsqueeze(1) * deltas[top]).sum(dim=0)
    return theta + how.step / (how.top * spread) * step


def perturbations(theta: Tensor, how: RandomSearch, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """(N, D) directions and the (2N, D) weights tried: θ+νδ for each, then θ-νδ for each."""
    deltas = torch.randn(how.directions, theta.numel(), generator=gen)
    return deltas, torch.cat([theta + how.noise * deltas, theta - how.noise * deltas])


def episode_steps(how: RandomSearch, policy_steps: int, super_timestep: float) -> int:
    """Super-steps of each emulated episode: ``seconds`` of them, at most the task's episode."""
    if how.seconds is None:
        return policy_steps
    return max(1, min(policy_steps, round(how.seconds / super_timestep)))


def as_generator(rng: np.random.Generator) -> torch.Generator:
    """A torch generator seeded from a NumPy one (the trainer's draws stay one stream)."""
    return torch.Generator().manual_seed(int(rng.integers(1 << 62)))


def held_on_mujoco(physical: PhysicalModel, substeps: int) -> Callable[[Tensor, Tensor], Tensor]:
    """A super-step on MuJoCo as the emulator's: (B, S) states, (B, U) controls held ``substeps``
    physical steps → (B, S) states."""

    def step(s: Tensor, u: Tensor) -> Tensor:
        nxt = physical.step_held(s.double().numpy(), u.double().numpy(), None, substeps)
        return torch.as_tensor(nxt, dtype=s.dtype)

    return step


@torch.no_grad()
def policies_returns(
    policy: RewardPolicy,
    net: nn.Sequential,
    weights: Tensor,
    starts: Tensor,
    params: Tensor,
    steps: int,
    step: Callable[[Tensor, Tensor], Tensor],
    reward: Callable[[Tensor, Tensor, Tensor], Tensor],
    repeat: int,
    envelope: tuple[Tensor, Tensor],
    halt_outside: bool = False,
) -> tuple[Tensor, int]:
    """(K,) mean return of ``policy`` with K sets of weights (K, D) in its network ``net``, all run
    as one batch: episodes of ``steps`` super-steps of ``step`` (the emulator's, or MuJoCo's:
    ``held_on_mujoco``) from the same starts (E, S) and parameters (E, P), ``reward`` (states,
    controls, parameters → (B,)) at every super-step times its ``repeat`` control steps. An episode
    that diverges (``DIVERGED``) earns nothing from then on, nor, with ``halt_outside``, one that
    leaves the ``envelope`` (low (S,), high (S,)); and the number of states outside it."""
    k, e = weights.shape[0], starts.shape[0]
    s = starts.repeat(k, 1)  # (K·E, S): the k-th policy's episodes are rows k·E .. k·E+E-1
    p = params.repeat(k, 1)
    total = torch.zeros(k * e)
    alive = torch.ones(k * e, dtype=torch.bool)
    outside = 0
    for _ in range(steps):
        f = policy.features(s, p).reshape(k, e, -1)
        a = torch.tanh(batched_forward(net, weights, f)).reshape(k * e, -1)
        u = nn.functional.linear(a, policy.spread, policy.centre)
        nxt = step(s, u)
        z = policy.features.plain_z(nxt)
        alive &= torch.isfinite(nxt).all(dim=1) & (z.abs() <= DIVERGED).all(dim=1)
        out = ((nxt < envelope[0]) | (nxt > envelope[1])).any(dim=1)
        if halt_outside:
            alive &= ~out
        s = torch.where(alive.unsqueeze(1), nxt, s)
        outside += int(out.sum())
        r = torch.nan_to_num(reward(s, u, p))
        total += torch.where(alive, r, torch.zeros_like(r)) * repeat
    return total.reshape(k, e).mean(dim=1), outside


class SearchLearner:
    """Random search on ``trainer``'s emulator, reward and policy (module doc)."""

    def __init__(self, trainer: RewardTrainer, how: RandomSearch) -> None:
        self.trainer, self.how = trainer, how
        self.gen = as_generator(trainer.rng)
        net = trainer.policy.net
        if not isinstance(net, nn.Sequential):
            raise TypeError("random search tries a sequential network's weights")
        self.net = net
        # the search starts from the controls' centres, as ARS's from a zero map
        last = [m for m in net if isinstance(m, nn.Linear)][-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.zero_()
        self.theta = flat_weights(net)
        # the latest step's tried weights (K, D) and their returns on the emulator (K,)
        self.tried: tuple[Tensor, Tensor] | None = None
        self.steps = episode_steps(how, trainer.task.policy_steps, trainer.manifest.super_timestep)
        self.substeps = trainer.manifest.substeps
        self.on_mujoco = held_on_mujoco(trainer.physical, self.substeps)

    def returns(self, weights: Tensor, starts: Tensor, params: Tensor) -> Tensor:
        """(K,) mean return of the policy under each of K sets of weights (K, D) over episodes of
        ``steps`` super-steps from the same starts (E, S) and parameters (E, P), on the emulator or
        on MuJoCo (``on``; ``policies_returns``). Its states outside the emulator's envelope are
        counted, as the actor-critic's are (``RewardTrainer.outside_share``), when the episodes are
        emulated."""
        tr = self.trainer
        on_emulator = self.how.on == "emulator"
        got, outside = policies_returns(
            tr.policy, self.net, weights, starts, params, self.steps,
            tr.step if on_emulator else self.physics_step,
            lambda s, u, p: tr.task.reward(tr.ctx, s, u, p, False), tr.task.repeat,
            (tr.env_low, tr.env_high), halt_outside=self.how.stay_inside,
        )  # fmt: skip
        if on_emulator:  # the share outside is the emulator's, not the physics'
            tr.outside_steps += outside
            tr.emulated_steps += self.steps * len(weights) * len(starts)
        return got

    def physics_step(self, s: Tensor, u: Tensor) -> Tensor:
        """One super-step of (B, S) states under (B, U) controls on MuJoCo (``on="mujoco"``), counted."""
        self.trainer.mujoco_steps += len(s) * self.substeps
        return self.on_mujoco(s, u)

    def iterate(self) -> float:
        """One ARS step from the task's starts; the mean return of the policies tried."""
        tr, how = self.trainer, self.how
        if how.seconds is None:
            pick = tr.rng.integers(len(tr.start_states), size=how.episodes)
            drawn = tr.start_states[pick], tr.start_params[pick]
        else:
            drawn = tr.restart(how.episodes)
        starts = torch.as_tensor(drawn[0], dtype=torch.float32)
        params = torch.as_tensor(drawn[1], dtype=torch.float32)
        deltas, tried = perturbations(self.theta, how, self.gen)
        got = self.returns(tried, starts, params)
        self.tried = (tried, got)
        self.theta = ars_update(self.theta, deltas, got[: how.directions], got[how.directions :], how)
        set_weights(self.net, self.theta)
        return float(got.mean())

    def run_tried(self) -> None:
        """The ``tried_runs`` best-earning of the latest step's tried policies, an episode each on
        MuJoCo from the task's starts (counted): runs the emulator is refined on, beside the
        policy's own (``RewardTrainer.runs``), and states restarts may begin from."""
        tr, n = self.trainer, self.how.tried_runs
        if not n or self.tried is None:
            return
        weights, got = self.tried
        trying = copy.deepcopy(tr.policy)
        trying_net = trying.net
        assert isinstance(trying_net, nn.Sequential)
        for k in torch.argsort(got, descending=True)[:n].tolist():
            set_weights(trying_net, weights[k])
            runs = tr.episodes(trying.act, 1, np.random.default_rng(int(tr.rng.integers(1 << 30))))
            tr.runs.append(runs)
            steps = runs.states.shape[1]  # every state of the episode, beside its parameters
            tr.visited.append((runs.states.reshape(steps, -1), np.repeat(runs.params, steps, axis=0)))

    def learn(
        self, best: tuple[float, dict[str, Tensor]], history: list[tuple[int, float, float]], it: int
    ) -> tuple[tuple[float, dict[str, Tensor]], list[tuple[int, float, float]], int, str]:
        """Random search until the budget is spent, checked on MuJoCo every ``eval_every`` of it (the
        best policy kept, the emulator refined where its return leaves MuJoCo's, the seeds met once
        at ``meet_at``); returns as ``RewardTrainer.learn`` does."""
        tr = self.trainer
        cfg, task = tr.settings, tr.task
        first, stop = it, "budget"
        check_every = max(1.0, cfg.eval_every * cfg.seconds)
        next_check = tr.elapsed() + check_every
        tried, last_return = math.nan, None
        while (it == first or tr.elapsed() < tr.deadline(cfg.eval_episodes)) and (
            cfg.max_iterations is None or it < cfg.max_iterations
        ):
            if tr.should_stop is not None and tr.should_stop():
                stop = "cancelled"
                break
            tried = self.iterate()
            it += 1
            last = tr.elapsed() >= tr.deadline(cfg.eval_episodes) or (
                cfg.max_iterations is not None and it >= cfg.max_iterations
            )
            if tr.elapsed() >= next_check or last:
                took_from = tr.took_from
                best, runs, emulated = tr.check(it, history, best)
                last_return = runs.mean
                log.info(
                    "%s: random search step %d, the tried policies' return on the %s %.1f; the "
                    "policy's on MuJoCo %.1f, on the emulator %.1f, tried states outside the envelope %.1f %%",
                    task.name, it, self.how.on, tried, last_return, emulated, 100 * tr.outside_share,
                )  # fmt: skip
                if tr.took_from != took_from:  # it goes on from the best seed's policy
                    self.theta = flat_weights(self.net)
                self.run_tried()
                tr.keep_runs(runs, emulated, may_refine=tr.elapsed() < 0.9 * cfg.seconds)
                next_check = tr.elapsed() + check_every
            tr.report(it, -tried, last_return)
        return best, history, it, stop
