"""Proximity of two geoms: the distance between their surfaces, for the pairs of geoms that touch each
other in a model's typical motion (a fingertip against a spinner, a ball against a cup's wall).

Where a contact between two moving bodies switches on depends on where the two geoms are, which a
network reads only through the chains of joint angles that place them. ``clearance.Clearance`` turns
the state into each geom's world pose by forward kinematics inside the graph; this module picks the
pairs (``touching_pairs``), describes each geom as a swept sphere (``Swept``: a segment and a radius;
exact for spheres and capsules, a bounding capsule along the longest axis for the others) and computes
the distance between two such shapes (``segment_gap``): the closest points of two segments, then
less both radii. Negative is how far the two overlap. Everything is elementwise arithmetic, clamps and
selects: it runs in the same ONNX graph as the rest of the step.

Shapes: N rows, P pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from torch import Tensor

MAX_PAIRS = 16  # the pairs that touch most often are read; more add inputs and little else
_EPS = 1e-9


@dataclass(frozen=True)
class Swept:
    """A geom as the points within ``radius`` of the segment ``centre ± half·axis`` in its geom frame
    (``centre`` (3,) and ``axis`` (3,) unit, in the geom's own frame)."""

    centre: np.ndarray
    axis: np.ndarray
    half: float
    radius: float


POINT = Swept(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.0, 0.0)  # a site: the end of a tendon's segment


def swept(m: mujoco.MjModel, g: int) -> Swept:
    """Geom ``g`` as a swept sphere: a sphere or capsule exactly; a cylinder as the capsule around it;
    an ellipsoid, box or mesh (its bounding box) as a capsule along its longest axis whose radius is the
    larger of the other two half-sizes (it encloses the shape's cross-section at its middle)."""
    kind = int(m.geom_type[g])
    mesh = kind == mujoco.mjtGeom.mjGEOM_MESH
    size = np.asarray(m.geom_aabb[g][3:] if mesh else m.geom_size[g], dtype=float)
    centre = np.asarray(m.geom_aabb[g][:3] if mesh else np.zeros(3), dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return Swept(centre, z, 0.0, float(size[0]))
    if kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
        return Swept(centre, z, float(size[1]), float(size[0]))
    longest = int(np.argmax(size))
    radius = float(np.delete(size, longest).max())
    axis = np.eye(3)[longest]
    return Swept(centre, axis, max(float(size[longest]) - radius, 0.0), radius)


def touching_pairs(m: mujoco.MjModel, qpos_rows: np.ndarray, floor_geoms: set[int]) -> list[tuple[int, int]]:
    """The geom pairs (ids, lower first) in contact in some of the configurations ``qpos_rows`` (N, nq),
    most frequent first, at most ``MAX_PAIRS``; pairs with a floor geom (``floor_geoms``, which the
    clearance features cover) and pairs of two world geoms are left out."""
    d = mujoco.MjData(m)
    counts: dict[tuple[int, int], int] = {}
    for row in qpos_rows:
        d.qpos[:] = row
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        for c in d.contact[: d.ncon]:
            a, b = sorted((int(c.geom1), int(c.geom2)))
            if a in floor_geoms or b in floor_geoms or (m.geom_bodyid[a] == 0 and m.geom_bodyid[b] == 0):
                continue
            counts[(a, b)] = counts.get((a, b), 0) + 1
    ranked = sorted(counts, key=lambda p: (-counts[p], p))
    return ranked[:MAX_PAIRS]


def _dot(u: Tensor, v: Tensor, total: Tensor) -> Tensor:
    """Row-wise dot products of (N, 3P) vector rows: (N, P), summed by the (3P, P) constant ``total``."""
    return (u * v) @ total


def segment_gap(c1: Tensor, d1: Tensor, c2: Tensor, d2: Tensor, radii: Tensor, total: Tensor) -> Tensor:
    """(N, P) distances between swept spheres: segment i is ``c1 + s·d1`` for s in [-1, 1] (``c1``,
        ``d1`` (N, 3P): centres and half-extents, pair p in columns 3p..3p+2), segment j ``c2 + t·d2``,
        less ``radii`` (P,) (the two radii summed). The closest points as in the textbook method: s from
        the unclamped joint minimum, clamped; t for that s, clamped; s again for a clamped t. A zero-length
        segment (a sphere) or parallel segments are handled by the guards on each division; for a point as
    the second segment, s is its projection on the first."""
    r = c1 - c2
    a, e = _dot(d1, d1, total), _dot(d2, d2, total)
    b, c, f = _dot(d1, d2, total), _dot(d1, r, total), _dot(d2, r, total)
    denom = a * e - b * b
    ok = denom > _EPS * (a * e).clamp_min(_EPS)
    s = torch.where(ok, (b * f - c * e) / torch.where(ok, denom, torch.ones_like(denom)), torch.zeros_like(a))
    s = s.clamp(-1.0, 1.0)
    has_e = e > _EPS
    t_raw = torch.where(has_e, (b * s + f) / torch.where(has_e, e, torch.ones_like(e)), torch.zeros_like(e))
    t = t_raw.clamp(-1.0, 1.0)
    has_a = a > _EPS
    s_again = torch.where(has_a, (b * t - c) / torch.where(has_a, a, torch.ones_like(a)), torch.zeros_like(a))
    # a clamped t moves the closest point on the first segment; so does a point for the second one
    # (t = 0), where the joint minimum above is undefined
    s = torch.where((t_raw == t) & has_e, s, s_again.clamp(-1.0, 1.0))
    spread = total.T  # (P, 3P): a per-pair scalar onto its three columns
    gap = r + (s @ spread) * d1 - (t @ spread) * d2
    return torch.sqrt(_dot(gap, gap, total) + 1e-12) - radii


def sum_matrix(pairs: int) -> Tensor:
    """(3P, P): sums each pair's three columns."""
    out = torch.zeros(3 * pairs, pairs)
    for p in range(pairs):
        out[3 * p : 3 * p + 3, p] = 1.0
    return out
