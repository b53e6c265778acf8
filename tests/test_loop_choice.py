"""The kept epoch weighed by a closed loop (``neuroanimator.training.loop_choice``): the candidates within the
tolerance of the best validation loss, the one with the lowest loop error kept, its weights restored;
the runner's own loop check on the committed emulator."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.catalog.runner import data as runner_data
from neuroanimator.training import train as training
from neuroanimator.training.loop_choice import LoopChoice, Step, loop_choice, numpy_step
from neuroanimator.training.train import TrainConfig
from tests.helpers import regression_problem, truck_emulator

ROOT = Path(__file__).resolve().parents[1]


def _output_size(step: Step) -> float:
    """A loop check that reads the emulator: the size of its step from fixed states and controls."""
    gen = np.random.default_rng(3)
    s, u = gen.normal(size=(8, 6)), gen.normal(size=(8, 2))
    return float(np.abs(step(s, u, np.zeros((8, 0)))).mean())


def test_the_candidate_with_the_lowest_loop_error_within_the_tolerance_is_kept() -> None:
    """Scripted loop errors over five epochs: epoch 1 has the lowest loop but a validation loss beyond
    10 % of the best, so epoch 3 (within it, the lowest loop there) is kept and its weights restored."""
    emu = truck_emulator()
    vals = [1.0, 0.5, 0.3, 0.32, 0.30]  # best 0.3: within 10 % are epochs 2, 3, 4
    loops = iter([5.0, 0.1, 2.0, 0.7, 1.5])
    choice = LoopChoice(lambda step: next(loops), tolerance=0.1)
    weights = []
    best = math.inf
    for epoch, val in enumerate(vals):
        with torch.no_grad():
            for p in emu.parameters():
                p.add_(0.01)
        weights.append([p.detach().clone() for p in emu.parameters()])
        best = min(best, val)
        choice.offer(epoch, val, best, emu, emu)
    assert choice.restore(emu) == 3
    for p, kept in zip(emu.parameters(), weights[3], strict=True):
        assert torch.equal(p, kept)
    m = choice.metrics()
    assert m["loop_kept_epoch"] == 3 and m["loop_error_kept"] == pytest.approx(0.7)
    assert [row[0] for row in m["loop_curve"]] == [0, 1, 2, 3, 4]


def test_with_no_tolerance_the_kept_epoch_is_one_of_the_lowest_validation_loss() -> None:
    emu = truck_emulator()
    loops = iter([0.1, 3.0, 2.0])
    choice = LoopChoice(lambda step: next(loops), tolerance=0.0)
    for epoch, (val, best) in enumerate([(1.0, 1.0), (0.4, 0.4), (0.5, 0.4)]):
        choice.offer(epoch, val, best, emu, emu)
    assert choice.restore(emu) == 1


def test_train_core_keeps_the_epoch_the_choice_names_and_records_every_epoch() -> None:
    """Through ``train_core``: one curve row per epoch; the kept epoch within the tolerance of the
    lowest validation loss and the lowest loop error among those; the emulator left with its weights
    (its loop check measures the kept error again)."""
    x, y, xv, yv = regression_problem()
    emu = truck_emulator()
    choice = LoopChoice(_output_size, tolerance=0.2)
    cfg = TrainConfig(lr=1e-2, batch_size=64, max_epochs=12, threads=1, progress=False)
    training.train_core(emu, x, y, xv, yv, cfg, choice)
    curve = choice.curve
    assert [row[0] for row in curve] == list(range(len(curve))) and len(curve) == 12
    best_val = min(v for _, v, _ in curve)
    within = [(e, loop) for e, v, loop in curve if v <= 1.2 * best_val]
    kept = choice.metrics()["loop_kept_epoch"]
    assert kept == min(within, key=lambda r: r[1])[0]
    assert _output_size(numpy_step(emu.eval())) == pytest.approx(
        choice.metrics()["loop_error_kept"], rel=1e-5
    )


def test_a_loop_tolerance_needs_a_model_with_a_loop_check() -> None:
    pendulum = catalog.get("pendulum-active")
    assert loop_choice(pendulum, TrainConfig()) is None  # off by default
    with pytest.raises(ValueError, match="no loop check"):
        loop_choice(pendulum, TrainConfig(loop_tolerance=0.05))
    with pytest.raises(ValueError, match="at least 0"):
        loop_choice(catalog.get("runner"), TrainConfig(loop_tolerance=-0.1))


def test_the_runner_loop_check_on_the_committed_emulator_is_within_half_a_metre() -> None:
    """The runner's loop check (its controller closed through the committed emulator from the running
    starts at three trained speeds for 5 s) measures metres from MuJoCo's runs: finite, and under the
    0.5 m an emulated run must keep at 5 s."""
    path = registry.resolve(ROOT / "artifacts", "runner")
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    check = runner_data.loop_check(model, manifest.substeps)
    error = check(numpy_step(artifacts.load_torch(path).eval()))
    assert math.isfinite(error) and 0.0 < error < 0.5


def test_neuro_train_with_a_loop_tolerance_for_a_model_without_a_loop_check_fails_at_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A clear error before any data are simulated, and nothing written."""
    from neuroanimator.cli import main

    rc = main(["train", "pendulum-active", "--loop-tolerance", "0.05", "--out", str(tmp_path), "--quiet"])
    assert rc == 2
    assert "no loop check" in caplog.text
    assert not any(tmp_path.iterdir())
