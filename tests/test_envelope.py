"""The training envelope: per state group, the range of the training states, widened by a margin; no
bounds where the emulator is indifferent to a value; written by training, optional in a manifest."""

from __future__ import annotations

import json

import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.core.manifest import ManifestError, parse_manifest
from neuroanimator.training.envelope import MARGIN, training_envelope, unbounded
from tests.helpers import Trained


def test_lander_bounds_its_velocities_not_its_pose() -> None:
    model = catalog.get("lander")  # no floor: translation-invariant along x, y and z
    free = unbounded(model.layout, model.frame.translate, model.frame.rotate)
    sl = {g.name: model.layout.slice_of(g.name) for g in model.layout}
    assert free[sl["position"]].all() and free[sl["orientation"]].all()
    assert not free[sl["velocity"]].any() and not free[sl["angular_velocity"]].any()


def test_truck_heading_and_pendulum_angles_are_free() -> None:
    truck = catalog.get("truck")
    free = unbounded(truck.layout, truck.frame.translate, truck.frame.rotate)
    assert free[truck.layout.slice_of("heading")].all()
    assert not free[truck.layout.slice_of("velocity")].any()
    pendulum = catalog.get("pendulum-active")  # hinge angles enter as sin and cos
    free = unbounded(pendulum.layout, pendulum.frame.translate, pendulum.frame.rotate)
    assert free[pendulum.layout.slice_of("angles")].all()
    assert not free[pendulum.layout.slice_of("rates")].any()


def test_the_range_of_the_data_widened_by_the_margin() -> None:
    model = catalog.get("pendulum-active")
    rates = np.array([[-1.0, 0.0, 2.0], [3.0, 0.0, 4.0]])
    states = np.concatenate([np.zeros((2, 3)), rates], axis=1)
    env = {g.group: g for g in training_envelope(model.layout, states, (), False)}
    assert env["angles"].low == [None] * 3 and env["angles"].high == [None] * 3
    low, high = np.asarray(env["rates"].low), np.asarray(env["rates"].high)
    np.testing.assert_allclose(low, [-1 - 4 * MARGIN, 0, 2 - 2 * MARGIN], atol=1e-5)
    np.testing.assert_allclose(high, [3 + 4 * MARGIN, 0, 4 + 2 * MARGIN], atol=1e-5)
    assert low[1] < 0 < high[1]  # a value constant in the data keeps a rounding error of room
    assert (low <= rates.min(axis=0)).all() and (high >= rates.max(axis=0)).all()


def test_training_writes_the_envelope_and_older_manifests_still_load(trained_pendulum: Trained) -> None:
    manifest = registry.read_manifest(trained_pendulum.path)
    assert manifest.envelope is not None
    assert [g.group for g in manifest.envelope] == ["angles", "rates"]
    rates = next(g for g in manifest.envelope if g.group == "rates")
    assert all(
        lo is not None and hi is not None and lo < hi for lo, hi in zip(rates.low, rates.high, strict=True)
    )
    data = json.loads((trained_pendulum.path / registry.MANIFEST_FILE).read_text())
    assert parse_manifest({k: v for k, v in data.items() if k != "envelope"}).envelope is None
    data["envelope"][1]["low"] = [0.0]
    with pytest.raises(ManifestError, match="envelope of 'rates'"):
        parse_manifest(data)
