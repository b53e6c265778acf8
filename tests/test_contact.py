"""Contacts and world-axis controls: how the trainer sees contacts and limits in typical motion, and a
ball on a floor pushed along world axes (tests/data/pushed_ball.xml)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from neuroanimator import physics, quaternion
from neuroanimator.physics.mjcf import load_mjcf
from neuroanimator.physics.model import PhysicalModel
from neuroanimator.structured import StructuredEmulator
from neuroanimator.super_step import constraint_activity, probe_config
from neuroanimator.train_config import TrainConfig
from tests.helpers import ROOT
from tests.test_body_frame import _move, _predict, _sphere_of_attitudes

MakeEmulator = Callable[..., StructuredEmulator]
BALL = ROOT / "tests" / "data" / "pushed_ball.xml"


def _ball() -> PhysicalModel:
    return load_mjcf(BALL, substeps=10)


def test_the_ball_touches_the_ground_and_nothing_limits_it() -> None:
    activity = constraint_activity(_ball())
    assert activity.contact > 0.5  # it spends most of its time on the floor
    assert activity.limit == 0


def test_a_pendulum_has_neither_contact_nor_limits() -> None:
    activity = constraint_activity(physics.get("pendulum-active"))
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
