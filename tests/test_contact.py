"""Ground contact: the catalog's ball, and how the trainer sees contacts and limits in typical motion."""

from __future__ import annotations

from neuroanimator import physics
from neuroanimator.super_step import constraint_activity, probe_config
from neuroanimator.train_config import TrainConfig


def test_a_pendulum_has_neither_contact_nor_limits() -> None:
    activity = constraint_activity(physics.get("pendulum-active"))
    assert not activity.any


def test_probes_are_short_and_keep_the_users_choices() -> None:
    cfg = TrainConfig(hidden=(32,), examples=50_000, max_seconds=150.0, seed=4)
    probe = probe_config(cfg, 25)
    assert (probe.substeps, probe.hidden, probe.seed) == (25, (32,), 4)
    assert probe.examples == 6000 and probe.max_epochs == 40 and probe.rollout_steps == 0
