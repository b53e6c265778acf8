"""Typical controls of a rhythmic gait (``ModelSpec.travelling_waves``): the dolphin's strokes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from neuroanimator import catalog
from neuroanimator.catalog import dolphin
from neuroanimator.core.model_spec import TravellingWaves
from neuroanimator.sim.model import ModelError
from neuroanimator.sim.waves import mix_waves, wave_controls

LOHI = np.array([[0.0, 1.0]] * 6)
TIMES = np.arange(0.0, 20.0, 0.05)


def test_a_pure_wave_alternates_antagonists_and_travels_head_to_tail() -> None:
    waves = dolphin.STROKES.model_copy(
        update={"period_s": (4.0, 4.0), "lag": (0.5, 0.5), "amplitude": (1.0, 1.0)}
    )
    u = wave_controls(waves, np.random.default_rng(1), 3, TIMES, LOHI)
    assert u.shape == (3, TIMES.size, 6)
    # dorsal and ventral of an interval in antiphase about the middle of [0, 1]: they sum to 1
    np.testing.assert_allclose(u[..., 0::2] + u[..., 1::2], 1.0, atol=1e-12)
    assert u.min() == pytest.approx(0.0, abs=1e-3) and u.max() == pytest.approx(1.0, abs=1e-3)
    # interval 2 is interval 1 delayed by lag / (2π) of the 4 s period: 0.318 s, about 6 samples of 0.05 s
    delay = round(0.5 / (2 * math.pi) * 4.0 / 0.05)
    np.testing.assert_allclose(u[:, delay:, 2], u[:, :-delay, 0], atol=0.03)


def test_a_share_of_runs_are_waves_and_all_stay_in_range() -> None:
    rng = np.random.default_rng(0)
    random = rng.uniform(0.0, 1.0, (400, TIMES.size, 6))
    waves = dolphin.STROKES.model_copy(update={"blend": 0.0})
    mixed = mix_waves(waves, np.random.default_rng(2), random, TIMES, LOHI)
    is_wave = np.all(np.abs(mixed[..., 0] + mixed[..., 1] - 1.0) < 1e-9, axis=1)
    assert 0.4 < is_wave.mean() < 0.6  # fraction 0.5
    np.testing.assert_array_equal(mixed[~is_wave], random[~is_wave])  # the others untouched
    assert mixed.min() >= 0.0 and mixed.max() <= 1.0


def test_the_dolphins_typical_controls_hold_strokes() -> None:
    model = catalog.get("dolphin")
    u = model.typical_controls(np.random.default_rng(3), 200, TIMES)
    # per run, the correlation of dorsal and ventral muscle 1: near −1 for strokes (blended 4:1 with
    # random activations), near 0 for independent random ones
    corr = np.array([np.corrcoef(run[:, 0], run[:, 1])[0, 1] for run in u])
    assert 0.3 < np.mean(corr < -0.7) < 0.7
    assert np.mean(np.abs(corr) < 0.5) > 0.25


def test_bad_waves_are_refused_with_the_reason() -> None:
    with pytest.raises(ValidationError, match="one per control"):
        TravellingWaves(fraction=0.5, period_s=(1, 2), lag=(0, 1), amplitude=(0, 1), phase=[0.0], rank=[0, 1])
    with pytest.raises(ValidationError, match=r"low 3\.0 above high 2\.0"):
        TravellingWaves(fraction=0.5, period_s=(3, 2), lag=(0, 1), amplitude=(0, 1), phase=[0.0], rank=[0])
    with pytest.raises(ValidationError, match="amplitude"):
        TravellingWaves(fraction=0.5, period_s=(1, 2), lag=(0, 1), amplitude=(0, 2), phase=[0.0], rank=[0])
    one = TravellingWaves(fraction=1.0, period_s=(1, 2), lag=(0, 1), amplitude=(0, 1), phase=[0.0], rank=[0])
    with pytest.raises(ModelError, match="1 phases and ranks for 6 controls"):
        wave_controls(one, np.random.default_rng(0), 2, TIMES, LOHI)
