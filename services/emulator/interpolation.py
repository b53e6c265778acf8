"""Frames between super-steps (thesis 4.1): linear for every number, slerp for quaternion groups,
the shorter arc for wrapped angles (a heading)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.quaternion import slerp, wrap_angle


def frames(
    states: NDArray[np.floating],
    per_step: int,
    quaternion_slices: list[slice],
    angle_columns: Sequence[int] = (),
) -> NDArray[np.float32]:
    """States (M+1, S) at super-step boundaries -> (M·per_step + 1, S) frames evenly spaced in time.

    Frame ``k·per_step`` is exactly ``states[k]``; the frames between two states are linear
    interpolations, except quaternion groups, which are slerped (so they stay unit quaternions), and
    ``angle_columns`` (reported wrapped to [-π, π)), which turn the shorter way and stay wrapped.
    """
    s = np.asarray(states, dtype=np.float64)
    m = s.shape[0] - 1
    if m < 1:
        return s.astype(np.float32)
    t = np.arange(per_step, dtype=np.float64) / per_step  # (P,) fractions within each step
    a, b = s[:-1, None, :], s[1:, None, :]  # (M, 1, S)
    change = b - a
    cols = list(angle_columns)
    if cols:
        change[..., cols] = wrap_angle(change[..., cols])  # 3.1 -> -3.1 is a turn of 0.08, not of -6.2
    out = a + change * t[None, :, None]  # (M, P, S)
    if cols:
        out[..., cols] = wrap_angle(out[..., cols])
    for sl in quaternion_slices:
        q0 = np.broadcast_to(a[..., sl], out[..., sl].shape)
        q1 = np.broadcast_to(b[..., sl], out[..., sl].shape)
        out[..., sl] = slerp(q0, q1, np.broadcast_to(t[None, :], out.shape[:2]))
        out[:, 0, sl] = s[:-1, sl]  # exact endpoints (slerp renormalises)
    return np.concatenate([out.reshape(m * per_step, -1), s[-1:]], axis=0).astype(np.float32)
