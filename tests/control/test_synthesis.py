"""BPTT through the emulator (thesis 5.3): gradients, the momentum optimiser, divergence,
cancellation, parity of the torch path with the artifact's ONNX graph, and the MuJoCo replay."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.control.bptt import ControlProblem, FastStep
from neuroanimator.control.job import Progress, run_job
from neuroanimator.control.replay import simulate_held
from neuroanimator.control.synthesis import Settings, optimize
from neuroanimator.control.validation import validate_job
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.goals.spec import JobSpec

ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"


def short_spec(task: str = "pendulum-swing", **kw: Any) -> JobSpec:
    return validate_job({"task": task, "horizon": 8, "points_per_step": 1.0, **kw}, ARTIFACTS)


def problem_of(spec: JobSpec, dtype: torch.dtype = torch.float32) -> ControlProblem:
    path = registry.resolve(ARTIFACTS, spec.model, spec.version)
    emu = artifacts.load_torch(path)
    if dtype == torch.float64:
        emu = emu.double()
    return ControlProblem(emu, spec, registry.read_manifest(path), dtype=dtype)


@pytest.mark.parametrize("model", ["pendulum-active", "lander", "truck"])
def test_torch_rollout_matches_the_artifacts_onnx(model: str) -> None:
    """The emulator the gradients run through is the artifact's ONNX graph, step for step."""
    path = registry.resolve(ARTIFACTS, model, substeps=50)
    physical = registry.load_physical_model(path)
    rng = np.random.default_rng(0)
    s0 = physical.initial_states(rng, 4)
    u = physical.typical_controls(rng, 4, np.arange(10.0) * 0.5)  # (4, 10, U) held per super-step
    expected = OnnxEmulator(path / "emulator.onnx").rollout(s0, u)
    step = FastStep(artifacts.load_torch(path))
    s = torch.tensor(s0, dtype=torch.float32)
    got = [s]
    with torch.no_grad():
        for k in range(u.shape[1]):
            s = step(s, torch.tensor(u[:, k], dtype=torch.float32))
            got.append(s)
    np.testing.assert_allclose(torch.stack(got, 1).numpy(), expected, rtol=1e-4, atol=2e-4)


@pytest.mark.parametrize("task", ["pendulum-swing", "lander-landing"])
def test_bptt_gradient_matches_finite_differences(task: str) -> None:
    """∇_z J by backpropagation through time equals central differences (float64 emulator)."""
    problem = problem_of(short_spec(task, optimizer={"learning_rate": 1.0}), torch.float64)
    rng = np.random.default_rng(1)
    z = problem.project(problem.initial_points() + 0.3 * rng.normal(size=problem.initial_points().shape))
    z = np.clip(z, problem.z_low + 0.05, problem.z_high - 0.05)  # away from the clamps' kinks
    _, grad, _, _ = problem.value_and_grad(z)
    h = 1e-4  # central differences: O(h²) truncation; a smaller h drowns a small component in roundoff of J
    for idx in [(0, 0), (3, 1), (problem.num_points - 1, problem.num_controls - 1)]:
        zp, zm = z.copy(), z.copy()
        zp[idx] += h
        zm[idx] -= h
        fd = (problem.evaluate(zp[None])[0] - problem.evaluate(zm[None])[0]) / (2 * h)
        assert grad[idx] == pytest.approx(fd, rel=1e-5, abs=1e-8), idx


def test_momentum_descent_on_a_tiny_emulator_lowers_the_objective(
    make_emulator: Callable[..., StructuredEmulator],
) -> None:
    """A random-weight emulator of the active pendulum (16 hidden units): plain thesis updates
    (fixed η and α, no line search) still go downhill."""
    spec = short_spec(optimizer={"learning_rate": 0.02, "momentum": 0.5, "line_search": False})
    emu = make_emulator(catalog.get("pendulum-active"))
    path = registry.resolve(ARTIFACTS, spec.model, spec.version)
    problem = ControlProblem(emu, spec, registry.read_manifest(path))
    seen: list[tuple[int, float, float, bool]] = []
    out = optimize(
        lambda z: problem.value_and_grad(z)[:3],
        problem.initial_points() + 0.1,
        Settings(learning_rate=0.02, momentum=0.5, max_iterations=15, tolerance=0.0, line_search=False),
        project=problem.project,
        on_iteration=lambda *a: seen.append(a),
    )
    assert out.stop == "max_iterations" and out.iterations == 15 and len(out.history) == 16
    assert out.history[-1] < 0.9 * out.history[0]
    assert out.objective == min(out.history)
    assert [s[0] for s in seen] == list(range(16))
    assert all(b == pytest.approx(min(out.history[: i + 1])) for i, (_, _, b, _) in enumerate(seen))


