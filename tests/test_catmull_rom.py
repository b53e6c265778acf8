"""Catmull-Rom control functions (thesis appendix G)."""

from __future__ import annotations

import numpy as np
import pytest

from neuroanimator.core import catmull_rom

SPACING = 0.7


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(3).normal(size=(6, 2))  # M = 6 points of U = 2 controls


def test_curve_interpolates_control_points_at_knots(points: np.ndarray) -> None:
    knots = np.arange(points.shape[0]) * SPACING
    np.testing.assert_allclose(catmull_rom.evaluate(points, knots, SPACING), points, atol=1e-12)


def test_end_points_are_reached(points: np.ndarray) -> None:
    end = (points.shape[0] - 1) * SPACING
    values = catmull_rom.evaluate(points, np.array([0.0, end]), SPACING)
    np.testing.assert_allclose(values[0], points[0], atol=1e-12)
    np.testing.assert_allclose(values[1], points[-1], atol=1e-12)


def _slope(points: np.ndarray, t: float, h: float) -> np.ndarray:
    """du/dτ (per unit of normalised time τ = t / spacing) by a one-sided difference of step h."""
    u = catmull_rom.evaluate(points, np.array([t, t + h]), SPACING)
    return (u[1] - u[0]) / (h / SPACING)


def test_slope_at_start_uses_duplicated_first_point(points: np.ndarray) -> None:
    # App. G: with p_{-1} = p_0 the tangent at the first point is (p_1 - p_{-1}) / 2 = (p_1 - p_0) / 2
    np.testing.assert_allclose(_slope(points, 0.0, 1e-7), (points[1] - points[0]) / 2, atol=1e-5)


def test_slope_at_end_uses_duplicated_last_point(points: np.ndarray) -> None:
    end = (points.shape[0] - 1) * SPACING
    h = 1e-7
    np.testing.assert_allclose(_slope(points, end - h, h), (points[-1] - points[-2]) / 2, atol=1e-5)


def test_slope_at_interior_knot_is_central_difference(points: np.ndarray) -> None:
    j = 2
    h = 1e-6
    left = _slope(points, j * SPACING - h, h)
    right = _slope(points, j * SPACING, h)
    expected = (points[j + 1] - points[j - 1]) / 2
    np.testing.assert_allclose(left, expected, atol=1e-4)  # C1: both sides share the tangent
    np.testing.assert_allclose(right, expected, atol=1e-4)


def test_basis_times_points_equals_evaluate(points: np.ndarray) -> None:
    times = np.linspace(-0.5, points.shape[0] * SPACING, 57)
    w = catmull_rom.basis(points.shape[0], times, SPACING)
    assert w.shape == (times.size, points.shape[0])
    np.testing.assert_allclose(w @ points, catmull_rom.evaluate(points, times, SPACING), atol=1e-12)


def test_curve_is_linear_in_points(points: np.ndarray) -> None:
    other = np.random.default_rng(4).normal(size=points.shape)
    times = np.linspace(0.0, 5 * SPACING, 31)
    combo = catmull_rom.evaluate(2.5 * points - 1.5 * other, times, SPACING)
    separate = 2.5 * catmull_rom.evaluate(points, times, SPACING) - 1.5 * catmull_rom.evaluate(
        other, times, SPACING
    )
    np.testing.assert_allclose(combo, separate, atol=1e-12)


def test_basis_rows_sum_to_one() -> None:
    w = catmull_rom.basis(5, np.linspace(0.0, 4.0, 41), 1.0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("num_points", [1, 2, 5])
def test_constant_points_give_constant_curve(num_points: int) -> None:
    pts = np.tile(np.array([[1.25, -3.0]]), (num_points, 1))
    values = catmull_rom.evaluate(pts, np.linspace(0.0, 4.0, 23), 0.5)
    np.testing.assert_allclose(values, np.broadcast_to(pts[0], values.shape), atol=1e-12)


def test_batched_points_evaluate_each_batch(points: np.ndarray) -> None:
    batch = np.stack([points, 2 * points + 1])
    times = np.linspace(0.0, 3.0, 9)
    out = catmull_rom.evaluate(batch, times, SPACING)
    assert out.shape == (2, times.size, points.shape[1])
    np.testing.assert_allclose(out[1], 2 * catmull_rom.evaluate(points, times, SPACING) + 1, atol=1e-12)


@pytest.mark.parametrize("spacing", [0.0, -1.0])
def test_non_positive_spacing_raises(spacing: float) -> None:
    with pytest.raises(ValueError, match="spacing"):
        catmull_rom.basis(3, np.zeros(2), spacing)


def test_no_points_raises() -> None:
    with pytest.raises(ValueError, match="num_points"):
        catmull_rom.basis(0, np.zeros(2), 1.0)


def test_points_without_control_axis_raise() -> None:
    with pytest.raises(ValueError):
        catmull_rom.evaluate(np.zeros(4), np.zeros(2), 1.0)


def test_random_points_stay_in_range() -> None:
    lo, hi = np.array([-1.0, 0.0, 5.0]), np.array([1.0, 0.5, 6.0])
    pts = catmull_rom.random_points(np.random.default_rng(0), (10, 7), lo, hi)
    assert pts.shape == (10, 7, 3)
    assert np.all(pts >= lo) and np.all(pts <= hi)
