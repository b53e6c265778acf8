"""Typical controls of a rhythmic gait: travelling waves (``ModelSpec.travelling_waves``).

Shapes: B runs, T times, U controls.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.model_spec import TravellingWaves
from neuroanimator.sim.errors import ModelError

FloatArray = NDArray[np.float64]


def wave_controls(
    waves: TravellingWaves, rng: np.random.Generator, batch: int, times: FloatArray, lohi: FloatArray
) -> FloatArray:
    """(B, T, U) controls of ``batch`` wave runs over ``lohi`` (U, 2), before any blending: each run its
    own period, lag, amplitude and starting phase, drawn uniformly from the spec's ranges."""
    u = lohi.shape[0]
    if len(waves.phase) != u:
        raise ModelError(f"travelling_waves: {len(waves.phase)} phases and ranks for {u} controls")
    period = rng.uniform(*waves.period_s, size=(batch, 1, 1))
    lag = rng.uniform(*waves.lag, size=(batch, 1, 1))
    amplitude = rng.uniform(*waves.amplitude, size=(batch, 1, 1))
    start = rng.uniform(0.0, 2 * math.pi, size=(batch, 1, 1))
    t = np.asarray(times, dtype=np.float64)[None, :, None]
    phase = np.asarray(waves.phase)[None, None, :] + lag * np.asarray(waves.rank)[None, None, :]
    centre, half = lohi.mean(axis=1), (lohi[:, 1] - lohi[:, 0]) / 2
    return centre + amplitude * half * np.sin(2 * math.pi * t / period - phase + start)


def mix_waves(
    waves: TravellingWaves, rng: np.random.Generator, random: FloatArray, times: FloatArray, lohi: FloatArray
) -> FloatArray:
    """(B, T, U) ``random`` smooth controls with a ``waves.fraction`` share of the runs (drawn at
    random) replaced by waves blended with their own random controls, clipped to ``lohi``."""
    chosen = np.flatnonzero(rng.random(random.shape[0]) < waves.fraction)
    if chosen.size == 0:
        return random
    out = random.copy()
    wave = wave_controls(waves, rng, chosen.size, times, lohi)
    out[chosen] = np.clip((1 - waves.blend) * wave + waves.blend * random[chosen], lohi[:, 0], lohi[:, 1])
    return out