def test_momentum_reuses_the_previous_step() -> None:
    """On J = ½‖z‖² the update is δ ← −η ĝ + α δ (eqs. 5.5-5.6) with ĝ = ∇J / max|∇J|."""
    z0 = np.array([[4.0, -2.0]])
    steps: list[np.ndarray] = []

    def vg(z: np.ndarray) -> tuple[float, np.ndarray, None]:
        steps.append(z.copy())
        return float(0.5 * (z**2).sum()), z.copy(), None

    optimize(vg, z0, Settings(0.5, 0.5, 2, tolerance=0.0, line_search=False))
    d1 = -0.5 * np.array([[1.0, -0.5]])
    np.testing.assert_allclose(steps[1], z0 + d1)
    g1 = steps[1] / np.abs(steps[1]).max()
    np.testing.assert_allclose(steps[2], steps[1] - 0.5 * g1 + 0.5 * d1)


def test_divergence_keeps_the_best_finite_controller() -> None:
    calls = {"n": 0}

    def vg(z: np.ndarray) -> tuple[float, np.ndarray, str]:
        calls["n"] += 1
        j = float(0.5 * (z**2).sum())
        if calls["n"] == 5:
            return float("nan"), z.copy(), "nan"
        return j, z.copy(), f"trajectory {calls['n']}"

    out = optimize(vg, np.array([[3.0, 1.0]]), Settings(0.4, 0.5, 50, tolerance=0.0, line_search=False))
    assert out.stop == "diverged"
    assert out.reason is not None and "diverged at iteration 4: the objective is not finite" in out.reason
    assert np.isfinite(out.objective) and out.objective == min(out.history)
    assert len(out.history) == 4 and out.extra != "nan"


