"""Training a hierarchical emulator (thesis 4.4): each network on its own targets.

The global network learns the motion of the parts' frames (their change over a super-step); each
local network learns its part's next groups in the part's *true* next frame, so the local networks
do not depend on the global one's errors while they train. Every network is fitted like a
one-network emulator (``training``: normalisation, the linear baseline that starts its linear path,
mini-batch training with early stopping), from the same simulated examples.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuroanimator.core.manifest import EnvelopeGroup
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.hierarchy import GLOBAL, HierarchicalEmulator
from neuroanimator.emulator.regularizer import regularization
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim import sampling
from neuroanimator.sim.model import ModelError, PhysicalModel
from neuroanimator.training.envelope import examples_envelope
from neuroanimator.training.hierarchy_rollouts import train_hierarchy_over_rollouts
from neuroanimator.training.metrics import HierarchyMetrics, RolloutMetrics
from neuroanimator.training.train import (
    apply_linear,
    cached_examples,
    cached_held_out,
    relative_error,
    rollout_sequences,
    start_from_linear,
    to_tensors,
    train_core,
)

log = logging.getLogger(__name__)


SMALL_HIDDEN = (16,)
SMALL_EXAMPLES = 5_000
SMALL_TEST_EXAMPLES = 1_000


def small_defaults(
    cfg: TrainConfig, *, hidden_given: bool, examples_given: bool, rollout_given: bool = False
) -> TrainConfig:
    """The config with a hierarchy's small defaults where the user chose nothing: one hidden layer of
    16 units per network, 5,000 examples, 1,000 held out (minutes of simulation for the dolphin; the
    thesis-sized training is a benchmark), and no rollout phase: fine-tuning through the composed
    step is asked for with ``rollout_steps`` (BENCHMARKS.md measures what it does to the dolphin)."""
    return dataclasses.replace(
        cfg,
        hidden=cfg.hidden if hidden_given else SMALL_HIDDEN,
        examples=cfg.examples if examples_given else SMALL_EXAMPLES,
        test_examples=min(cfg.test_examples, SMALL_TEST_EXAMPLES),
        rollout_steps=cfg.rollout_steps if rollout_given else 0,
    )


@dataclass
class HierarchyResult:
    """A trained hierarchy, saved like a ``training.TrainResult``; ``linear`` is the global network's
    least-squares baseline."""

    emulator: HierarchicalEmulator
    config: TrainConfig
    metrics: HierarchyMetrics
    linear: np.ndarray
    data_sha256: str
    envelope: list[EnvelopeGroup] | None = None  # per state group, the range of the training states


def build_hierarchy(model: PhysicalModel, cfg: TrainConfig) -> HierarchicalEmulator:
    """The hierarchy of ``model.spec.parts``: the global network ``cfg.hidden`` wide, each part's
    ``cfg.branch_hidden`` (None: as wide as the global one)."""
    if not model.spec.parts:
        raise ModelError(f"model {model.name} has no parts: its emulator is one network")
    return HierarchicalEmulator(
        model.layout,
        model.num_controls,
        model.spec.parts,
        cfg.hidden,
        cfg.branch_hidden or cfg.hidden,
        cfg.activation,
        skip=cfg.skip and cfg.preset != "thesis",
        num_forces=model.num_forces,
    )


@dataclass
class _Targets:
    """One network's training data: its state, controls, extra inputs and next state, (N, ·) each."""

    state: Tensor
    controls: Tensor | None
    extra: Tensor | None
    next_state: Tensor

    def rows(self, sl: slice) -> _Targets:
        return _Targets(
            self.state[sl],
            None if self.controls is None else self.controls[sl],
            None if self.extra is None else self.extra[sl],
            self.next_state[sl],
        )


def network_data(emu: HierarchicalEmulator, s: Tensor, u: Tensor | None, nxt: Tensor) -> list[_Targets]:
    """Every network's data for transitions s -> nxt: the global network's frames, then each part's
    groups in its frame, given the true next frames."""
    with torch.no_grad():
        g_state, g_next = emu.global_inputs(s, nxt)
        out = [_Targets(g_state, u, None, g_next)]
        frames, next_frames = emu.frames_of(s), emu.frames_of(nxt)
        for k in range(len(emu.parts)):
            part, frame_in = emu.local_inputs(k, s, next_frames, frames)
            out.append(_Targets(part, u, frame_in, emu.local_target(k, nxt)))
    return out


def fit_linear(x: Tensor, y: Tensor, rcond: float = 1e-5) -> np.ndarray:
    """Least-squares affine map (D+1, S), the minimum-norm solution with singular values below ``rcond``
    of the largest dropped: a local network's inputs are linearly dependent (its points' offsets from
    their centre sum to zero, its axes are sums of them), and a plain solve blows up along those
    directions."""
    xa = torch.cat([x, torch.ones(x.shape[0], 1)], dim=1).double()
    sol = torch.linalg.lstsq(xa, y.double(), rcond=rcond, driver="gelsd").solution
    return sol.numpy()


