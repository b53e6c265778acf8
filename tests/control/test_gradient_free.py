"""The gradient-free baselines of thesis 6.3 (simulated annealing, Nelder-Mead, CMA-ES) on known problems."""

from __future__ import annotations

import numpy as np
import pytest

from neuroanimator.control.gradient_free import cma_es, nelder_mead, simulated_annealing


def ellipsoid(xs: np.ndarray) -> np.ndarray:
    """(B, D) -> (B,): a badly scaled quadratic with its minimum 0 at x = 0.3."""
    scale = np.logspace(0, 2, xs.shape[1])
    return (((xs - 0.3) * scale) ** 2).sum(axis=1)


# annealing with isotropic moves is slow on a badly scaled problem: it is held to a looser target
@pytest.mark.parametrize(
    ("method", "target"), [(simulated_annealing, 0.1), (nelder_mead, 1e-3), (cma_es, 1e-3)]
)
def test_reaches_the_target_and_counts_evaluations(method: object, target: float) -> None:
    calls = {"n": 0}

    def f(xs: np.ndarray) -> np.ndarray:
        calls["n"] += xs.shape[0]
        return ellipsoid(xs)

    low, high = -np.ones(6), np.ones(6)
    trace = method(f, np.full(6, -0.8), low=low, high=high, target=target, budget=20_000)  # type: ignore[operator]
    assert trace.evaluations_to_target is not None
    assert trace.best[-1] <= target
    assert trace.total_evaluations == calls["n"] == trace.evaluations[-1]
    assert trace.evaluations_to_target <= trace.total_evaluations
    assert trace.best_x is not None and np.all(trace.best_x >= low) and np.all(trace.best_x <= high)
    assert all(a >= b for a, b in zip(trace.best, trace.best[1:], strict=False))  # best never worsens


@pytest.mark.parametrize("method", [simulated_annealing, nelder_mead, cma_es])
def test_budget_caps_the_evaluations_and_bounds_hold(method: object) -> None:
    seen: list[np.ndarray] = []

    def f(xs: np.ndarray) -> np.ndarray:
        seen.append(xs.copy())
        return ((xs - 5.0) ** 2).sum(axis=1)  # minimum outside the box: the search presses on the bound

    trace = method(f, np.zeros(4), low=-np.ones(4), high=np.ones(4), budget=150)  # type: ignore[operator]
    assert trace.total_evaluations == 150 and trace.evaluations_to_target is None
    points = np.concatenate(seen)
    assert points.shape[0] == 150
    assert np.all(points <= 1.0) and np.all(points >= -1.0)
    assert trace.best[-1] < ((np.zeros(4) - 5.0) ** 2).sum()
