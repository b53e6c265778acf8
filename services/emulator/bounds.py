"""Per-value bounds checked over batches of rows, for the input range and the training envelope.

Comparing rows (N, W) with a (W,) bound broadcasts it along a short last axis, which numpy runs as N
short inner loops: for 4,096 rows of a few values that is several times slower than one flat loop.
So the bounds are kept repeated for as many rows as the largest batch seen, and every comparison is
between two arrays of the same shape; which rows are out is then read from the flat indices of the
values that are out, never by a reduction along the short axis.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class RowBounds:
    """``low``..``high`` (W,) float32 per value of rows (N, W)."""

    def __init__(self, low: NDArray[np.float32], high: NDArray[np.float32]) -> None:
        self.low = low
        self.high = high
        self._low_rows = low[None]
        self._high_rows = high[None]

    def repeated(self, n: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """The bounds as (n, W) arrays."""
        if len(self._low_rows) < n:
            rows = max(n, 2 * len(self._low_rows))
            self._low_rows = np.tile(self.low, (rows, 1))
            self._high_rows = np.tile(self.high, (rows, 1))
        return self._low_rows[:n], self._high_rows[:n]

    def contain(self, x: NDArray[np.float32]) -> bool:
        """Every value of rows (N, W) in bounds (NaN is not)."""
        low, high = self.repeated(len(x))
        return bool((x >= low).all() and (x <= high).all())

    def rows_outside(self, x: NDArray[np.float32]) -> NDArray[np.bool_] | None:
        """(N,) the rows of (N, W) with a value out of bounds (NaN is not out), or None when none has."""
        low, high = self.repeated(len(x))
        below, above = x < low, x > high
        if not (below.any() or above.any()):
            return None
        out = np.zeros(len(x), bool)
        width = x.shape[1]
        out[np.flatnonzero(below) // width] = True
        out[np.flatnonzero(above) // width] = True
        return out
