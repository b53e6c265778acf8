"""Typical initial states that do not start inside the floor or inside each other.

A typical initial state perturbs the rest pose: joint angles by a few tenths of a radian, a root
slide by a few tenths of a metre, the root tilted. On a body that stands on a floor that often puts
a foot into the ground or one limb into another (dm_control's hopper, walker and cheetah in 39-53%
of their starts, by up to 35 cm; the quadruped and the dog in 84% and 95%). MuJoCo's soft
contact then pushes the geoms apart with forces that no motion of the model ever meets again: the
first tenths of a second of such a run are an explosion, which an emulator is trained and measured
on, and the dog's runs diverge outright.

``separate`` mends the starts that penetrate deeper than the rest pose does (by more than
``TOLERANCE``): a start inside something fixed (the floor) is lifted by its root's vertical
translation, where the root has one, as if dropped from just above the ground; one that still
penetrates (a limb in another, or a root that cannot rise) has its perturbation halved, up to
``HALVINGS`` times, and failing that starts at the rest pose. Starts that touch nothing are left
exactly as drawn, so a model without such contacts samples as before.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

TOLERANCE = 0.002  # metres past the rest pose's own depth: a resting soft contact sinks well under this
CLEARANCE = 0.002  # metres: how far above the deepest contact a lifted start ends
LIFTS = 3  # a lift clears a flat floor at once; a few more for slopes and height fields
HALVINGS = 6  # then 1/64 of the drawn perturbation; past it the rest pose


@dataclass(frozen=True)
class Depths:
    """How far a pose penetrates: the deepest contact with something fixed to the world, and the
    deepest between two moving bodies (metres, 0 for none); ``roots``: the root bodies of the moving
    geoms in the first kind, deepest first."""

    fixed: float
    moving: float
    roots: tuple[int, ...]

    @property
    def deepest(self) -> float:
        return max(self.fixed, self.moving)


class Separator:
    """Measures and mends the penetration of poses of one MuJoCo model (``qpos``, nq values)."""

    def __init__(self, m: mujoco.MjModel) -> None:
        self.m = m
        self.d = mujoco.MjData(m)
        self.rest_depth = self.depths(m.qpos0.copy()).deepest
        self._lifts = self._vertical_dofs()

    def depths(self, qpos: FloatArray) -> Depths:
        m, d = self.m, self.d
        d.qpos[:] = qpos
        mujoco.mj_fwdPosition(m, d)
        fixed, moving = 0.0, 0.0
        roots: dict[int, float] = {}
        for c in d.contact[: d.ncon]:
            depth = -float(c.dist)
            if depth <= 0.0:
                continue
            b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
            static1, static2 = m.body_weldid[b1] == 0, m.body_weldid[b2] == 0
            if static1 or static2:
                fixed = max(fixed, depth)
                root = int(m.body_rootid[b2 if static1 else b1])
                roots[root] = max(roots.get(root, 0.0), depth)
            else:
                moving = max(moving, depth)
        order = tuple(sorted(roots, key=lambda r: -roots[r]))
        return Depths(fixed, moving, order)

    def _vertical_dofs(self) -> dict[int, tuple[int, float]]:
        """root body -> (qpos address, cosine with the vertical) of a translation that raises it: a free
        joint's z, or a slide joint along the vertical (within 60°)."""
        m, d = self.m, self.d
        g = np.asarray(m.opt.gravity, dtype=np.float64)
        up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, 1.0])
        d.qpos[:] = m.qpos0
        mujoco.mj_kinematics(m, d)
        out: dict[int, tuple[int, float]] = {}
        for j in range(m.njnt):
            body = int(m.jnt_bodyid[j])
            root = int(m.body_rootid[body])
            if root in out or body != root:  # a translation of the root body itself
                continue
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                out[root] = (int(m.jnt_qposadr[j]) + 2, float(up[2]) if up[2] != 0 else 1.0)
            elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE:
                cos = float(np.dot(d.xaxis[j], up))
                if abs(cos) > 0.5:
                    out[root] = (int(m.jnt_qposadr[j]), cos)
        return out

    def acceptable(self, depths: Depths) -> bool:
        return depths.deepest <= self.rest_depth + TOLERANCE

    def lift(self, qpos: FloatArray) -> tuple[FloatArray, Depths]:
        """``qpos`` raised until nothing fixed holds it (where its roots can rise), and its depths."""
        q = qpos.copy()
        depths = self.depths(q)
        for _ in range(LIFTS):
            if self.acceptable(depths) or depths.fixed <= self.rest_depth + TOLERANCE:
                break
            raised = False
            for root in depths.roots:
                if root in self._lifts:
                    adr, cos = self._lifts[root]
                    q[adr] += (depths.fixed + CLEARANCE) / cos
                    raised = True
                    break  # the deepest root first; the others are looked at again after it moved
            if not raised:
                break
            depths = self.depths(q)
        return q, depths


def separate(
    separator: Separator,
    qpos: FloatArray,
    rebuild: Callable[[int, float], FloatArray],
) -> tuple[FloatArray, int, int]:
    """Mend the rows of ``qpos`` (B, nq) that penetrate (module doc). ``rebuild(row, scale)`` gives the
    row's pose with its perturbation scaled by ``scale`` (0: the rest pose). Returns the poses, how many
    were lifted and how many had their perturbation cut."""
    out = qpos.copy()
    lifted = shrunk = 0
    scales = [0.5**k for k in range(1, HALVINGS + 1)] + [0.0]
    for i in range(out.shape[0]):
        if separator.acceptable(separator.depths(out[i])):
            continue
        q, depths = separator.lift(out[i])
        if separator.acceptable(depths):
            lifted += 1
        else:
            shrunk += 1
            for scale in scales:
                q, depths = separator.lift(rebuild(i, scale))
                if separator.acceptable(depths):
                    break
        out[i] = q
    return out, lifted, shrunk
