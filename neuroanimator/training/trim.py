"""Trimming an emulator at its model's operating point: what holds the model still holds the emulator.

A hovering drone is what a user flies first, and an open-loop hover is a neutral equilibrium: a small
error in the emulated step at hover (a vertical velocity off by a few mm/s, a body rate by a few mrad/s
per super-step) integrates into metres within seconds. Measured on Menagerie's X2 at n = 50, trained to
a one-step error of 1.5e-4 over its typical motion: at exact hover the network's step was off by
6.6 mm/s vertically and 1.3 mrad/s in roll, and the emulator drifted 10 m from MuJoCo's hover in 10 s.

So after training, the network's output bias takes up its residual at the operating points (the states
of ``spec.initial.centres`` held at ``spec.operating.control_centres``, one per keyframe): the emulated
step there becomes MuJoCo's, up to float rounding, and everywhere else moves by the same small constant
(in normalised, local-frame units: rotating the hover about gravity keeps it trimmed). With several
operating points, their mean residual is taken.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from torch import nn

from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim.model import PhysicalModel

log = logging.getLogger(__name__)


def operating_points(model: PhysicalModel) -> tuple[np.ndarray, np.ndarray] | None:
    """(K, S) operating states and (K, U) their controls, or None for a model without them."""
    op, centres = model.spec.operating, model.spec.initial.centres
    if op is None or not centres or len(op.control_centres) != len(centres):
        return None
    return np.asarray(centres, dtype=np.float64), np.asarray(op.control_centres, dtype=np.float64)


def _residual(
    emu: StructuredEmulator, states: torch.Tensor, controls: torch.Tensor | None, nxt: torch.Tensor
) -> torch.Tensor:
    """(K, S) what the network should add to its normalised output at each operating point."""
    forces = torch.zeros(states.shape[0], emu.num_forces) if emu.num_forces else None
    return emu.network_targets(states, nxt) - emu.network(emu.network_inputs(states, controls, forces))


def trim(model: PhysicalModel, emu: StructuredEmulator, substeps: int) -> tuple[float, float] | None:
    """Shift the network's output bias so that the emulated super-step at the operating points is
    MuJoCo's (see the module doc); the largest normalised residual there before and after, or None
    when the model has no operating point or the network no single output layer."""
    points = operating_points(model)
    last = emu.core[-1] if isinstance(emu.core, nn.Sequential) and len(emu.core) else None
    if points is None or not isinstance(last, nn.Linear) or last.bias is None:
        return None
    x, u = points
    nxt = model.step_held(
        x,
        u if model.num_controls else None,
        np.zeros((len(x), model.num_forces)) if model.num_forces else None,
        substeps,
    )
    states = torch.tensor(x, dtype=torch.float32)
    controls = torch.tensor(u, dtype=torch.float32) if model.num_controls else None
    target = torch.tensor(nxt, dtype=torch.float32)
    with torch.no_grad():
        before = _residual(emu, states, controls, target)
        last.bias.add_(before.mean(dim=0))
        after = _residual(emu, states, controls, target)
    worst = float(before.abs().max()), float(after.abs().max())
    log.info("%s: trimmed at its operating point: normalised residual there %.3g -> %.3g", model.name, *worst)
    return worst
