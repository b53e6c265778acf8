"""Quaternion algebra (thesis appendix D), ``[w, x, y, z]`` order, batched over leading axes.

Written once against the array API shared by numpy and torch (``*``, ``+``, ``stack``), so the
structured emulator, the ONNX export and the numpy tools use the very same formulas.

PyTorch is not imported here: a torch tensor can only reach these functions once torch is loaded,
so ``_torch_of`` looks it up in ``sys.modules`` and numpy-only processes (the emulator service)
never import it.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np


def _torch_of(like: Any) -> Any:
    """The torch module when ``like`` is a torch tensor, else None (without importing torch)."""
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(like, torch.Tensor):
        return torch
    return None


def _stack(parts: list[Any], like: Any) -> Any:
    torch = _torch_of(like)
    if torch is not None:
        return torch.stack(parts, dim=-1)
    return np.stack(parts, axis=-1)


def multiply(a: Any, b: Any) -> Any:
    """Hamilton product ``a ⊗ b`` (eq. 4.2/4.3): rotation ``b`` followed by rotation ``a``."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return _stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        a,
    )


def conjugate(q: Any) -> Any:
    return _stack([q[..., 0], -q[..., 1], -q[..., 2], -q[..., 3]], q)


def matrix(q: Any) -> Any:
    """The 4×4 matrix ``Q`` with ``q ⊗ p = Q p`` (eq. 4.3); shape (..., 4, 4)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        _stack([w, -x, -y, -z], q),
        _stack([x, w, -z, y], q),
        _stack([y, z, w, -x], q),
        _stack([z, -y, x, w], q),
    ]
    torch = _torch_of(q)
    if torch is not None:
        return torch.stack(rows, dim=-2)
    return np.stack(rows, axis=-2)


def rotate(q: Any, v: Any) -> Any:
    """Rotate 3-vectors ``v`` (..., 3) by unit quaternions ``q`` (..., 4)."""
    zero = v[..., 0] * 0
    p = _stack([zero, v[..., 0], v[..., 1], v[..., 2]], v)
    r = multiply(multiply(q, p), conjugate(q))
    return r[..., 1:]


def from_axis_angle(axis: Any, angle: Any) -> Any:
    """Unit quaternion for a rotation by ``angle`` about unit ``axis`` (..., 3)."""
    a = np.asarray(axis, dtype=np.float64)
    half = np.asarray(angle, dtype=np.float64) / 2.0
    s = np.sin(half)
    return np.stack([np.cos(half), a[..., 0] * s, a[..., 1] * s, a[..., 2] * s], axis=-1)


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation (Shoemake; thesis D.3) along the shorter arc.

    q0, q1: (..., 4) unit quaternions; t broadcastable to (...,). Returns (..., 4).
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)  # q and -q are the same rotation: take the short way
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    close = sin_theta < 1e-6
    safe = np.where(close, 1.0, sin_theta)
    a = np.where(close, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    b = np.where(close, t, np.sin(t * theta) / safe)
    out = a * q0 + b * q1
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def angle_between(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Rotation angle (radians) taking q0 to q1 (thesis D.6 error metric), shape (...)."""
    dot = np.abs(np.sum(np.asarray(q0) * np.asarray(q1), axis=-1))
    return 2.0 * np.arccos(np.clip(dot, -1.0, 1.0))


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Angles (radians) wrapped to [-π, π): how a ``heading`` is reported (``state.heading_columns``)."""
    return np.remainder(np.asarray(angle, dtype=np.float64) + np.pi, 2 * np.pi) - np.pi
