"""Which epoch of a training to keep, weighing a closed loop beside the one-step validation loss.

A one-step loss does not weigh the small biases that a loop of hundreds of super-steps integrates: the
runner's emulators with the lowest one-step errors were, three times, the ones whose emulated run
drifted farthest from MuJoCo's (BENCHMARKS.md, the runner's emulator). A model's data source can offer
a *loop check* (``loop_check(model, substeps)`` in its module: a callable that closes the model's own
controller through a step function and returns how far the loop ends from MuJoCo's, in metres or any
unit where lower is better). With ``TrainConfig.loop_tolerance`` set, every epoch whose validation loss
is within that fraction of the best one is a candidate, and the candidate whose loop ends nearest
MuJoCo's is kept; early stopping still follows the validation loss.

A loop check must average many runs: the runner's distance from MuJoCo's at 5 s from one start ranged
over 0.2-1.2 m among epochs of one training whose validation losses were within 5 % of each other, and
an epoch chosen on three starts was no better on others (BENCHMARKS.md).
"""

from __future__ import annotations

import importlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from numpy.typing import NDArray

from neuroanimator.core.train_config import TrainConfig
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.metrics import LoopChoiceMetrics

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
Step = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]
LoopCheck = Callable[[Step], float]


def numpy_step(emu: torch.nn.Module) -> Step:
    """The emulator as a step on numpy arrays: states (B, S), controls (B, U), forces (B, F) -> (B, S)."""

    def step(s: FloatArray, u: FloatArray, f: FloatArray) -> FloatArray:
        with torch.no_grad():
            out = emu(
                torch.from_numpy(s).float(),
                torch.from_numpy(u).float() if u.shape[1] else None,
                torch.from_numpy(f).float() if f.shape[1] else None,
            )
        return np.asarray(out.double().numpy())

    return step


def loop_choice(model: PhysicalModel, cfg: TrainConfig) -> LoopChoice | None:
    """The choice of the kept epoch for ``cfg.loop_tolerance`` (None: off) from the loop check of the
    model's data source; a tolerance for a model without one is an error."""
    if cfg.loop_tolerance is None:
        return None
    if cfg.loop_tolerance < 0:
        raise ValueError(f"loop_tolerance must be at least 0, got {cfg.loop_tolerance}")
    source = model.spec.data_source
    make = None if source is None else getattr(importlib.import_module(source), "loop_check", None)
    if make is None:
        raise ValueError(
            f"{model.name}: loop_tolerance weighs a closed loop in the choice of the kept epoch, and this "
            "model's data source has no loop check (a controller of its own to close the loop with)"
        )
    check: LoopCheck = make(model, cfg.substeps)
    return LoopChoice(check, cfg.loop_tolerance)


@dataclass
class _Candidate:
    epoch: int
    val: float
    loop: float
    state: dict[str, torch.Tensor]


@dataclass
class LoopChoice:
    """The candidates of one training (see the module docstring) and the curve of every epoch's
    validation loss and loop error."""

    check: LoopCheck
    tolerance: float
    curve: list[tuple[int, float, float]] = field(default_factory=list)
    _candidates: list[_Candidate] = field(default_factory=list)

    def offer(self, epoch: int, val: float, best: float, net: torch.nn.Module, emu: torch.nn.Module) -> float:
        """Measure the loop after ``epoch`` (validation loss ``val``, the best so far ``best``), keep
        the state as a candidate if ``val`` is within the tolerance; returns the loop error."""
        was_training = net.training
        net.eval()
        loop = float(self.check(numpy_step(emu)))
        net.train(was_training)
        if not math.isfinite(loop):
            loop = math.inf
        self.curve.append((epoch, val, loop))
        limit = (1 + self.tolerance) * best
        self._candidates = [c for c in self._candidates if c.val <= limit]
        if val <= limit:
            state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            self._candidates.append(_Candidate(epoch, val, loop, state))
        return loop

    def _kept(self) -> _Candidate | None:
        return min(self._candidates, key=lambda c: c.loop) if self._candidates else None

    def restore(self, net: torch.nn.Module) -> int | None:
        """Load the kept candidate into ``net``; its epoch (None if there was none)."""
        kept = self._kept()
        if kept is None:
            return None
        net.load_state_dict(kept.state)
        best_val = min(c.val for c in self._candidates)
        log.info(
            "kept epoch %d: loop error %.3g, validation %.3e (the best %.3e)",
            kept.epoch,
            kept.loop,
            kept.val,
            best_val,
        )
        return kept.epoch

    def metrics(self) -> LoopChoiceMetrics:
        """For the training's metrics: the kept epoch, its loop error, and every epoch's
        ``[epoch, validation loss, loop error]``."""
        kept = self._kept()
        return {
            "loop_tolerance": self.tolerance,
            "loop_kept_epoch": None if kept is None else kept.epoch,
            "loop_error_kept": None if kept is None or not math.isfinite(kept.loop) else kept.loop,
            # JSON has no infinity: a loop that went non-finite is null
            "loop_curve": [[e, v, lp if math.isfinite(lp) else None] for e, v, lp in self.curve],
        }
