"""Controls as Catmull-Rom splines over control points (thesis appendix G), in torch.

Control ``i`` is a spline through points ``p_i^0 .. p_i^{M-1}`` spread evenly over the start times
of the K super-steps, ``[0, (K-1)·Δt]``, end points duplicated (``neuroanimator.core.catmull_rom.basis``).
The emulator was trained with controls held for the n physical steps of each super-step, so the
value used in super-step k is the spline *sampled at the super-step's start* and held; the MuJoCo
replay holds the very same values. Sampling is one constant matrix, so it is differentiable:
``held = B @ points`` with ``B`` (K, M).

Shapes: K super-steps, M control points per control, U controls, leading batch axes allowed.
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from neuroanimator.core import catmull_rom


def spacing_of(horizon: int, num_points: int, super_dt: float) -> float:
    """Seconds between control points: M points spread over the K super-step starts.

    With one point per super-step this is Δt, and every held value *is* a control point.
    """
    if num_points < 2 or horizon < 2:
        return super_dt
    return (horizon - 1) * super_dt / (num_points - 1)


def held_basis(horizon: int, num_points: int, super_dt: float) -> NDArray[np.float64]:
    """(K, M) weights: the held value of super-step k is ``basis[k] @ points``."""
    times = np.arange(horizon, dtype=np.float64) * super_dt
    return catmull_rom.basis(num_points, times, spacing_of(horizon, num_points, super_dt))


class ControlSpline:
    """The map from control points (..., M, U) to held per-super-step values (..., K, U)."""

    def __init__(
        self, horizon: int, num_points: int, super_dt: float, dtype: torch.dtype = torch.float32
    ) -> None:
        if horizon < 1 or num_points < 1:
            raise ValueError(f"horizon and num_points must be >= 1, got {horizon} and {num_points}")
        self.horizon = horizon
        self.num_points = num_points
        self.super_dt = super_dt
        self.spacing = spacing_of(horizon, num_points, super_dt)
        self.basis = torch.from_numpy(held_basis(horizon, num_points, super_dt)).to(dtype)  # (K, M)

    def held(self, points: Tensor) -> Tensor:
        """Held control values (..., K, U) of points (..., M, U); differentiable in the points."""
        if points.shape[-2] != self.num_points:
            raise ValueError(
                f"points must have {self.num_points} rows (axis -2), got shape {tuple(points.shape)}"
            )
        return torch.matmul(self.basis.to(points.dtype), points)

    def times(self) -> NDArray[np.float64]:
        """(K,) the start time of every super-step, where the spline is sampled."""
        return np.arange(self.horizon, dtype=np.float64) * self.super_dt
