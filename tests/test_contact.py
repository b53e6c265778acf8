"""Contacts and world-axis controls: how the trainer sees contacts and limits in typical motion, and a
ball on a floor pushed along world axes (tests/data/pushed_ball.xml)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.cli import main
from neuroanimator.core import quaternion
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.evaluation import evaluate as evaluation
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.super_step import (
    ACCEPT_ERROR,
    ModelOutOfReach,
    check_useful,
    constrained_defaults,
    constraint_activity,
    pick,
    probe_config,
    user_defaults,
)
from tests.helpers import ROOT
from tests.test_body_frame import _move, _predict, _sphere_of_attitudes

MakeEmulator = Callable[..., StructuredEmulator]
BALL = ROOT / "tests" / "data" / "pushed_ball.xml"
ARTIFACTS = ROOT / "artifacts"


def _ball() -> PhysicalModel:
    return load_mjcf(BALL, substeps=10)


def test_the_ball_touches_the_ground_and_nothing_limits_it() -> None:
    activity = constraint_activity(_ball())
    assert activity.contact > 0.5  # it spends most of its time on the floor
    assert activity.limit == 0


def test_a_pendulum_has_neither_contact_nor_limits() -> None:
    activity = constraint_activity(catalog.get("pendulum-active"))
    assert not activity.any


def test_probes_are_short_and_keep_the_users_choices() -> None:
    cfg = TrainConfig(hidden=(32,), examples=50_000, max_seconds=150.0, seed=4)
    probe = probe_config(cfg, 25)
    assert (probe.substeps, probe.hidden, probe.seed) == (25, (32,), 4)
    assert probe.examples == 6000 and probe.max_epochs == 40 and probe.rollout_steps == 0


def test_world_axis_pushes_turn_with_the_frame(make_emulator: MakeEmulator) -> None:
    """The pushes act along world x and y (``refsite`` on the world). The emulator turns them
    into the body frame with the world vectors, so turning the whole scene, pushes included, about
    gravity turns the prediction the same way: the rotation stays a symmetry."""
    model = _ball()
    assert model.world_control_vectors == ((0, 1),) and model.frame.rotate
    emu = make_emulator(model, seed=2).double()
    s, u = _sphere_of_attitudes(model, 32, 5)
    s[:, 2] = 0.2  # near the floor (height is no symmetry)
    u = np.random.default_rng(6).uniform(-2, 2, (32, 2))
    for angle in (0.4, 2.5):
        q_z = quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), angle)
        c, sn = np.cos(angle), np.sin(angle)
        u_turned = u @ np.array([[c, sn], [-sn, c]])  # rows (R u)ᵀ
        got = _predict(emu, _move(model, s, q_z, np.array([3.0, -1.0, 0.0])), u_turned)
        expected = _move(model, _predict(emu, s, u), q_z, np.array([3.0, -1.0, 0.0]))
        np.testing.assert_allclose(got, expected, atol=1e-9 * max(1.0, np.abs(expected).max()))
        # and the pushes must be turned: left as they were, the prediction differs
        assert (
            np.abs(
                _predict(emu, _move(model, s, q_z, np.zeros(3)), u)
                - _move(model, _predict(emu, s, u), q_z, np.zeros(3))
            ).max()
            > 1e-4
        )


def test_a_world_axis_control_without_its_partner_breaks_the_rotation(tmp_path: Path) -> None:
    xml = BALL.read_text().replace(
        '<general name="push_y" site="centre" refsite="world" gear="0 1 0 0 0 0" ctrlrange="-2 2"/>', ""
    )
    path = tmp_path / "pushed_along_x.xml"
    path.write_text(xml)
    model = load_mjcf(path, substeps=10)
    assert model.world_control_vectors is None and not model.frame.rotate


def test_a_model_in_contact_gets_a_wider_network_of_units_that_do_not_saturate() -> None:
    activity = constraint_activity(catalog.get("ball"))
    assert activity.contact > 0.5
    cfg, why = constrained_defaults(TrainConfig(), activity, hidden_given=False, activation_given=False)
    assert (cfg.hidden, cfg.activation, cfg.schedule) == ((128, 128), "silu", "cosine")
    assert why is not None and "128×128 silu" in why and "contacts in" in why
    # what the user chose stays
    mine, _ = constrained_defaults(
        TrainConfig(hidden=(32,)), activity, hidden_given=True, activation_given=False
    )
    assert (mine.hidden, mine.activation) == ((32,), "silu")
    kept, why_kept = constrained_defaults(
        TrainConfig(schedule="plateau"),
        activity,
        hidden_given=False,
        activation_given=False,
        schedule_given=True,
    )
    assert kept.schedule == "plateau" and why_kept is not None and "plateau schedule" in why_kept
    both = TrainConfig(hidden=(32,), activation="tanh")
    assert constrained_defaults(both, activity, hidden_given=True, activation_given=True) == (both, None)
    # a smooth model keeps the defaults
    smooth = constraint_activity(catalog.get("pendulum-active"))
    assert constrained_defaults(TrainConfig(), smooth, hidden_given=False, activation_given=False) == (
        TrainConfig(),
        None,
    )


def test_a_model_of_ones_own_gets_the_deeper_network_unless_the_user_chose() -> None:
    smooth = constraint_activity(catalog.get("pendulum-active"))
    cfg, why = user_defaults(TrainConfig(), smooth, hidden_given=False, activation_given=False)
    assert (cfg.hidden, cfg.activation, cfg.schedule, cfg.batch_size) == (
        (128, 128, 128),
        "silu",
        "cosine",
        512,
    )
    assert why is not None and "a model of one's own" in why and "limits engaged in 0%" in why
    mine, why_mine = user_defaults(
        TrainConfig(hidden=(32,), batch_size=64),
        smooth,
        hidden_given=True,
        activation_given=False,
        batch_given=True,
    )
    assert (mine.hidden, mine.batch_size, mine.activation) == ((32,), 64, "silu") and "32 silu" in str(
        why_mine
    )
    chosen = TrainConfig(hidden=(32,), activation="tanh", schedule="plateau", batch_size=64)
    assert user_defaults(
        chosen, smooth, hidden_given=True, activation_given=True, schedule_given=True, batch_given=True
    ) == (chosen, None)


def test_neuro_train_says_why_a_model_in_contact_gets_its_network(tmp_path: Path) -> None:
    out = tmp_path / "out"
    argv = ["train", "--mjcf", str(BALL), "--substeps", "10", "--examples", "300", "--epochs", "1"]
    assert main([*argv, "--rollout-steps", "0", "--force", "--out", str(out), "--quiet"]) == 0
    manifest = registry.read_manifest(registry.resolve(out, "ball"))
    assert manifest.train_config.hidden == (128, 128, 128) and manifest.train_config.activation == "silu"
    assert manifest.train_config.batch_size == 512
    extra = manifest.metrics.model_extra or {}
    assert extra["network_reason"].startswith(
        "128×128×128 silu units, cosine schedule, batches of 512: a model"
    )
    assert "contacts in" in extra["network_reason"]
    assert extra["contact_fraction"] > 0.5 and extra["limit_fraction"] == 0


def test_the_catalog_ball_is_emulated_within_the_bar_on_held_out_contact_data() -> None:
    """The committed ball emulator (n = 10, 0.02 s) on the trainer's held-out typical motion (4,000
    examples: landing, rolling and sliding on the floor, pushed along world axes). A third of the
    error is in the 1% of landings, so a smaller sample swings by ±20%."""
    model = catalog.get("ball")
    assert model.frame.translate == (True, True, False)  # its height above the floor is no symmetry
    assert model.world_control_vectors == ((0, 1),) and model.frame.rotate
    path = registry.resolve(ARTIFACTS, "ball")
    manifest = registry.read_manifest(path)
    assert manifest.substeps == 10
    errors = evaluation.one_step_errors(path, model, manifest)
    assert errors["one_step_rel_error"] <= 0.01
    assert errors["linear_baseline_rel_error"] >= 5 * errors["one_step_rel_error"]


def test_an_emulator_is_refused_off_the_bar_and_kept_when_exact() -> None:
    """Refused: far off the target, or hardly better than the linear fit; kept: any emulator under the
    absolute floor of 1e-3, such as an exact one of a linear system, which the linear fit also matches
    (dm_control's LQR: 9e-15 against 5e-15)."""
    check_useful("m", 50, 0.004, 0.3)
    with pytest.raises(
        ModelOutOfReach, match=r"m n=50: one-step relative error 0.06 \(linear baseline 0.3\)"
    ):
        check_useful("m", 50, 0.06, 0.3)
    with pytest.raises(ModelOutOfReach, match="≥ 2× below linear") as refused:
        check_useful("m", 50, 0.004, 0.006)
    check_useful("pendulum", 50, 1.07e-5, 1.78e-5)  # under the absolute floor: kept whatever the ratio
    check_useful("m", 50, 1e-3, 1.1e-3)  # the floor's exact edge
    with pytest.raises(ModelOutOfReach):
        check_useful("m", 50, 1.001e-3, 1.1e-3)
    assert "time budget" not in str(refused.value)
    with pytest.raises(ModelOutOfReach, match="The time budget cut its data: sampling cut to 10 examples"):
        check_useful("m", 50, 0.004, 0.006, "sampling cut to 10 examples")
    with pytest.raises(ModelOutOfReach):
        check_useful("m", 50, float("nan"), 0.3)
    check_useful("lqr", 50, 8.96e-15, 5.23e-15)
    check_useful("lqr", 50, ACCEPT_ERROR, ACCEPT_ERROR / 10)
    with pytest.raises(ModelOutOfReach):
        check_useful("m", 50, 2 * ACCEPT_ERROR, ACCEPT_ERROR)


def test_the_longest_super_step_wins_among_probes_within_their_noise() -> None:
    # ball_in_cup's probes: a near tie, so the longest (fully trained: 0.013 at n = 50, 0.019 at 25)
    n, why = pick({50: 0.0607, 25: 0.0529, 10: 0.0562})
    assert n == 50 and "within 1.25× of the best" in why
    # the finger's: n = 10 is clearly best
    assert pick({50: 0.342, 25: 0.24, 10: 0.156})[0] == 10
    assert pick({50: 0.119, 25: 0.0604, 10: 0.0552})[0] == 25
    # a probe that reaches the target wins outright
    n, why = pick({50: 0.08, 25: 0.049})
    assert n == 25 and "reached 0.05" in why
    # the exact edge of a tie counts as one
    assert pick({50: 0.125, 10: 0.1})[0] == 50
