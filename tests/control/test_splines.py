"""Catmull-Rom controls in torch (App. G): the same curve as the numpy basis, held per super-step."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuroanimator.control.splines import ControlSpline, spacing_of
from neuroanimator.core import catmull_rom


@pytest.fixture
def points() -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(0).normal(size=(20, 3)))  # M = 20 points, U = 3


def test_held_values_equal_the_numpy_curve_at_super_step_starts(points: torch.Tensor) -> None:
    spline = ControlSpline(horizon=40, num_points=20, super_dt=0.5, dtype=torch.float64)
    held = spline.held(points).numpy()
    expected = catmull_rom.evaluate(points.numpy(), spline.times(), spline.spacing)
    np.testing.assert_allclose(held, expected, atol=1e-12)
    assert held.shape == (40, 3)


def test_spacing_spreads_points_over_the_super_step_starts() -> None:
    # 20 points over 40 super-steps of 0.5 s: first at 0 s, last at the last super-step's start 19.5 s
    assert spacing_of(40, 20, 0.5) == pytest.approx(19.5 / 19)
    assert spacing_of(40, 40, 0.5) == pytest.approx(0.5)  # one point per super-step: Δt apart
    assert spacing_of(1, 1, 0.5) == 0.5


def test_one_point_per_super_step_holds_each_point(points: torch.Tensor) -> None:
    spline = ControlSpline(horizon=20, num_points=20, super_dt=0.5, dtype=torch.float64)
    np.testing.assert_allclose(spline.held(points).numpy(), points.numpy(), atol=1e-12)


def test_spline_interpolates_its_points_and_ends(points: torch.Tensor) -> None:
    spline = ControlSpline(horizon=39, num_points=20, super_dt=0.5, dtype=torch.float64)
    held = spline.held(points).numpy()
    # with 39 super-steps the points fall on every second super-step start exactly
    np.testing.assert_allclose(held[::2], points.numpy(), atol=1e-12)
    np.testing.assert_allclose(held[0], points[0].numpy(), atol=1e-12)
    np.testing.assert_allclose(held[-1], points[-1].numpy(), atol=1e-12)


def test_end_points_are_duplicated() -> None:
    """The first segment uses u^{j-1} = u^j = p_0 and the last u^{M+1} = u^M (App. G): compare with the
    segment formula evaluated on the duplicated points written out."""
    p = np.array([[1.0], [3.0], [2.0], [5.0]])
    tau = 0.3
    value = catmull_rom.evaluate(p, np.array([tau]), 1.0)[0, 0]
    seg = np.array([p[0, 0], p[0, 0], p[1, 0], p[2, 0]])  # u^{j-1} = u^j = p0 at the start
    expected = np.array([tau**3, tau**2, tau, 1.0]) @ catmull_rom.CATMULL_ROM @ seg
    assert value == pytest.approx(expected, abs=1e-12)
    # and at the far end: u^{M+1} = u^M
    value_end = catmull_rom.evaluate(p, np.array([2.0 + tau]), 1.0)[0, 0]
    seg_end = np.array([p[1, 0], p[2, 0], p[3, 0], p[3, 0]])
    expected_end = np.array([tau**3, tau**2, tau, 1.0]) @ catmull_rom.CATMULL_ROM @ seg_end
    assert value_end == pytest.approx(expected_end, abs=1e-12)


def test_held_values_are_differentiable_in_the_points(points: torch.Tensor) -> None:
    spline = ControlSpline(horizon=40, num_points=20, super_dt=0.5, dtype=torch.float64)
    pts = points.clone().requires_grad_(True)
    spline.held(pts).sum().backward()
    assert pts.grad is not None
    # d(sum of held)/d(points) is the column sums of the constant basis
    expected = spline.basis.sum(dim=0)[:, None].expand(-1, 3)
    torch.testing.assert_close(pts.grad, expected)


def test_batched_points_and_bad_shapes(points: torch.Tensor) -> None:
    spline = ControlSpline(horizon=10, num_points=20, super_dt=0.5, dtype=torch.float64)
    batch = torch.stack([points, 2 * points])
    held = spline.held(batch)
    assert held.shape == (2, 10, 3)
    torch.testing.assert_close(held[1], 2 * held[0])
    with pytest.raises(ValueError, match="points must have 20 rows"):
        spline.held(points[:5])
