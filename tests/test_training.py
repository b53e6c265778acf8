"""Training: the whole recipe end to end, presets, optimisers and divergence."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import store as artifacts
from neuroanimator.sim import sampling
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainConfig, TrainingDiverged
from tests.helpers import regression_problem, truck_emulator


@pytest.fixture(scope="module")
def pendulum_result() -> training.TrainResult:
    cfg = TrainConfig(
        substeps=50,
        examples=3000,
        test_examples=500,
        hidden=(32,),
        max_epochs=40,
        lr=1e-2,
        threads=1,
        progress=False,
    )
    return training.train(catalog.get("pendulum-active"), cfg)


def test_trained_emulator_beats_the_linear_baseline(pendulum_result: training.TrainResult) -> None:
    m = pendulum_result.metrics
    assert math.isfinite(m["one_step_rel_error"])
    assert m["one_step_rel_error"] < m["linear_baseline_rel_error"]
    assert m["one_step_rel_error"] < 0.1  # explains most of the variance of the state change


def test_metrics_describe_the_run(pendulum_result: training.TrainResult) -> None:
    m = pendulum_result.metrics
    assert m["examples"] == 3000
    assert m["test_examples"] == 500
    assert m["weights"] == sum(p.numel() for p in pendulum_result.emulator.parameters())
    assert len(pendulum_result.data_sha256) == 64
    assert pendulum_result.linear.shape == (pendulum_result.emulator.input_size + 1, 6)


def test_trained_emulator_predicts_fresh_physics(pendulum_result: training.TrainResult) -> None:
    """One super-step from new states: the emulator is closer to MuJoCo than 'nothing moves' is."""
    model = catalog.get("pendulum-active")
    rng = np.random.default_rng(77)
    s = model.initial_states(rng, 200)
    u = model.typical_controls(rng, 200, np.zeros(1))[:, 0]
    truth = model.step_held(s, u, None, 50)
    with torch.no_grad():
        pred = (
            pendulum_result.emulator(torch.from_numpy(s).float(), torch.from_numpy(u).float())
            .double()
            .numpy()
        )
    assert np.mean((pred - truth) ** 2) < 0.2 * np.mean((s - truth) ** 2)


def test_thesis_preset_is_one_sigmoid_layer_of_thesis_width() -> None:
    cfg = TrainConfig(preset="thesis", thesis_hidden=20, hidden=(64, 64), activation="tanh").resolved()
    assert cfg.hidden == (20,)
    assert cfg.activation == "sigmoid"
    emu = training.build_emulator(catalog.get("pendulum-active"), cfg)
    layers = [type(m).__name__ for m in emu.core]
    assert layers == ["Linear", "Sigmoid", "Linear"]
    assert emu.core[0].out_features == 20


def test_thesis_preset_without_width_uses_a_default() -> None:
    cfg = TrainConfig(preset="thesis").resolved()
    assert len(cfg.hidden) == 1 and cfg.hidden[0] > 0
    assert cfg.activation == "sigmoid"


def test_default_preset_is_left_alone() -> None:
    cfg = TrainConfig(hidden=(7, 5), activation="relu")
    assert cfg.resolved() == cfg


def test_unknown_preset_raises() -> None:
    with pytest.raises(ValueError, match="preset"):
        TrainConfig(preset="huge").resolved()


def test_to_dict_is_plain_data() -> None:
    d = TrainConfig(hidden=(3, 4)).to_dict()
    assert d["hidden"] == [3, 4]
    assert d["optimizer"] == "adam"


def _emulator() -> training.StructuredEmulator:
    emu = truck_emulator()
    assert emu.input_size == 5 and emu.layout.size == 6
    return emu


@pytest.mark.parametrize("optimizer", ["sgd", "adam"])
def test_optimizers_reduce_the_validation_loss(optimizer: str) -> None:
    x, y, xv, yv = regression_problem()
    emu = _emulator()
    with torch.no_grad():
        before = float(torch.mean((emu.network(xv) - yv) ** 2))
    cfg = TrainConfig(
        optimizer=optimizer,
        lr=0.05 if optimizer == "sgd" else 1e-2,
        batch_size=64,
        max_epochs=20,
        threads=1,
        progress=False,
    )
    training.train_core(emu, x, y, xv, yv, cfg)
    with torch.no_grad():
        after = float(torch.mean((emu.network(xv) - yv) ** 2))
    assert after < 0.5 * before


def test_cosine_schedule_does_not_stop_before_it_has_annealed_halfway() -> None:
    """With validation targets that nothing predicts and a patience of one epoch, the plateau schedule
    stops within a few epochs; the cosine one goes on until its learning rate has come down halfway
    (the learning rate it returns says where it stopped)."""
    x, y, xv, _ = regression_problem()
    noise = torch.randn(xv.shape[0], y.shape[1], generator=torch.Generator().manual_seed(1))
    base = TrainConfig(lr=1e-2, batch_size=64, max_epochs=20, patience=1, threads=1, progress=False)
    plateau_lr = training.train_core(
        _emulator(), x, y, xv, noise, dataclasses.replace(base, schedule="plateau")
    )
    cosine_lr = training.train_core(
        _emulator(), x, y, xv, noise, dataclasses.replace(base, schedule="cosine")
    )
    assert plateau_lr == pytest.approx(1e-2)  # stopped before the plateau schedule lowered it
    assert cosine_lr <= 0.51 * 1e-2


def test_bad_optimizer_name_raises() -> None:
    x, y, xv, yv = regression_problem()
    emu = _emulator()
    with pytest.raises(ValueError, match="optimizer"):
        training.train_core(emu, x, y, xv, yv, TrainConfig(optimizer="lbfgs", progress=False))


def test_huge_learning_rate_raises_training_diverged() -> None:
    x, y, xv, yv = regression_problem()
    emu = _emulator()
    with pytest.raises(TrainingDiverged, match="learning rate"):
        training.train_core(
            emu, x, y, xv, yv, TrainConfig(optimizer="sgd", lr=1e6, max_epochs=20, progress=False)
        )


def test_diverged_training_writes_no_artifact(tmp_path: Path) -> None:
    model = catalog.get("pendulum-active")
    cfg = TrainConfig(
        substeps=10,
        examples=300,
        test_examples=100,
        hidden=(16,),
        max_epochs=20,
        optimizer="sgd",
        lr=1e6,
        threads=1,
        progress=False,
    )
    root = tmp_path / "registry"
    with pytest.raises(TrainingDiverged):
        artifacts.save(root, model, training.train(model, cfg))
    assert not root.exists()


def test_relative_error_of_mean_prediction_is_one() -> None:
    y = torch.randn(50, 3)
    assert training.relative_error(y.mean(dim=0).expand_as(y), y) == pytest.approx(1.0, rel=1e-5)
    assert training.relative_error(y, y) == 0.0


def test_linear_baseline_recovers_an_affine_map() -> None:
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(200, 4, generator=gen)
    w, b = torch.randn(4, 2, generator=gen), torch.randn(2, generator=gen)
    y = x @ w + b
    fit = training.fit_linear(x, y)
    np.testing.assert_allclose(fit[:4], w.numpy(), atol=1e-5)
    np.testing.assert_allclose(fit[4], b.numpy(), atol=1e-5)
    torch.testing.assert_close(training.apply_linear(fit, x), y, atol=1e-4, rtol=1e-4)


def test_frame_config_of_catalog_models() -> None:
    lander = training.frame_config(catalog.get("lander"))
    assert lander.rotate and lander.translate == (True, True, True)
    truck = training.frame_config(catalog.get("truck"))
    assert truck.rotate and truck.translate == (True, True)
    pend = training.frame_config(catalog.get("pendulum-force"))
    assert not pend.rotate and pend.force_pairs == ()


def test_training_over_rollouts_lowers_the_rollout_loss() -> None:
    """From a one-step solution, the rollout phase lowers the error of emulated rollouts."""
    model = catalog.get("pendulum-active")
    cfg = TrainConfig(
        substeps=10, hidden=(16,), examples=600, max_epochs=15, rollout_steps=0, progress=False, threads=1
    )
    result = training.train(model, cfg)
    seqs = sampling.generate_sequences(model, 10, 96, 6, seed=3, progress=False)
    out = training.train_over_rollouts(
        result.emulator, seqs, TrainConfig(substeps=10, rollout_seconds=5.0, threads=1, progress=False)
    )
    assert out["rollout_loss_after"] < out["rollout_loss_before"]
    assert out["rollout_epochs"] >= 1


def test_training_over_rollouts_keeps_the_one_step_accuracy() -> None:
    """Given the one-step data, the rollout phase keeps a state only where the two losses, each
    relative to its start, sum lower than they started: the one-step error cannot double."""
    model = catalog.get("pendulum-active")
    cfg = TrainConfig(
        substeps=10, hidden=(16,), examples=600, max_epochs=15, rollout_steps=0, progress=False, threads=1
    )
    emu = training.train(model, cfg).emulator
    s, u, f, nxt = training.to_tensors(sampling.generate(model, 10, 600, 5, progress=False))
    with torch.no_grad():
        x, y = emu.network_inputs(s, u, f), emu.network_targets(s, nxt)

    def val_mse() -> float:
        with torch.no_grad():
            return float(((emu.network(x[:100]) - y[:100]) ** 2).mean())

    step_before = val_mse()
    seqs = sampling.generate_sequences(model, 10, 96, 6, seed=3, progress=False)
    out = training.train_over_rollouts(
        emu,
        seqs,
        TrainConfig(substeps=10, rollout_seconds=5.0, threads=1, progress=False),
        one_step=(x[100:], y[100:], x[:100], y[:100]),
    )
    step_after = val_mse()
    relative = out["rollout_loss_after"] / out["rollout_loss_before"] + step_after / step_before
    assert relative <= 2.0 + 1e-9 and step_after < 2.0 * step_before
    assert out["rollout_epochs"] >= 1


def test_the_time_budget_trims_the_rollout_phase_first() -> None:
    """285 s in all: after quick sampling both phases keep their caps; after slow sampling (the
    swimmer's 100 s) the rollout phase gets what is left, down to a third of its cap; the one-step
    phase is cut only when sampling leaves it less than its cap, never below a third of it."""
    cfg = TrainConfig()  # max_seconds 150, rollout_seconds 60, time_budget 285
    assert training.one_step_seconds(cfg, 30.0) == 150.0
    assert training.rollout_seconds(cfg, 30.0 + 150.0) == 60.0
    assert training.one_step_seconds(cfg, 100.0) == 150.0
    assert training.rollout_seconds(cfg, 100.0 + 150.0) == pytest.approx(25.0)
    assert training.rollout_seconds(cfg, 270.0) == pytest.approx(20.0)  # a third of 60, not less
    assert training.one_step_seconds(cfg, 150.0) == pytest.approx(285 - 150 - 20 - 10)
    assert training.one_step_seconds(cfg, 260.0) == pytest.approx(50.0)  # a third of 150, not less
    no_rollouts = TrainConfig(rollout_steps=0)
    assert training.one_step_seconds(no_rollouts, 150.0) == pytest.approx(285 - 150 - 10)
    unbudgeted = TrainConfig(time_budget=None)
    assert training.one_step_seconds(unbudgeted, 1e4) == 150.0
    assert training.rollout_seconds(unbudgeted, 1e4) == 60.0


def test_a_larger_time_budget_buys_more_data_and_longer_phases() -> None:
    """A budget above the default is spent, not only allowed: 900 s (3.16× the default) multiplies the
    examples per weight and both phases' caps by 3.16, and the phases still keep within it; a budget
    under the default, or none, keeps the caps and the examples as they are."""
    big = TrainConfig(time_budget=900.0)
    scale = 900.0 / 285.0
    assert big.budget_scale() == pytest.approx(scale)
    assert training.one_step_seconds(big, 60.0) == pytest.approx(150.0 * scale)
    assert training.rollout_seconds(big, 60.0 + 150.0 * scale) == pytest.approx(60.0 * scale)
    # after slow sampling the one-step phase is cut so that the rollout phase keeps a third of its cap
    assert training.one_step_seconds(big, 400.0) == pytest.approx(900 - 400 - 20 * scale - 10)
    model = catalog.get("pendulum-passive")
    plan = training.examples_plan(model, big, 1000, 0.0)
    assert plan.examples == math.ceil(10.0 * scale * 1000)
    assert training.examples_plan(model, TrainConfig(), 1000, 0.0).examples == 10_000
    assert TrainConfig(time_budget=120.0).budget_scale() == 1.0
    assert TrainConfig(time_budget=None).budget_scale() == 1.0


def test_time_spent_before_the_training_comes_off_its_budget(caplog: pytest.LogCaptureFixture) -> None:
    """`neuro train` spends time before the training (loading, the contact check, super-step probes:
    dm_control's humanoid took 433 s against the 285 s budget when they were not counted); the
    training counts it against the budget, and its manifest keeps the budget as given."""
    cfg = TrainConfig(
        substeps=10,
        hidden=(8,),
        examples=200,
        test_examples=100,
        max_epochs=2,
        rollout_steps=0,
        progress=False,
    )
    with caplog.at_level("INFO", logger="neuroanimator.training.train"):
        result = training.train(catalog.get("pendulum-passive"), cfg, spent=200.0)
    # 285 s less the 200 spent and the 10 kept for what follows: 75 s for the one-step phase
    assert any("the one-step phase gets 75 s" in r.getMessage() for r in caplog.records), caplog.text
    assert result.config.time_budget == 285.0


def test_sampling_keeps_to_its_share_of_the_time_budget() -> None:
    """Without a count from the user, the examples are what the budget's sampling share (less what set-up
    spent, down to its floor) simulates; a count the user set, or no budget, keeps every example."""
    from neuroanimator.training.train import SAMPLING_FLOOR, SAMPLING_SHARE, sampling_plan

    model = catalog.get("lander")
    rate = model.measure_step_rate()
    # a share of 10 M physical steps: 17 batches of 256 runs of 45 × 50 steps (a batch is the grain)
    budget = 10_000_000 / rate / SAMPLING_SHARE
    cfg = TrainConfig(substeps=50, time_budget=budget)
    fresh = sampling_plan(model, cfg, 400_000, elapsed=0.0)
    late = sampling_plan(model, cfg, 400_000, elapsed=0.15 * budget)
    floor = sampling_plan(model, cfg, 400_000, elapsed=budget)
    assert fresh.reason and 2000 < floor.examples < late.examples < fresh.examples < 400_000

    def steps(plan: sampling.SamplingPlan) -> float:
        return sampling.sampling_steps(model, 50, plan.examples, plan.test_examples)

    assert steps(floor) / steps(fresh) == pytest.approx(SAMPLING_FLOOR / SAMPLING_SHARE, rel=0.15)
    given = sampling_plan(model, TrainConfig(substeps=50, examples=400_000, time_budget=budget), 400_000, 0.0)
    unbounded = sampling_plan(model, TrainConfig(substeps=50, time_budget=None), 400_000, 0.0)
    assert given.examples == unbounded.examples == 400_000 and given.reason is None