def _normalised(net: StructuredEmulator, d: _Targets) -> tuple[Tensor, Tensor]:
    with torch.no_grad():
        return net.network_inputs(d.state, d.controls, d.extra), net.network_targets(d.state, d.next_state)


def fit_network(net: StructuredEmulator, d: _Targets, cfg: TrainConfig) -> tuple[np.ndarray, float]:
    """Fit one network's normalisation, its linear baseline (which starts its linear path) and train
    it; returns the baseline (D+1, S) and the relative error on the validation rows."""
    with torch.no_grad():
        x_local = net.local_inputs(d.state, d.controls, d.extra)
        net.set_normalization(x_local, net.delta_to_local(d.state, d.next_state - d.state), cfg.normalization)
    x, y = _normalised(net, d)
    n_val = max(1, int(x.shape[0] * cfg.val_fraction))
    linear = fit_linear(x[n_val:], y[n_val:])
    if net.skip is not None:
        start_from_linear(net, linear)
    train_core(net, x[n_val:], y[n_val:], x[:n_val], y[:n_val], cfg)
    net.eval()
    with torch.no_grad():
        return linear, relative_error(net.network(x[:n_val]), y[:n_val])


def group_scale(model: PhysicalModel, change: Tensor) -> Tensor:
    """(S,) each column's scale for the composed step's error: the spread of its group's change (all
    of a group's columns together, as the networks normalise). A per-column scale would divide by
    nothing where a column never changes (a symmetric body that moves only in its plane)."""
    scale = torch.empty(change.shape[1], dtype=change.dtype)
    for _, sl in model.layout.group_slices():
        scale[sl] = change[:, sl].std(dim=0).pow(2).mean().sqrt()
    return scale.clamp_min(1e-12)


def drifted(model: PhysicalModel, s: Tensor, nxt: Tensor, share: float, seed: int) -> Tensor:
    """(N, S) states moved by Gaussian noise of ``share`` of each group's change over a super-step
    (``group_scale``): the states an emulator's own small errors lead it to. Trained from them to the
    true next states, a network learns to pull a drifted state back towards the simulation's."""
    gen = torch.Generator().manual_seed(seed + 1)
    noise = torch.randn(s.shape, generator=gen, dtype=s.dtype)
    return s + share * group_scale(model, nxt - s) * noise


def _train_composed(
    model: PhysicalModel, emu: HierarchicalEmulator, cfg: TrainConfig, count: int, own_data: list[_Targets]
) -> RolloutMetrics:
    """The rollout phase (``hierarchy_rollouts``): simulate sequences, then fine-tune every network
    through the composed step as it is served, keeping each network's one-step loss in the objective."""
    seqs = rollout_sequences(model, cfg, count)
    one_step = {}
    for (name, net), d in zip(emu.networks, own_data, strict=True):
        x, y = _normalised(net, d)
        n_val = max(1, int(x.shape[0] * cfg.val_fraction))  # the rows ``fit_network`` validated on
        one_step[name] = (x[n_val:], y[n_val:], x[:n_val], y[:n_val])
    steps = torch.from_numpy(seqs.states[:, 1:] - seqs.states[:, :-1]).float()
    scale = group_scale(model, steps.reshape(-1, steps.shape[2]))
    return train_hierarchy_over_rollouts(emu, seqs, cfg, scale, one_step)