def test_run_job_reports_divergence_as_failed_with_the_best_finite_controller(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    original = ControlProblem.value_and_grad
    calls = {"n": 0}

    def flaky(self: ControlProblem, z: np.ndarray) -> Any:
        calls["n"] += 1
        j, g, s, u = original(self, z)
        return (j, g * np.nan, s, u) if calls["n"] == 3 else (j, g, s, u)

    monkeypatch.setattr(ControlProblem, "value_and_grad", flaky)
    single = {"starts": 1, "global_generations": 0}  # the single-start descent alone
    result = run_job({"task": "truck-parking", "horizon": 6, "optimizer": single}, ARTIFACTS)
    assert result.status == "failed"
    assert (
        result.reason is not None and "diverged at iteration 2: the gradient is not finite" in result.reason
    )
    assert result.iterations == 2 and len(result.objective_history) == 2
    assert result.controls is not None and all(v is not None for row in result.controls for v in row)
    assert result.physical is not None and len(result.physical.states) == 7


def test_should_stop_cancels_and_progress_is_reported() -> None:
    events: list[Progress] = []
    result = run_job(
        {"task": "lander-landing", "horizon": 10},
        ARTIFACTS,
        on_progress=events.append,
        should_stop=lambda: len(events) >= 3,
        threads=1,
    )
    assert result.status == "cancelled" and result.reason == "cancelled after 2 iterations"
    assert [e["iteration"] for e in events] == [0, 1, 2]
    assert {"iteration", "objective", "best_objective", "success_emulator", "elapsed_s"} <= set(events[0])
    assert events[0]["phase"] == "emulator"
    best, first = events[-1]["best_objective"], events[0]["objective"]
    assert best is not None and first is not None and best <= first
    assert result.emulated is not None
    assert len(result.emulated.states) == 11  # the best controller so far is still replayed
    assert torch.get_num_threads() >= 1


def test_replay_holds_each_value_for_its_super_step() -> None:
    model = catalog.get("truck")
    s0 = model.rest_state()[None]
    held = np.array([[[2.0, 3.0], [-1.0, 1.0], [0.5, -2.0]]])  # (1, K=3, U=2)
    states = simulate_held(model, s0, held, 50)
    s = s0
    for k in range(3):
        s = model.step_held(s, held[:, k], None, 50)
        np.testing.assert_allclose(states[0, k + 1], s[0], atol=1e-12)
    np.testing.assert_allclose(states[0, 0], s0[0])


def shape_of(rows: list[list[float | None]] | None) -> tuple[int, ...]:
    """The shape of a JSON table of numbers (missing ones as NaN); a ragged table raises."""
    assert rows is not None
    return np.array(rows, dtype=float).shape


def test_result_contract() -> None:
    result = run_job({"task": "pendulum-swing", "horizon": 6, "optimizer": {"max_iterations": 3}}, ARTIFACTS)
    k, s, m, u = 6, 6, 3, 3  # horizon 6 at 0.5 points per step: 3 points
    assert result.status == "succeeded" and result.stop in ("max_iterations", "success", "converged")
    assert result.emulated is not None and result.physical is not None
    assert shape_of(result.control_points) == (m, u)
    assert shape_of(result.controls) == (k, u)
    assert result.times == [0.5 * i for i in range(k)]
    assert shape_of(result.emulated.states) == (k + 1, s)
    assert shape_of(result.physical.states) == (k + 1, s)
    assert result.physical.states[0] == result.initial_state
    assert result.control_spacing_s == pytest.approx(2.5 / 2)
    assert np.all(np.abs(np.asarray(result.controls)) <= 2.0)  # the torque limit holds
    for value in (result.final_error_emulator, result.final_error_physics, result.wall_s):
        assert isinstance(value, float)
    assert isinstance(result.success_emulator, bool) and isinstance(result.success_physics, bool)
    assert result.state_labels is not None and result.state_labels[0] == "angles.j0"
    assert result.iterations == len(result.objective_history) - 1
    assert result.spec is not None and result.spec.task == "pendulum-swing"
    # the outcome is JSON as stored: the same object read back
    assert type(result).model_validate_json(result.model_dump_json()) == result


def test_physics_correction_makes_the_emulator_replay_the_physical_trajectory() -> None:
    spec = short_spec("lander-landing")
    problem = problem_of(spec)
    path = registry.resolve(ARTIFACTS, spec.model, spec.version)
    physical = registry.load_physical_model(path)
    z = problem.project(problem.initial_points() + 0.2)
    _, held = problem.trajectory(z)
    phys = simulate_held(physical, np.asarray(spec.initial_state)[None], held[None], spec.substeps)[0]
    plain, _ = problem.trajectory(z)
    assert np.abs(plain - phys).max() > 1e-3  # the emulator alone is not exact
    problem.set_correction(phys, held)
    corrected, _ = problem.trajectory(z)
    np.testing.assert_allclose(corrected, phys, atol=2e-4)
    problem.set_correction(None)
    np.testing.assert_allclose(problem.trajectory(z)[0], plain)


def test_result_reports_a_heading_wrapped_as_the_emulator_service_does() -> None:
    """The truck starts turning left at a heading of 3.05 rad: its trajectories cross π and are
    reported wrapped to [-π, π), as every step of the emulator service reports a heading."""
    result = run_job(
        {
            "task": "truck-parking",
            "horizon": 6,
            "initial_state": [0, 0, 3.05, 3.0, 0, 1.0],
            "target_state": [-10, 3, -2.5, 0, 0, 0],
            "optimizer": {"max_iterations": 2},
        },
        ARTIFACTS,
    )
    assert result.emulated is not None and result.physical is not None
    for trajectory in (result.emulated, result.physical):
        heading = np.asarray(trajectory.states, dtype=float)[:, 2]
        assert np.all((heading >= -np.pi) & (heading < np.pi)), heading
        assert heading[0] == pytest.approx(3.05, abs=1e-6) and heading[1] < 0  # turned past π
