"""Evaluation against MuJoCo from the artifact alone: one-step errors and rollout curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.core.results import RolloutCurve
from neuroanimator.evaluation import evaluate as evaluation
from tests.helpers import Trained


def test_one_step_errors_reproduce_the_training_metrics(trained_pendulum: Trained) -> None:
    """Evaluation regenerates the same held-out set from the manifest: the same errors come out."""
    path = trained_pendulum.path
    errs = evaluation.one_step_errors(path, registry.load_physical_model(path), registry.read_manifest(path))
    metrics = trained_pendulum.result.metrics
    assert errs["one_step_rel_error"] == pytest.approx(metrics["one_step_rel_error"], rel=1e-4)
    assert errs["linear_baseline_rel_error"] == pytest.approx(metrics["linear_baseline_rel_error"], rel=1e-4)


def test_held_controls_are_the_same_functions_for_every_n() -> None:
    model = catalog.get("truck")
    u25, _ = evaluation.held_controls(model, np.random.default_rng(1), 3, 400, 25)
    u50, _ = evaluation.held_controls(model, np.random.default_rng(1), 3, 400, 50)
    assert u25.shape == (3, 16, 2) and u50.shape == (3, 8, 2)
    np.testing.assert_array_equal(u50, u25[:, ::2])


def test_rollout_curve_shape_and_start(trained_lander: Trained) -> None:
    curve = evaluation.rollout_curve(trained_lander.path, trained_lander.model, 10, trials=2, steps=300)
    assert len(curve.t) == len(curve.error) == 300 // 10 + 1
    np.testing.assert_allclose(np.diff(curve.t), 10 * trained_lander.model.dt)
    assert curve.error[0] == 0.0
    assert all(np.isfinite(curve.error)) and min(curve.error[1:]) > 0.0


def test_rollout_curve_is_deterministic(trained_pendulum: Trained) -> None:
    a = evaluation.rollout_curve(trained_pendulum.path, trained_pendulum.model, 10, trials=2, steps=100)
    b = evaluation.rollout_curve(trained_pendulum.path, trained_pendulum.model, 10, trials=2, steps=100)
    assert a == b


def test_curve_at_interpolates() -> None:
    curve = RolloutCurve(t=[0.0, 1.0, 2.0], error=[0.0, 0.4, 1.0])
    assert curve.at(0.5) == pytest.approx(0.2)
    assert curve.at(1.5) == pytest.approx(0.7)
    assert curve.at(5.0) == pytest.approx(1.0)  # past the end: the last value
    assert curve.at(-1.0) == 0.0 and curve.at(1.0) == pytest.approx(0.4)
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.1, 1.0, 50))
    e = rng.uniform(0.0, 1.0, 50)
    curve = RolloutCurve(t=t.tolist(), error=e.tolist())
    for x in rng.uniform(-1.0, t[-1] + 1.0, 200):
        assert curve.at(float(x)) == pytest.approx(float(np.interp(x, t, e)), abs=1e-12)


def test_plot_curves_writes_a_png(tmp_path: Path) -> None:
    out = tmp_path / "deep" / "plot.png"
    curves = {
        10: RolloutCurve(t=[0.0, 1.0], error=[0.0, 0.1]),
        50: RolloutCurve(t=[0.0, 1.0], error=[0.0, 0.3]),
    }
    evaluation.plot_curves(curves, "test", out)
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_a_model_with_a_driver_is_evaluated_in_its_closed_loop() -> None:
    """The runner's controller closes its loop through the committed emulator and through MuJoCo from
    the same perturbed starts: both run forward, close together over the first strides."""
    from neuroanimator.export.runtime import OnnxEmulator

    path = registry.resolve(Path(__file__).resolve().parents[1] / "artifacts", "runner")
    model = registry.load_physical_model(path, registry.read_manifest(path))
    emu = OnnxEmulator(path / registry.ONNX_FILE)
    s0, pred, phys = evaluation.driven_rollouts(model, emu, 6, trials=2, steps=6 * 20, seed=3)
    assert s0.shape == (2, model.state_size) and pred.shape == phys.shape == (2, 20, model.state_size)
    assert not np.allclose(s0[0], s0[1])  # the starts are perturbed apart
    moved = phys[:, -1, 0] - s0[:, 0]
    assert np.all(moved > 0.4)  # 0.32 s at about 2 m/s
    assert np.abs(pred[:, -1, :3] - phys[:, -1, :3]).max() < 0.1  # metres, after 20 super-steps