def train_hierarchy(
    model: PhysicalModel, cfg: TrainConfig, data_cache: Path | None = None
) -> HierarchyResult:
    """Simulate data, then train the global network and every local network on their own targets
    (the time budget ``max_seconds`` shared between them); evaluate each and the composed step on
    held-out data. ``data_cache``: a directory where the simulated examples are kept and read back,
    the same files as a one-network training of the model makes (``neuroanimator.training.data_cache``)."""
    cfg = cfg.resolved()
    if cfg.mirror:
        raise ModelError(
            "mirror images are for joint-space figures (one network or an articulated hierarchy)"
        )
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    t_start = time.perf_counter()
    emu = build_hierarchy(model, cfg)
    networks = emu.networks
    weights = sum(p.numel() for p in emu.parameters())
    count = _examples(model, cfg, emu, weights)
    data = cached_examples(data_cache, model, cfg, count)
    test = cached_held_out(data_cache, model, cfg, cfg.test_examples, like=count)
    t_data = time.perf_counter() - t_start

    own_data = _own_data(model, emu, cfg, data)
    each = dataclasses.replace(cfg, max_seconds=cfg.max_seconds / len(networks))
    fitted = {name: fit_network(net, d, each) for (name, net), d in zip(networks, own_data, strict=True)}
    linears = {name: lin for name, (lin, _) in fitted.items()}
    # the step as it is served: a deformable model's ends with the spring regulariser (thesis 6.1.3)
    emu.regularizer = regularization(
        model.layout, model.spec.regularizer, model.num_controls, cfg.regularizer_steps
    )
    rollout_metrics: RolloutMetrics = {}
    if cfg.rollout_steps > 0:
        rollout_metrics = _train_composed(model, emu, cfg, count, own_data)

    errors, composed, regularized = _held_out_errors(model, emu, linears, test)
    worst = max(errors, key=lambda n: errors[n]["one_step_rel_error"])
    metrics: HierarchyMetrics = {
        "weights": weights,
        "examples": count,
        "test_examples": len(test),
        # the worst network's held-out errors: every network must be accurate
        "one_step_rel_error": errors[worst]["one_step_rel_error"],
        "linear_baseline_rel_error": errors[worst]["linear_baseline_rel_error"],
        "validation_rel_error": max(val for _, val in fitted.values()),
        "network_errors": errors,
        "composed_rel_error": composed,
        # the same with the spring regulariser after the networks (thesis 6.1.3), as the step is served
        "composed_regularized_rel_error": regularized,
        **rollout_metrics,
        "data_seconds": round(t_data, 2),
        "train_seconds": round(time.perf_counter() - t_start - t_data, 2),
        "total_seconds": round(time.perf_counter() - t_start, 2),
    }
    log.info(
        "%s n=%d: worst network %s one-step relative error %.3g (linear %.3g), composed %.3g, %.0f s",
        model.name,
        cfg.substeps,
        worst,
        metrics["one_step_rel_error"],
        metrics["linear_baseline_rel_error"],
        composed,
        metrics["total_seconds"],
    )
    envelope = examples_envelope(model, data)
    return HierarchyResult(emu.eval(), cfg, metrics, linears[GLOBAL], data.sha256(), envelope)


def _examples(model: PhysicalModel, cfg: TrainConfig, emu: HierarchicalEmulator, weights: int) -> int:
    """How many examples to simulate: ``cfg.examples``, or ``cfg.examples_per_weight`` per weight of
    the largest network (every network sees every example)."""
    largest = max(sum(p.numel() for p in net.parameters()) for _, net in emu.networks)
    count = cfg.examples or math.ceil(cfg.examples_per_weight * largest)
    log.info(
        "%s n=%d: %d networks, %d weights, %d examples",
        model.name,
        cfg.substeps,
        len(emu.networks),
        weights,
        count,
    )
    return count


def _own_data(
    model: PhysicalModel, emu: HierarchicalEmulator, cfg: TrainConfig, data: sampling.Examples
) -> list[_Targets]:
    """Every network's training data from ``data`` (``network_data``), the global network's from
    drifted states with ``cfg.state_noise``."""
    s, u, _, nxt = to_tensors(data)
    own_data = network_data(emu, s, u, nxt)
    if cfg.state_noise > 0:
        # the global network from drifted states: it carries the body's motion from step to step, so
        # its drift is what a long rollout integrates (the parts are placed in its frames each step)
        with torch.no_grad():
            g_state, g_next = emu.global_inputs(drifted(model, s, nxt, cfg.state_noise, cfg.seed), nxt)
        own_data[0] = _Targets(g_state, u, None, g_next)
    return own_data


def _held_out_errors(
    model: PhysicalModel, emu: HierarchicalEmulator, linears: dict[str, np.ndarray], test: sampling.Examples
) -> tuple[dict[str, dict[str, float]], float, float | None]:
    """On the held-out ``test`` examples: each network's one-step relative error and its linear
    baseline's (``linears``, by name), the composed step's error without the regulariser and with it
    (None without one), each column scaled by its group's change (``group_scale``)."""
    ts, tu, _, tn = to_tensors(test)
    regularizer = emu.regularizer
    errors: dict[str, dict[str, float]] = {}
    with torch.no_grad():
        for (name, net), d in zip(emu.networks, network_data(emu, ts, tu, tn), strict=True):
            x, y = _normalised(net, d)
            errors[name] = {
                "one_step_rel_error": relative_error(net.network(x), y),
                "linear_baseline_rel_error": relative_error(apply_linear(linears[name], x), y),
            }
        change = tn - ts
        scale = group_scale(model, change)
        emu.regularizer = None
        composed = relative_error((emu(ts, tu) - ts) / scale, change / scale)
        emu.regularizer = regularizer
        regularized = (
            None if regularizer is None else relative_error((emu(ts, tu) - ts) / scale, change / scale)
        )
    return errors, composed, regularized
