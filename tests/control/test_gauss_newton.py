"""Levenberg-Marquardt through the emulator (``gauss_newton.py``): the residual Jacobian against
autograd and finite differences, the step on a problem where descent crawls, and a job it rescues."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from neuroanimator.control.gauss_newton import levenberg_marquardt, steps
from neuroanimator.control.job import load_problem, run_job
from neuroanimator.control.synthesis import Settings, optimize
from neuroanimator.control.validation import validate_job

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "artifacts"


def test_residual_jacobian_matches_the_gradient_and_finite_differences() -> None:
    spec = validate_job({"task": "lander-landing", "horizon": 6}, ARTIFACTS)
    problem, _, _ = load_problem(spec, ARTIFACTS)
    z = problem.initial_points() + 0.2 * np.random.default_rng(0).standard_normal(
        problem.initial_points().shape
    )
    j, grad, r, jr, (states, _) = problem.residual_jacobian(z)
    j_ref, grad_ref, states_ref, _ = problem.value_and_grad(z)
    assert j == pytest.approx(j_ref, rel=1e-6)
    np.testing.assert_allclose(grad, grad_ref, rtol=1e-4, atol=1e-6 * np.abs(grad_ref).max())
    np.testing.assert_allclose(states, states_ref, rtol=1e-6, atol=1e-6)
    assert jr.shape == (r.size, z.size)
    # no linear term in this job: ∇J = Jᵣᵀ r
    np.testing.assert_allclose(jr.T @ r, grad.ravel(), rtol=1e-3, atol=1e-4 * np.abs(grad).max())
    # one row against central differences of the residuals, in float64 through the same emulator
    with torch.no_grad():
        problem64, _, _ = load_problem(spec, ARTIFACTS)
        problem64.step.double()
        problem64.dtype = torch.float64
        problem64.s0 = problem64.s0.double()
        for name in ("_centre", "_half", "_low", "_high"):
            setattr(problem64, name, getattr(problem64, name).double())
        problem64.spline = type(problem64.spline)(
            problem64.horizon, problem64.num_points, problem64.super_dt, torch.float64
        )

        def residuals(zz: np.ndarray) -> np.ndarray:
            states64, u64 = problem64.rollout(torch.as_tensor(zz[None], dtype=torch.float64))
            return problem64.objective.residuals(states64, u64)[0].numpy()

        row = int(np.argmax(np.abs(r[problem.num_points * problem.num_controls :]))) + (
            problem.num_points * problem.num_controls
        )  # the largest state residual
        for v in np.random.default_rng(1).choice(z.size, size=6, replace=False):
            h = 1e-5
            zp, zm = z.copy().ravel(), z.copy().ravel()
            zp[v] += h
            zm[v] -= h
            fd = (residuals(zp.reshape(z.shape))[row] - residuals(zm.reshape(z.shape))[row]) / (2 * h)
            assert jr[row, v] == pytest.approx(fd, rel=2e-2, abs=1e-3 * np.abs(jr[row]).max())


def ill_conditioned() -> tuple[np.ndarray, np.ndarray]:
    """A 2-point least-squares problem with curvatures 1 and 10⁴: descent crawls along the valley."""
    a = np.array([[1.0, 0.0], [0.0, 100.0]])
    b = np.array([1.0, 2.0])
    return a, b


def rj(z: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, Any]:
    """J, ∇J, r, Jᵣ and (as what a success check reads) r of ``ill_conditioned`` at z (2, 1)."""
    a, b = ill_conditioned()
    r = a @ z.ravel() - b
    return 0.5 * float(r @ r), (a.T @ r).reshape(z.shape), r, a, r


def evaluate(zs: np.ndarray) -> np.ndarray:
    """J of a batch (B, 2, 1) of ``ill_conditioned``."""
    a, b = ill_conditioned()
    r = zs.reshape(len(zs), -1) @ a.T - b
    return 0.5 * (r * r).sum(-1)


def test_levenberg_marquardt_solves_in_a_few_steps_where_descent_crawls() -> None:
    a, _ = ill_conditioned()

    def solved(r: np.ndarray) -> bool:
        return bool(np.abs(r).max() < 1e-3)

    z0 = np.zeros((2, 1))
    lm = levenberg_marquardt(
        rj, evaluate, z0, max_iterations=10, project=lambda z: z, is_success=solved, polish_iterations=0
    )
    assert lm.success and lm.stop == "success" and lm.iterations <= 3
    np.testing.assert_allclose(lm.z.ravel(), [1.0, 0.02], atol=1e-3)
    # every Jacobian is a batch of R + 1 = 3 rollouts; every update scores one step per damping
    assert lm.rollouts == 3 * (lm.iterations + 1) + lm.iterations * len(steps(a, np.zeros(2)))

    def value_and_grad(z: np.ndarray) -> tuple[float, np.ndarray, Any]:
        j, g, r, _, _ = rj(z)
        return j, g, r

    descent = optimize(
        value_and_grad,
        z0,
        Settings(learning_rate=1.0, momentum=0.5, max_iterations=10),
        evaluate=evaluate,
        is_success=solved,
    )
    assert not descent.success  # the same budget of momentum descent does not get there


def test_levenberg_marquardt_keeps_to_the_limits_and_stops_when_no_step_helps() -> None:
    out = levenberg_marquardt(
        rj,
        evaluate,
        np.zeros((2, 1)),
        max_iterations=20,
        project=lambda z: np.clip(z, -0.5, 0.5),  # the optimum x = 1 lies beyond the limit
        is_success=lambda extra: False,
    )
    assert out.z[0, 0] == pytest.approx(0.5) and out.z[1, 0] == pytest.approx(0.02, abs=1e-4)
    assert out.stop == "stalled" and not out.success and out.iterations < 20


def test_a_lander_goal_that_descent_misses_is_reached_with_levenberg_marquardt() -> None:
    # a pad 13 m from the start, in a corner of the random-goal range: the descent alone arrives
    # tilted about 12° (the check is 10°), a compromise between tilt and position it cannot leave
    job = {"task": "lander-landing", "target_state": [-9.92, -7.83, 0, 1, 0, 0, 0, 0, 0, -0.5, 0, 0, 0]}
    without = run_job({**job, "optimizer": {"physics_rounds": 0, "gauss_newton_iterations": 0}}, ARTIFACTS)
    result = run_job({**job, "optimizer": {"physics_rounds": 0}}, ARTIFACTS)
    assert without.success_emulator is False
    assert without.gauss_newton is not None and without.gauss_newton.runs == 0
    assert result.success_emulator is True and result.success_physics is True and result.stop == "success"
    gn = result.gauss_newton
    assert gn is not None and gn.runs == 1 and gn.success and 1 <= gn.iterations <= 10
    assert result.iterations is not None and without.iterations is not None
    assert result.iterations == without.iterations + gn.iterations
    assert result.emulator_rollouts is not None and without.emulator_rollouts is not None
    assert result.emulator_rollouts == without.emulator_rollouts + gn.rollouts
    assert result.iterations_to_success is not None and result.iterations_to_success > without.iterations
