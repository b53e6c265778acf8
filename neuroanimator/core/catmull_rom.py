"""Catmull-Rom control functions (thesis appendix G).

A control function ``u_i(t)`` interpolates control points ``u_i^j`` placed every ``spacing`` seconds;
the end points are duplicated so the curve passes through the first and the last point. Because a
Catmull-Rom curve is linear in its points, the whole evaluation is one matrix: ``basis(M, times,
spacing)`` gives ``W`` of shape ``(T, M)`` and ``u(times) = W @ points``. The same ``W`` serves the
numpy samplers and the differentiable torch controllers (``torch.from_numpy(W) @ points``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

# Appendix G: u(τ) = ½ [τ³ τ² τ 1] · CATMULL_ROM · [u_{j-1} u_j u_{j+1} u_{j+2}]ᵀ
CATMULL_ROM = 0.5 * np.array(
    [[-1.0, 3.0, -3.0, 1.0], [2.0, -5.0, 4.0, -1.0], [-1.0, 0.0, 1.0, 0.0], [0.0, 2.0, 0.0, 0.0]]
)


def basis(num_points: int, times: NDArray[np.floating], spacing: float) -> NDArray[np.float64]:
    """Weights ``W`` (T, num_points) with ``u(times) = W @ points`` for points (num_points, U).

    Point ``j`` sits at time ``j * spacing``; times outside ``[0, (num_points-1)*spacing]`` are clamped.
    """
    if num_points < 1:
        raise ValueError(f"num_points must be at least 1, got {num_points}")
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    weights = np.zeros((t.size, num_points))
    if num_points == 1:
        weights[:, 0] = 1.0
        return weights
    x = np.clip(t / spacing, 0.0, num_points - 1)
    seg = np.minimum(np.floor(x).astype(np.int64), num_points - 2)  # segment j spans points j..j+1
    tau = x - seg
    powers = np.stack([tau**3, tau**2, tau, np.ones_like(tau)], axis=1)  # (T, 4)
    coeff = powers @ CATMULL_ROM  # (T, 4): weights of points j-1, j, j+1, j+2
    rows = np.arange(t.size)
    for k, offset in enumerate((-1, 0, 1, 2)):
        # duplicated end points: index -1 is point 0, index M is point M-1
        idx = np.clip(seg + offset, 0, num_points - 1)
        np.add.at(weights, (rows, idx), coeff[:, k])
    return weights


def evaluate(
    points: NDArray[np.floating], times: NDArray[np.floating], spacing: float
) -> NDArray[np.float64]:
    """Evaluate control functions: points (..., M, U) at times (T,) -> (..., T, U)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim < 2:
        raise ValueError(f"points must have shape (..., M, U), got {pts.shape}")
    w = basis(pts.shape[-2], times, spacing)
    return np.einsum("tm,...mu->...tu", w, pts)


def random_points(
    rng: np.random.Generator, shape: tuple[int, ...], low: NDArray[np.floating], high: NDArray[np.floating]
) -> NDArray[np.float64]:
    """Control points drawn uniformly over the useful range: shape (..., M, U), low/high (U,) or
    broadcasting against it (one band per run: (..., 1, U))."""
    lo = np.asarray(low, dtype=np.float64)
    hi = np.asarray(high, dtype=np.float64)
    return lo + (hi - lo) * rng.random((*shape, lo.shape[-1]))
