"""The normalisation folded into a structured emulator's core: the same map with fewer operations
(what the ONNX graph and the torch controller paths step)."""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn

from neuroanimator.emulator.articulated import NormalizedCore, articulated_core
from neuroanimator.emulator.structured import StructuredEmulator


def fold_normalization(emu: StructuredEmulator) -> Any:
    """A copy of the core (nn.Sequential) with T^σ_x folded into its first layer and T^σ_y into its last.

    (x - μ)/σ followed by W x + b is W' x + b' with W' = W / σ and b' = b - W' μ; likewise the
    output scaling. The input placement x = ext @ P folds in too (W'' = W' Pᵀ), so the first layer
    reads the unplaced local columns. The map is the same; the graph has five fewer nodes per call.
    """

    class WithSkip(nn.Module):
        """The folded MLP plus the folded linear path: ``core(cols) + skip(cols)``."""

        def __init__(self, core: nn.Module, skip: nn.Module) -> None:
            super().__init__()
            self.core = core
            self.skip = skip

        def forward(self, cols: torch.Tensor) -> torch.Tensor:
            return self.core(cols) + self.skip(cols)

    if articulated_core(emu) is not None:  # a composed core: its normalisation stays around it
        return NormalizedCore(emu)
    core = copy.deepcopy(emu.core)
    first, last = core[0], core[-1]
    assert isinstance(first, nn.Linear) and isinstance(last, nn.Linear)

    def fold_input(layer: nn.Linear) -> None:
        w = layer.weight / emu.x_std  # (H, D) / (D,)
        layer.bias.copy_(layer.bias - w @ emu.x_mean)
        placed = w @ emu.input_placement.T  # (H, E)
        layer.weight = nn.Parameter(placed)
        layer.in_features = placed.shape[1]

    with torch.no_grad():
        fold_input(first)
        last.weight.copy_(last.weight * emu.y_std[:, None])
        last.bias.copy_(last.bias * emu.y_std + emu.y_mean)
        if emu.skip is None:
            return core
        skip = copy.deepcopy(emu.skip)
        fold_input(skip)
        skip.weight.copy_(skip.weight * emu.y_std[:, None])
        skip.bias.copy_(skip.bias * emu.y_std)  # y_mean is added once, by the MLP's last layer
    return WithSkip(core, skip)
