"""Rollout errors in physical units: root position in metres, attitude in degrees, hinge and ball joints
in radians, slide joints in metres.

A normalised rollout error divides by the spread of each variable over the data, so a lander that
flies tens of metres hides metres of drift behind a small number. These are the errors a user sees:
how far the emulated body is from MuJoCo's, how differently it is turned, how far its joints are off.

Shapes: N trials, M super-steps, S state size.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.results import PhysicalErrorAt, PhysicalErrors
from neuroanimator.core.state import StateLayout

FloatArray = NDArray[np.float64]
REPORT_TIMES_S: tuple[float, ...] = (1.0, 5.0, 10.0, 20.0)


def _wrap(angle: FloatArray) -> FloatArray:
    """Angles folded into [-π, π)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def _quaternion_angle(a: FloatArray, b: FloatArray) -> FloatArray:
    """The rotation angle (rad) between unit quaternions a and b (..., 4); q and −q are the same."""
    na = a / np.linalg.norm(a, axis=-1, keepdims=True)
    nb = b / np.linalg.norm(b, axis=-1, keepdims=True)
    dot = np.clip(np.abs(np.sum(na * nb, axis=-1)), 0.0, 1.0)
    return 2.0 * np.arccos(dot)


def error_series(layout: StateLayout, pred: FloatArray, truth: FloatArray) -> dict[str, FloatArray]:
    """Per trial and super-step errors (N, M) in physical units, for the quantities the layout has.

    - ``root_position_m``: distance between the root positions (a ``position`` group);
    - ``attitude_deg``: the angle between root orientations (``quaternion``) or headings (``heading``);
    - ``joint_angle_rad``: mean absolute wrapped difference over hinge angles (``angle`` groups) and
      ball joints (``local_quaternion``, the angle between them);
    - ``joint_position_m``: mean absolute difference over the lengths of ``qpos`` (``scalar`` groups:
      slide joints, and the positions of free bodies other than the root).
    """
    out: dict[str, FloatArray] = {}
    pos = layout.find("position")
    if pos is not None:
        sl = layout.slice_of(pos.name)
        out["root_position_m"] = np.linalg.norm(pred[..., sl] - truth[..., sl], axis=-1)
    att = layout.find("quaternion", "heading")
    if att is not None:
        sl = layout.slice_of(att.name)
        if att.kind == "quaternion":
            rad = _quaternion_angle(pred[..., sl], truth[..., sl])
        else:
            rad = np.abs(_wrap(pred[..., sl.start] - truth[..., sl.start]))
        out["attitude_deg"] = np.degrees(rad)
    joints: list[FloatArray] = []
    for g, sl in layout.group_slices():
        if g.kind == "angle":
            joints.extend(np.abs(_wrap(pred[..., c] - truth[..., c])) for c in range(sl.start, sl.stop))
        elif g.kind == "local_quaternion":
            joints.append(_quaternion_angle(pred[..., sl], truth[..., sl]))
    if joints:
        out["joint_angle_rad"] = np.mean(np.stack(joints, axis=0), axis=0)
    # qpos holds lengths (metres) or angles; the angles have their own kinds, so a qpos scalar is a length.
    lengths = [
        c
        for g, sl in layout.group_slices()
        if g.kind == "scalar" and g.source == "qpos"
        for c in range(sl.start, sl.stop)
    ]
    if lengths:
        out["joint_position_m"] = np.mean(np.abs(pred[..., lengths] - truth[..., lengths]), axis=-1)
    return out


def summarize(
    series: dict[str, FloatArray], super_dt: float, times_s: Sequence[float] = REPORT_TIMES_S
) -> PhysicalErrors:
    """The errors at the given times (those the rollouts reach): mean and 90th percentile over trials.

    ``series[q]`` is (N, M) with column k the error after k + 1 super-steps of ``super_dt`` seconds.
    A non-finite error (a diverged emulator) makes the statistic it enters infinite, reported as None
    (JSON's null), never hidden.
    """
    out: dict[str, list[PhysicalErrorAt]] = {}
    for name, err in series.items():
        rows = []
        for t in times_s:
            k = round(t / super_dt) - 1
            if k < 0 or k >= err.shape[1]:
                continue
            col = np.where(np.isfinite(err[:, k]), err[:, k], np.inf)
            mean, p90 = float(np.mean(col)), float(np.percentile(col, 90))
            rows.append(
                PhysicalErrorAt(
                    t_s=t, mean=mean if np.isfinite(mean) else None, p90=p90 if np.isfinite(p90) else None
                )
            )
        out[name] = rows
    return PhysicalErrors(**out)


def _num(v: float | None) -> str:
    return "inf" if v is None else f"{v:.3g}"


UNITS = {"root_position_m": "m", "attitude_deg": "°", "joint_angle_rad": "rad", "joint_position_m": "m"}


def format_table(errors: PhysicalErrors) -> list[str]:
    """Readable lines: one per quantity, mean (p90) at each reported time."""
    lines = []
    for name in UNITS:
        rows = getattr(errors, name)
        if rows:
            cells = "  ".join(f"{e.t_s:g} s: {_num(e.mean)} ({_num(e.p90)})" for e in rows)
            lines.append(f"{name:<16} mean (p90) in {UNITS[name]}: {cells}")
    return lines
