"""Whether states lie in the envelope a model version was trained on (``Manifest.envelope``).

The batcher checks every new state it writes back (one comparison over the whole batch) and keeps the
answer per session (``Session.outside_envelope``); step replies carry it as ``outside_envelope`` and
name the state groups that are out (``outside_groups``). An artifact without an envelope (older ones)
has no ``StateEnvelope``: its states are never flagged. Each value is given at least ``GROUP_FLOOR`` of its
group's scale (``widened``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.manifest import EnvelopeGroup
from neuroanimator.core.state import StateLayout
from services.emulator.bounds import RowBounds

GROUP_FLOOR = 0.01
"""The least half-width of a value's bounds, as a fraction of the widest range in its group: a value the
training data never moved (a node's y, in a body that swims in its plane of symmetry) is not flagged
for the emulator's millimetres of drift across it while its group moves metres."""


def widened(
    low: NDArray[np.float64], high: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One group's bounds (n,), each at least ``GROUP_FLOOR`` of the group's widest finite range either
    side of its middle; unbounded values stay unbounded."""
    finite = np.isfinite(low) & np.isfinite(high)
    if not finite.any():
        return low, high
    floor = GROUP_FLOOR * float((high[finite] - low[finite]).max())
    mid = np.zeros_like(low)
    mid[finite] = 0.5 * (low[finite] + high[finite])
    return (
        np.where(finite, np.minimum(low, mid - floor), low),
        np.where(finite, np.maximum(high, mid + floor), high),
    )


class StateEnvelope:
    """A model version's envelope as (S,) float32 bounds (±inf where a value is unbounded), rounded
    outwards so that a float32 state on the edge is inside."""

    def __init__(self, layout: StateLayout, groups: list[EnvelopeGroup]) -> None:
        low = np.full(layout.size, -np.inf, np.float64)
        high = np.full(layout.size, np.inf, np.float64)
        self.groups: list[tuple[str, slice]] = []
        for env in groups:
            sl = layout.slice_of(env.group)
            lo = np.array([-np.inf if v is None else v for v in env.low], np.float64)
            hi = np.array([np.inf if v is None else v for v in env.high], np.float64)
            low[sl], high[sl] = widened(lo, hi)
            if np.isfinite(low[sl]).any() or np.isfinite(high[sl]).any():
                self.groups.append((env.group, sl))
        lo32, hi32 = low.astype(np.float32), high.astype(np.float32)
        self.low = np.where(lo32 > low, np.nextafter(lo32, np.float32(-np.inf)), lo32)
        self.high = np.where(hi32 < high, np.nextafter(hi32, np.float32(np.inf)), hi32)
        self.rows = RowBounds(self.low, self.high)

    def outside(self, states: NDArray[np.float32]) -> NDArray[np.bool_] | None:
        """(B,) whether each state of (B, S) is outside (NaN is not), or None when none is (the usual
        answer, found in two flat comparisons)."""
        return self.rows.rows_outside(states)

    def groups_outside(self, states: NDArray[np.float32]) -> list[str]:
        """The groups with a value outside the envelope in any of the states (S,) or (K, S)."""
        x = np.atleast_2d(states)
        out = np.asarray(((x < self.low) | (x > self.high)).any(axis=0))
        if not out.any():
            return []
        return [name for name, sl in self.groups if out[sl].any()]
