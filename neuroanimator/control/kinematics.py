"""Forward kinematics in torch: where a model's bodies, sites and geoms are, and how they are turned,
as differentiable functions of the emulator's state.

A reward or a task's term speaks of places (a fingertip's distance to a target, a pole's height, a
torso's up vector); the emulator predicts joint coordinates. ``Kinematics`` walks MuJoCo's kinematic
tree as ``mj_kinematics`` does (each body placed in its parent's frame at ``body_pos``/``body_quat``,
then moved by its joints: a hinge turns about its axis through its anchor, a slide moves along its
axis, both by ``qpos − qpos0``; a ball joint turns by its quaternion; a free joint sets the body's
world position and orientation), so that gradients reach the state through every place. A
subtree's centre-of-mass velocity (MuJoCo's ``subtree_linvel``, what the suite's locomotion rewards
pay for) follows from each body's twist, propagated down the same walk from the state's joint
velocities as ``mj_comVel`` does.

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


def _columns(layout: Sequence[LayoutGroup], source: str) -> tuple[Tensor, Tensor]:
    """The state's columns holding entries of MuJoCo's ``source`` (qpos or qvel), and their addresses there."""
    cols: list[int] = []
    addrs: list[int] = []
    for g in layout:
        if g.source == source:
            cols += range(g.offset, g.offset + g.size)
            addrs += range(g.address, g.address + g.size)
    return torch.tensor(cols, dtype=torch.long), torch.tensor(addrs, dtype=torch.long)


class Kinematics:
    """A model's kinematic tree, read once from its ``MjModel``; ``places(state)`` gives every body's
    world position and rotation for a batch of emulator states laid out as ``layout`` says."""

    def __init__(self, m: mujoco.MjModel, layout: Sequence[LayoutGroup]) -> None:
        self.m = m
        self.qpos0 = torch.tensor(np.asarray(m.qpos0), dtype=torch.float32)
        self.state_cols, self.qpos_addrs = _columns(layout, "qpos")
        self.vel_cols, self.qvel_addrs = _columns(layout, "qvel")

        def f32(a: object) -> Tensor:
            return torch.tensor(np.asarray(a, dtype=np.float64), dtype=torch.float32)

        self.body_pos = f32(m.body_pos)
        self.body_rot = quat_to_matrix(f32(m.body_quat))
        self.joints = [
            (int(m.jnt_type[j]), int(m.jnt_qposadr[j]), f32(m.jnt_axis[j]), f32(m.jnt_pos[j]))
            for j in range(m.njnt)
        ]
        self.joint_dofs = [int(m.jnt_dofadr[j]) for j in range(m.njnt)]
        self.body_ipos = f32(m.body_ipos)
        self.body_mass = f32(m.body_mass)
        # the last batch walked outside autograd: its state, the state's version, its places
        self._last: tuple[Tensor, int, tuple[Tensor, Tensor]] | None = None

    def qpos(self, state: Tensor) -> Tensor:
        """(B, S) states → (B, nq): the state's joint coordinates, MuJoCo's qpos0 for any it omits."""
        q = self.qpos0.to(state.dtype).expand(state.shape[0], -1).clone()
        q[:, self.qpos_addrs] = state[:, self.state_cols]
        return q

    def places(self, state: Tensor) -> tuple[Tensor, Tensor]:
        """(B, S) → body positions (B, nbody, 3) and rotations (B, nbody, 3, 3) in the world frame.

        Outside autograd the last batch's places are kept and given again for the same unchanged
        tensor: a planner scores each state by two rewards (exact and smooth), each of which walks
        the tree, and the walk costs as much as the emulator's step."""
        if torch.is_grad_enabled():
            return self.places_at(self.qpos(state))
        last = self._last
        if last is not None and last[0] is state and last[1] == state._version:
            return last[2]
        out = self.places_at(self.qpos(state))
        self._last = (state, state._version, out)
        return out

    def subtree(self, name: str) -> list[int]:
        """The named body and every body below it."""
        m = self.m
        root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
        if root < 0:
            raise KeyError(f"the model has no body named {name!r}")
        inside = [root]
        for body in range(root + 1, m.nbody):  # (MuJoCo numbers a parent before its children)
            if int(m.body_parentid[body]) in inside:
                inside.append(body)
        return inside

    def subtree_velocity(self, state: Tensor, name: str) -> Tensor:
        """(B, S) → (B, 3) the velocity of the named body's subtree's centre of mass (MuJoCo's
        ``subtree_linvel``, the suite's ``subtreelinvel`` sensor): each body's centre of mass moving
        with its body's twist, weighted by the bodies' masses."""
        v = torch.zeros(state.shape[0], self.m.nv, dtype=state.dtype)
        v[:, self.qvel_addrs] = state[:, self.vel_cols]
        pos, rot, twists = self._walk(self.qpos(state), v)
        assert twists is not None
        idx = torch.tensor(self.subtree(name), dtype=torch.long)
        centres = pos[:, idx] + (rot[:, idx] @ self.body_ipos[idx].to(state.dtype)[..., None])[..., 0]
        vo, om = twists
        moving = vo[:, idx] + torch.linalg.cross(om[:, idx], centres)  # (B, k, 3)
        mass = self.body_mass[idx].to(state.dtype)
        return (moving * mass[:, None]).sum(dim=1) / mass.sum().clamp_min(1e-12)

    def places_at(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """(B, nq) joint coordinates → body positions (B, nbody, 3) and rotations (B, nbody, 3, 3)."""
        pos, rot, _ = self._walk(q, None)
        return pos, rot

    def _walk(self, q: Tensor, qd: Tensor | None) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor] | None]:
        """The tree walked once: body positions (B, nbody, 3) and rotations (B, nbody, 3, 3), and with
        joint velocities ``qd`` (B, nv) each body's twist (MuJoCo's ``cvel`` about the world's origin):
        ``v_o`` (B, nbody, 3), the velocity of the body's point at the origin, and ``ω`` (B, nbody, 3),
        so that a point x of the body moves at ``v_o + ω × x``. A hinge turning at rate q̇ about a
        world axis a through a point c adds ω_j = q̇·a and c × ω_j; a slide adds q̇·a to ``v_o``; a
        ball joint its local rate turned into the world; a free joint sets both."""
        m = self.m
        b = q.shape[0]
        dtype = q.dtype
        zero = torch.zeros(b, 3, dtype=dtype)
        pos: list[Tensor] = [zero]
        rot: list[Tensor] = [torch.eye(3, dtype=dtype).expand(b, 3, 3)]
        vo: list[Tensor] = [zero]
        om: list[Tensor] = [zero]
        for body in range(1, m.nbody):
            parent = int(m.body_parentid[body])
            p = pos[parent] + rot[parent] @ self.body_pos[body].to(dtype)
            r = rot[parent] @ self.body_rot[body].to(dtype)
            v, w = vo[parent], om[parent]
            first, count = int(m.body_jntadr[body]), int(m.body_jntnum[body])
            for j, (kind, adr, axis, anchor) in enumerate(self.joints[first : first + max(count, 0)]):
                axis, anchor = axis.to(dtype), anchor.to(dtype)
                dof = self.joint_dofs[first + j]
                pivot = p + _apply(r, anchor)  # (the joint's anchor in the world: the turn leaves it)
                if kind == mujoco.mjtJoint.mjJNT_FREE:
                    p, r = q[:, adr : adr + 3], quat_to_matrix(q[:, adr + 3 : adr + 7])
                    if qd is not None:
                        w = _apply(r, qd[:, dof + 3 : dof + 6])
                        v = qd[:, dof : dof + 3] - torch.linalg.cross(w, p)
                elif kind == mujoco.mjtJoint.mjJNT_BALL:
                    turn = quat_to_matrix(q[:, adr : adr + 4])
                    p = p + _apply(r, anchor - turn @ anchor)
                    r = r @ turn
                    if qd is not None:
                        wj = _apply(r, qd[:, dof : dof + 3])
                        w, v = w + wj, v + torch.linalg.cross(pivot, wj)
                elif kind == mujoco.mjtJoint.mjJNT_HINGE:
                    if qd is not None:
                        wj = _apply(r, axis.expand(b, 3)) * qd[:, dof : dof + 1]
                        w, v = w + wj, v + torch.linalg.cross(pivot, wj)
                    turn = axis_angle_matrix(axis, q[:, adr] - self.qpos0[adr])
                    p = p + _apply(r, anchor - turn @ anchor)
                    r = r @ turn
                else:  # slide
                    world_axis = r @ axis
                    p = p + world_axis * (q[:, adr] - self.qpos0[adr])[:, None]
                    if qd is not None:
                        v = v + world_axis * qd[:, dof : dof + 1]
            pos.append(p)
            rot.append(r)
            vo.append(v)
            om.append(w)
        twists = (torch.stack(vo, dim=1), torch.stack(om, dim=1)) if qd is not None else None
        return torch.stack(pos, dim=1), torch.stack(rot, dim=1), twists

    def _frame_of(self, kind: mujoco.mjtObj, name: str) -> tuple[int, Tensor, Tensor]:
        """(body, local position (3,), local rotation (3, 3)) of a named body, site or geom."""
        m = self.m
        i = mujoco.mj_name2id(
            m, mujoco.mjtObj.mjOBJ_BODY if kind == mujoco.mjtObj.mjOBJ_XBODY else kind, name
        )
        if i < 0:
            raise KeyError(f"the model has no {kind.name[6:].lower()} named {name!r}")
        if kind == mujoco.mjtObj.mjOBJ_BODY:
            return i, torch.zeros(3), torch.eye(3)
        if kind == mujoco.mjtObj.mjOBJ_XBODY:  # (here: the body's centre of mass, MuJoCo's xipos)
            return (
                i,
                torch.tensor(m.body_ipos[i]).float(),
                quat_to_matrix(torch.tensor(m.body_iquat[i]).float()),
            )
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
        position (B, 3) and rotation (B, 3, 3); ``inertial``: the named body's centre of mass and
        principal axes (MuJoCo's ``xipos``, ``ximat``)."""
        objs = {
            "body": mujoco.mjtObj.mjOBJ_BODY,
            "inertial": mujoco.mjtObj.mjOBJ_XBODY,
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
