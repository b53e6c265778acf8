"""Forward kinematics in torch: where a model's bodies, sites and geoms are, and how they are turned,
as differentiable functions of the emulator's state.

A reward or a task's term speaks of places (a fingertip's distance to a target, a pole's height, a
torso's up vector); the emulator predicts joint coordinates. ``Kinematics`` walks MuJoCo's kinematic
tree as ``mj_kinematics`` does (each body placed in its parent's frame at ``body_pos``/``body_quat``,
then moved by its joints: a hinge turns about its axis through its anchor, a slide moves along its
axis, both by ``qpos − qpos0``; a ball joint turns by its quaternion; a free joint sets the body's
world position and orientation), so that gradients reach the state through every place.

Shapes: B batch, S state, nq MuJoCo's qpos. Rotations are (B, 3, 3), positions (B, 3).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np
import torch
from torch import Tensor

from neuroanimator.core.state import LayoutGroup


def quat_to_matrix(q: Tensor) -> Tensor:
    """(..., 4) quaternions [w, x, y, z] (normalised here) → (..., 3, 3) rotation matrices."""
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True).clamp_min(1e-9)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def axis_angle_matrix(axis: Tensor, angle: Tensor) -> Tensor:
    """A fixed unit axis (3,) and angles (B,) → (B, 3, 3) rotations (Rodrigues)."""
    k = torch.zeros(3, 3, dtype=angle.dtype)
    k[0, 1], k[0, 2], k[1, 0] = -axis[2], axis[1], axis[2]
    k[1, 2], k[2, 0], k[2, 1] = -axis[0], -axis[1], axis[0]
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    eye = torch.eye(3, dtype=angle.dtype)
    return eye + s * k + (1 - c) * (k @ k)


def _apply(r: Tensor, v: Tensor) -> Tensor:
    """Rotations (B, 3, 3) applied to vectors (B, 3)."""
    return (r @ v[..., None])[..., 0]


class Kinematics:
    """A model's kinematic tree, read once from its ``MjModel``; ``places(state)`` gives every body's
    world position and rotation for a batch of emulator states laid out as ``layout`` says."""

    def __init__(self, m: mujoco.MjModel, layout: Sequence[LayoutGroup]) -> None:
        self.m = m
        self.qpos0 = torch.tensor(np.asarray(m.qpos0), dtype=torch.float32)
        cols: list[int] = []
        addrs: list[int] = []
        for g in layout:
            if g.source == "qpos":
                cols += range(g.offset, g.offset + g.size)
                addrs += range(g.address, g.address + g.size)
        self.state_cols = torch.tensor(cols, dtype=torch.long)
        self.qpos_addrs = torch.tensor(addrs, dtype=torch.long)

        def f32(a: object) -> Tensor:
            return torch.tensor(np.asarray(a, dtype=np.float64), dtype=torch.float32)

        self.body_pos = f32(m.body_pos)
        self.body_rot = quat_to_matrix(f32(m.body_quat))
        self.joints = [
            (int(m.jnt_type[j]), int(m.jnt_qposadr[j]), f32(m.jnt_axis[j]), f32(m.jnt_pos[j]))
            for j in range(m.njnt)
        ]

    def qpos(self, state: Tensor) -> Tensor:
        """(B, S) states → (B, nq): the state's joint coordinates, MuJoCo's qpos0 for any it omits."""
        q = self.qpos0.to(state.dtype).expand(state.shape[0], -1).clone()
        q[:, self.qpos_addrs] = state[:, self.state_cols]
        return q

    def places(self, state: Tensor) -> tuple[Tensor, Tensor]:
        """(B, S) → body positions (B, nbody, 3) and rotations (B, nbody, 3, 3) in the world frame."""
        m, q = self.m, self.qpos(state)
        b = state.shape[0]
        dtype = state.dtype
        pos: list[Tensor] = [torch.zeros(b, 3, dtype=dtype)]
        rot: list[Tensor] = [torch.eye(3, dtype=dtype).expand(b, 3, 3)]
        for body in range(1, m.nbody):
            parent = int(m.body_parentid[body])
            p = pos[parent] + rot[parent] @ self.body_pos[body].to(dtype)
            r = rot[parent] @ self.body_rot[body].to(dtype)
            first, count = int(m.body_jntadr[body]), int(m.body_jntnum[body])
            for kind, adr, axis, anchor in self.joints[first : first + max(count, 0)]:
                axis, anchor = axis.to(dtype), anchor.to(dtype)
                if kind == mujoco.mjtJoint.mjJNT_FREE:
                    p, r = q[:, adr : adr + 3], quat_to_matrix(q[:, adr + 3 : adr + 7])
                elif kind == mujoco.mjtJoint.mjJNT_BALL:
                    turn = quat_to_matrix(q[:, adr : adr + 4])
                    p = p + _apply(r, anchor - turn @ anchor)
                    r = r @ turn
                elif kind == mujoco.mjtJoint.mjJNT_HINGE:
                    turn = axis_angle_matrix(axis, q[:, adr] - self.qpos0[adr])
                    p = p + _apply(r, anchor - turn @ anchor)
                    r = r @ turn
                else:  # slide
                    p = p + (r @ axis) * (q[:, adr] - self.qpos0[adr])[:, None]
            pos.append(p)
            rot.append(r)
        return torch.stack(pos, dim=1), torch.stack(rot, dim=1)

    def _frame_of(self, kind: mujoco.mjtObj, name: str) -> tuple[int, Tensor, Tensor]:
        """(body, local position (3,), local rotation (3, 3)) of a named body, site or geom."""
        m = self.m
        i = mujoco.mj_name2id(m, kind, name)
        if i < 0:
            raise KeyError(f"the model has no {kind.name[6:].lower()} named {name!r}")
        if kind == mujoco.mjtObj.mjOBJ_BODY:
            return i, torch.zeros(3), torch.eye(3)
        if kind == mujoco.mjtObj.mjOBJ_SITE:
            return (
                int(m.site_bodyid[i]),
                torch.tensor(m.site_pos[i]).float(),
                quat_to_matrix(torch.tensor(m.site_quat[i]).float()),
            )
        return (
            int(m.geom_bodyid[i]),
            torch.tensor(m.geom_pos[i]).float(),
            quat_to_matrix(torch.tensor(m.geom_quat[i]).float()),
        )

    def locator(self, kind: str, name: str) -> Locator:
        """A function of the body places giving the named ``body``, ``site`` or ``geom``'s world
        position (B, 3) and rotation (B, 3, 3)."""
        objs = {
            "body": mujoco.mjtObj.mjOBJ_BODY,
            "site": mujoco.mjtObj.mjOBJ_SITE,
            "geom": mujoco.mjtObj.mjOBJ_GEOM,
        }
        if kind not in objs:
            raise ValueError(f"kind must be one of {sorted(objs)}, got {kind!r}")
        body, local_pos, local_rot = self._frame_of(objs[kind], name)
        return Locator(body, local_pos, local_rot)


class Locator:
    """A named place fixed in one body: ``position(places)`` (B, 3) and ``rotation(places)`` (B, 3, 3)."""

    def __init__(self, body: int, local_pos: Tensor, local_rot: Tensor) -> None:
        self.body, self.local_pos, self.local_rot = body, local_pos, local_rot

    def position(self, places: tuple[Tensor, Tensor]) -> Tensor:
        pos, rot = places
        return pos[:, self.body] + rot[:, self.body] @ self.local_pos.to(pos.dtype)

    def rotation(self, places: tuple[Tensor, Tensor]) -> Tensor:
        _, rot = places
        return rot[:, self.body] @ self.local_rot.to(rot.dtype)
