"""Training an emulator, top to bottom: simulate examples, fit T^σ, train N^σ, fit the linear baseline.

Read ``train`` from the top: it is the whole recipe. The configuration is one dataclass
(``neuroanimator.train_config``), saved in full with every artifact.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from neuroanimator import sampling
from neuroanimator.physics.model import PhysicalModel
from neuroanimator.structured import FrameConfig, StructuredEmulator
from neuroanimator.train_config import TrainConfig

log = logging.getLogger(__name__)


class TrainingDiverged(RuntimeError):
    """Training produced a non-finite loss; no artifact is written."""


@dataclass
class TrainResult:
    emulator: StructuredEmulator
    config: TrainConfig
    metrics: dict[str, Any]
    linear: np.ndarray  # (D + 1, S) least-squares baseline in the network's normalised space
    data_sha256: str


def frame_config(model: PhysicalModel) -> FrameConfig:
    """The emulator's symmetries for a model; horizontal external forces are rotated in pairs."""
    fr = model.frame
    pairs: list[tuple[int, int]] = []
    rotate = fr.rotate
    if rotate and model.num_forces:
        by_body: dict[tuple[str, int], dict[int, int]] = {}
        for i, f in enumerate(model.spec.forces):
            by_body.setdefault((f.body, f.component // 3), {})[f.component % 3] = i
        for comps in by_body.values():
            if 0 in comps and 1 in comps:
                pairs.append((comps[0], comps[1]))
            elif 0 in comps or 1 in comps:
                rotate = False  # a lone horizontal component is not rotation-invariant: keep world frame
    return FrameConfig(translate=fr.translate, rotate=rotate, force_pairs=tuple(pairs) if rotate else ())


def build_emulator(model: PhysicalModel, cfg: TrainConfig) -> StructuredEmulator:
    return StructuredEmulator(
        model.layout, model.num_controls, model.num_forces, frame_config(model), cfg.hidden, cfg.activation
    )


def to_tensors(ex: sampling.Examples) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor]:
    s = torch.from_numpy(ex.states).float()
    u = torch.from_numpy(ex.controls).float() if ex.controls.shape[1] else None
    f = torch.from_numpy(ex.forces).float() if ex.forces.shape[1] else None
    return s, u, f, torch.from_numpy(ex.next_states).float()


def relative_error(pred: Tensor, target: Tensor) -> float:
    """‖ŷ − y‖² / ‖y − mean(y)‖² over all rows and outputs (1 − R²), in the normalised target space."""
    num = ((pred - target) ** 2).sum()
    den = ((target - target.mean(dim=0)) ** 2).sum()
    return float(num / den.clamp_min(1e-12))


def fit_linear(x: Tensor, y: Tensor) -> np.ndarray:
    """Least-squares affine map (D+1, S) from normalised inputs to normalised targets."""
    xa = torch.cat([x, torch.ones(x.shape[0], 1)], dim=1).double()
    sol = torch.linalg.lstsq(xa, y.double()).solution
    return sol.numpy()


def apply_linear(w: np.ndarray, x: Tensor) -> Tensor:
    xa = torch.cat([x, torch.ones(x.shape[0], 1)], dim=1).double()
    return (xa @ torch.from_numpy(w)).float()


def held_out_seed(seed: int) -> int:
    """The seed of the held-out test set: a different stream from the training data's."""
    return seed + 1_000_003


def train(model: PhysicalModel, cfg: TrainConfig) -> TrainResult:
    """Simulate data, fit normalisation, train N^σ with early stopping, evaluate on held-out data."""
    cfg = cfg.resolved()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    t_start = time.perf_counter()
    emu = build_emulator(model, cfg)
    weights = sum(p.numel() for p in emu.core.parameters())
    count = cfg.examples or math.ceil(cfg.examples_per_weight * weights)
    log.info("%s n=%d: %d weights, %d examples", model.name, cfg.substeps, weights, count)

    # 1. data: training (+ validation) and an independent held-out test set
    data = sampling.generate(model, cfg.substeps, count, cfg.seed, progress=cfg.progress)
    test = sampling.generate(
        model, cfg.substeps, cfg.test_examples, held_out_seed(cfg.seed), progress=cfg.progress
    )
    t_data = time.perf_counter() - t_start

    # 2. T^σ from the training data (transformed by T'_x and (T'_y T^Δ_y)^-1 first, thesis 4.5.2)
    s, u, f, nxt = to_tensors(data)
    with torch.no_grad():
        x_local = emu.local_inputs(s, u, f)
        y_local = emu.delta_to_local(s, nxt - s)
        emu.set_normalization(x_local, y_local, cfg.normalization)
        x = emu.normalize_inputs(x_local)
        y = (y_local - emu.y_mean) / emu.y_std
    n_val = max(1, int(len(data) * cfg.val_fraction))
    x_tr, y_tr, x_val, y_val = x[n_val:], y[n_val:], x[:n_val], y[:n_val]

    # 3. the core network
    train_core(emu, x_tr, y_tr, x_val, y_val, cfg)

    # 4. held-out evaluation and the linear baseline fitted on the same training inputs
    linear = fit_linear(x_tr, y_tr)
    ts, tu, tf, tn = to_tensors(test)
    with torch.no_grad():
        xt = emu.network_inputs(ts, tu, tf)
        yt = emu.network_targets(ts, tn)
        one_step = relative_error(emu.core(xt), yt)
        lin = relative_error(apply_linear(linear, xt), yt)
        val = relative_error(emu.core(x_val), y_val)
    metrics = {
        "weights": weights,
        "examples": count,
        "test_examples": len(test),
        "one_step_rel_error": one_step,
        "linear_baseline_rel_error": lin,
        "validation_rel_error": val,
        "data_seconds": round(t_data, 2),
        "train_seconds": round(time.perf_counter() - t_start - t_data, 2),
        "total_seconds": round(time.perf_counter() - t_start, 2),
    }
    log.info(
        "%s n=%d: one-step relative error %.5f (linear %.4f), %.0f s",
        model.name,
        cfg.substeps,
        one_step,
        lin,
        metrics["total_seconds"],
    )
    return TrainResult(emu, cfg, metrics, linear, data.sha256())


def train_core(
    emu: StructuredEmulator, x: Tensor, y: Tensor, x_val: Tensor, y_val: Tensor, cfg: TrainConfig
) -> None:
    """Mini-batch training of N^σ on normalised data, early stopping on the validation loss."""
    net = emu.core
    if cfg.optimizer == "adam":
        opt: torch.optim.Optimizer = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    elif cfg.optimizer == "sgd":
        opt = torch.optim.SGD(net.parameters(), lr=cfg.lr, momentum=cfg.momentum)
    else:
        raise ValueError(f"optimizer must be 'adam' or 'sgd', got {cfg.optimizer!r}")
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=max(2, cfg.patience // 4))
    n_state_inputs = sum(w for name, w in emu.input_groups if name not in ("controls", "forces"))
    gen = torch.Generator().manual_seed(cfg.seed)
    best, best_state, stale = math.inf, None, 0
    t0 = time.perf_counter()
    bar = tqdm(range(cfg.max_epochs), desc="training", unit="epoch", disable=not cfg.progress, leave=False)
    for epoch in bar:
        net.train()
        perm = torch.randperm(x.shape[0], generator=gen)
        for i in range(0, x.shape[0], cfg.batch_size):
            idx = perm[i : i + cfg.batch_size]
            xb, yb = x[idx], y[idx]
            if cfg.input_noise > 0:
                # noise on the state inputs only: the net learns to pull a drifted state back
                noise = torch.randn(xb.shape[0], n_state_inputs, generator=gen) * cfg.input_noise
                xb = torch.cat([xb[:, :n_state_inputs] + noise, xb[:, n_state_inputs:]], dim=1)
            loss = torch.mean((net(xb) - yb) ** 2)
            if not torch.isfinite(loss):
                raise TrainingDiverged(
                    f"training diverged at epoch {epoch} (loss {float(loss.detach())}); lower the learning rate ({cfg.lr})"
                )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        net.eval()
        with torch.no_grad():
            val = float(torch.mean((net(x_val) - y_val) ** 2))
        if not math.isfinite(val):
            raise TrainingDiverged(f"validation loss became {val} at epoch {epoch}; lower the learning rate")
        sched.step(val)
        if val < best * (1 - 1e-4):
            best, stale = val, 0
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        else:
            stale += 1
        bar.set_postfix(val=f"{val:.2e}", best=f"{best:.2e}", lr=f"{opt.param_groups[0]['lr']:.1e}")
        if stale >= cfg.patience:
            log.info("early stop at epoch %d (best validation mse %.3e)", epoch, best)
            break
        if time.perf_counter() - t0 > cfg.max_seconds:
            log.info("time cap %.0f s reached at epoch %d", cfg.max_seconds, epoch)
            break
    bar.close()
    if best_state is not None:
        net.load_state_dict(best_state)
