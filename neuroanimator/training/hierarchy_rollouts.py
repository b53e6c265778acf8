"""Training a hierarchical emulator over its own rollouts, regulariser included (thesis 4.4, 6.1.3).

Each network of a hierarchy first learns its own one-step targets (``hierarchy_training``), given the
true next frames. Served, the step composes them: the local networks read the global network's
*predicted* frames, and a deformable model's step ends with the spring regulariser's Euler steps.
Neither is in the one-step targets, so a long rollout meets states that no network was trained on:
the regulariser moves velocities off the simulation's states, and over minutes the loop can run away.

This phase fine-tunes every network together through the composed step as it is served, on K-step
rollouts from simulated sequences: the loss is the rollout's error (each state value divided by the
spread of its group's change over a super-step) plus every network's one-step loss, each relative to
its value when the phase starts, so that the networks learn the states their own loop makes without
trading away their one-step accuracy. The state kept is the one with the best validation loss.
"""

from __future__ import annotations

import logging
import time

import torch
from torch import Tensor

from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.hierarchy import HierarchicalEmulator
from neuroanimator.sim import sampling
from neuroanimator.training.metrics import RolloutMetrics
from neuroanimator.training.train import KeepBest, TrainingDiverged

log = logging.getLogger(__name__)

STEP_FLOOR = 1e-4
OneStep = dict[str, tuple[Tensor, Tensor, Tensor, Tensor]]  # network -> normalised train x, y, val x, y


def composed_rollout_loss(emu: HierarchicalEmulator, s: Tensor, u: Tensor, scale: Tensor) -> Tensor:
    """Mean squared error of a K-step rollout of the composed step against the physics, each value
    divided by ``scale`` (S,): s (B, K+1, S), u (B, K, U)."""
    state = s[:, 0]
    total = torch.zeros((), dtype=s.dtype)
    for k in range(s.shape[1] - 1):
        state = emu(state, u[:, k])
        total = total + torch.mean(((state - s[:, k + 1]) / scale) ** 2)
    return total / (s.shape[1] - 1)


def train_hierarchy_over_rollouts(
    emu: HierarchicalEmulator, seq: sampling.Sequences, cfg: TrainConfig, scale: Tensor, one_step: OneStep
) -> RolloutMetrics:
    """Fine-tune every network of ``emu`` through its composed step (with ``emu.regularizer`` when set)
    on the rollouts of ``seq``, for at most ``cfg.rollout_seconds``; returns the validation rollout
    loss before and after, and the epochs run."""
    s = torch.from_numpy(seq.states).float()
    u = torch.from_numpy(seq.controls).float()
    n_val = max(1, len(seq) // 10)
    val, tr = slice(0, n_val), slice(n_val, None)
    nets = dict(emu.networks)
    params = [
        p
        for net in nets.values()
        for p in [*net.core.parameters(), *(net.skip.parameters() if net.skip else [])]
    ]
    opt = torch.optim.Adam(params, lr=cfg.lr * 0.1)
    gen = torch.Generator().manual_seed(cfg.seed + 13)

    def step_mse(name: str, x: Tensor, y: Tensor) -> Tensor:
        """A network's one-step mean squared error on normalised inputs x and targets y."""
        return torch.mean((nets[name].network(x) - y) ** 2)

    def validate_parts() -> tuple[float, dict[str, float]]:
        emu.eval()
        with torch.no_grad():
            roll = float(composed_rollout_loss(emu, s[val], u[val], scale))
            steps = {name: float(step_mse(name, d[2], d[3])) for name, d in one_step.items()}
        return roll, steps

    roll0, step0 = validate_parts()
    roll0 = max(roll0, 1e-12)
    # a network that is nearly exact (the dolphin's fluke: 1e-9) would make any change to it look
    # enormous; below a mean squared error of 1e-4 on its normalised targets it is held to that
    step0 = {name: max(v, STEP_FLOOR) for name, v in step0.items()}

    def validate() -> float:
        roll, steps = validate_parts()
        return roll / roll0 + sum(steps[n] / step0[n] for n in steps) / len(steps)

    keep = KeepBest(emu, validate())
    t0, epochs = time.perf_counter(), 0
    batch = max(16, cfg.batch_size // 8)
    s_tr, u_tr = s[tr], u[tr]
    while time.perf_counter() - t0 < cfg.rollout_seconds and keep.stale < 10 and epochs < cfg.max_epochs:
        emu.train()
        perm = torch.randperm(s_tr.shape[0], generator=gen)
        for i in range(0, perm.numel(), batch):
            idx = perm[i : i + batch]
            loss = composed_rollout_loss(emu, s_tr[idx], u_tr[idx], scale) / roll0
            for name, d in one_step.items():
                rows = torch.randint(0, d[0].shape[0], (4 * batch,), generator=gen)
                loss = loss + step_mse(name, d[0][rows], d[1][rows]) / step0[name] / len(one_step)
            if not torch.isfinite(loss):
                raise TrainingDiverged(f"training over rollouts diverged (loss {float(loss.detach())})")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if time.perf_counter() - t0 > cfg.rollout_seconds:
                break
        epochs += 1
        now = validate()
        log.debug("rollout epoch %d: validation %.4f (best %.4f)", epochs, now, keep.best)
        keep.offer(now)
    keep.restore()
    after, _ = validate_parts()
    emu.eval()
    log.info(
        "rollout phase through the composed step: %d epochs, validation rollout loss %.3g -> %.3g",
        epochs,
        roll0,
        after,
    )
    return {"rollout_loss_before": roll0, "rollout_loss_after": after, "rollout_epochs": epochs}
