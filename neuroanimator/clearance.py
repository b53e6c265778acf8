"""Ground clearance: how high each colliding geom's lowest point is above the floor, computed from the
state by forward kinematics inside the emulator's graph.

A body that touches the ground moves under forces that switch on at touchdown and off at lift-off.
Inside a super-step that is a kink, which an MLP of smooth units rounds off; and where a foot is
relative to the floor is a long chain of rotations away from the joint angles a network reads (the
root's height and tilt, hip, knee, ankle). So, as the joint-limit ramps do for limits
(``structured.JointLimit``), the network also reads, for each geom that can touch the floor and for
the state extrapolated at constant velocity to the start, middle and end of the super-step
(``FRACTIONS``), the height of its lowest point above the floor (``clearance``) and how far below the
floor that is (``contact``: a ramp, zero in the air, whose kink sits where contact switches on).

Forward kinematics follows MuJoCo's ``mj_kinematics`` for free, ball, hinge and slide joints, on the
qpos and qvel entries the emulator state holds (the others keep their values at the model's
reference pose). The floor is the highest plane of the world body facing up (+z); a model with no
such plane has no clearance features. Everything is constant matrices, sums, products, sin and cos:
one ONNX graph with the rest of the step.

Shapes: B batch, S state, G probed geoms, K = len(FRACTIONS).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import torch
from torch import Tensor, nn

if TYPE_CHECKING:
    from neuroanimator.physics.model import PhysicalModel

FRACTIONS = (0.0, 0.5, 1.0)  # points of the super-step at which each geom's clearance is computed
_UP_TOLERANCE = 1e-6


def floor_height(m: mujoco.MjModel) -> float | None:
    """The height of the world's highest upward-facing plane, or None when it has none."""
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    heights = [
        float(d.geom_xpos[g][2])
        for g in range(m.ngeom)
        if m.geom_bodyid[g] == 0
        and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE
        and d.geom_xmat[g].reshape(3, 3)[2, 2] > 1.0 - _UP_TOLERANCE
    ]
    return max(heights) if heights else None


def ground_geoms(m: mujoco.MjModel) -> list[str]:
    """The geoms of moving bodies that can collide with the floor plane (contype/conaffinity), by name
    (an unnamed geom is ``geom<id>``); none when the world has no floor."""
    if floor_height(m) is None:
        return []
    floors = [
        g for g in range(m.ngeom) if m.geom_bodyid[g] == 0 and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE
    ]
    out = []
    for g in range(m.ngeom):
        if m.geom_bodyid[g] == 0 or m.geom_type[g] in (
            mujoco.mjtGeom.mjGEOM_PLANE,
            mujoco.mjtGeom.mjGEOM_HFIELD,
        ):
            continue
        touches = any(
            (m.geom_contype[g] & m.geom_conaffinity[f]) or (m.geom_contype[f] & m.geom_conaffinity[g])
            for f in floors
        )
        if touches:
            out.append(geom_name(m, g))
    return out


NEAR_M = 0.05  # a geom whose lowest point comes this close to the floor in the training data is probed


def near_geoms(model: PhysicalModel, states: np.ndarray, horizon: float) -> list[str]:
    """The geoms of ``ground_geoms`` whose lowest point comes within ``NEAR_M`` of the floor in some of
    ``states`` (N, S) (a runner's feet and toes, not its hands): the others never touch it."""
    geoms = ground_geoms(model.mj_model)
    if not geoms:
        return []
    heights = Clearance(model, geoms, horizon)(torch.as_tensor(states, dtype=torch.float32)).detach()
    lowest = heights.reshape(len(states), len(geoms), len(FRACTIONS)).amin(dim=(0, 2))
    return [g for g, h in zip(geoms, lowest.tolist(), strict=True) if h < NEAR_M]


def geom_name(m: mujoco.MjModel, g: int) -> str:
    return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"


def _geom_id(m: mujoco.MjModel, name: str) -> int:
    if (
        name.startswith("geom")
        and name[4:].isdigit()
        and mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name) < 0
    ):
        return int(name[4:])
    g = int(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name))
    if g < 0:
        raise ValueError(f"no geom named {name!r} in the model")
    return g


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(q, float))
    return out.reshape(3, 3)


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


@dataclass(frozen=True)
class _Joint:
    kind: int  # mjtJoint
    qpos: int  # address in qpos
    dof: int  # address in qvel
    axis: np.ndarray  # (3,) in the body frame
    pos: np.ndarray  # (3,) anchor in the body frame
    ref: np.ndarray  # qpos0 of the joint's coordinates


class Clearance(nn.Module):
    """(B, S) states -> (B, G·K) clearances: for geom g (the order of ``geoms``) and fraction k, column
    g·K + k is the height of the geom's lowest point above the floor, the state extrapolated by
    ``FRACTIONS[k]`` of ``horizon`` seconds at constant velocity.

    The graph is kept small and made of 2-D GEMMs by constant matrices and same-shape elementwise
    operations: ONNX Runtime runs batched 3×3 products, products by 1-D operands and broadcasts many
    times slower than those, and every node costs a microsecond or so for a single client. A rotation
    is a row-major (N, 9) row; the states at the K fractions are stacked along the batch."""

    _qpos_sel: Tensor
    _qpos_const: Tensor
    _qvel_sel: Tensor
    _qvel_const: Tensor
    _lin: Tensor
    _ql: Tensor
    _vr: Tensor
    _tot: Tensor
    _hinge_sel: Tensor
    _hinge_ref: Tensor
    _hinge_spread: Tensor
    _reach: Tensor
    _lift: Tensor

    def __init__(self, model: PhysicalModel, geoms: Sequence[str], horizon: float) -> None:
        super().__init__()
        m = model.mj_model
        floor = floor_height(m)
        if floor is None:
            raise ValueError(f"model {model.name}: no floor (an upward-facing plane of the world body)")
        self.floor = floor
        self.geoms = tuple(geoms)
        self.horizon = float(horizon)
        ids = [_geom_id(m, g) for g in self.geoms]
        bad = [g for g, i in zip(self.geoms, ids, strict=True) if m.geom_bodyid[i] == 0]
        if bad or not ids:
            raise ValueError(f"clearance needs geoms of moving bodies; {bad or 'none'} given")
        # the state's columns of each qpos and qvel entry (full physics: time, qpos, qvel, ...)
        S, index, template = model.state_size, model._state_index, model._template

        def picks(first: int, n: int) -> tuple[Tensor, Tensor]:
            sel, const = torch.zeros(S, n), torch.zeros(n)
            for j in range(n):
                cols = np.flatnonzero(index == first + j)
                if cols.size:
                    sel[int(cols[0]), j] = 1.0
                else:
                    const[j] = float(template[first + j])
            return sel, const

        self._buffers_from(
            qpos_sel=picks(1, m.nq)[0], qpos_const=picks(1, m.nq)[1],
            qvel_sel=picks(1 + m.nq, m.nv)[0], qvel_const=picks(1 + m.nq, m.nv)[1],
        )  # fmt: skip
        # the bodies on the way from the world to each probed geom, parents first, and their joints
        need: set[int] = set()
        for g in ids:
            b = int(m.geom_bodyid[g])
            while b > 0:
                need.add(b)
                b = int(m.body_parentid[b])
        self._bodies = sorted(need)
        self._parent = {b: int(m.body_parentid[b]) for b in self._bodies}
        self._joints = {
            b: [
                _Joint(
                    int(m.jnt_type[j]),
                    int(m.jnt_qposadr[j]),
                    int(m.jnt_dofadr[j]),
                    m.jnt_axis[j].copy(),
                    m.jnt_pos[j].copy(),
                    m.qpos0[int(m.jnt_qposadr[j])].reshape(1).copy(),
                )
                for j in range(int(m.body_jntadr[b]), int(m.body_jntadr[b]) + int(m.body_jntnum[b]))
            ]
            for b in self._bodies
        }
        joints = [j for b in self._bodies for j in self._joints[b]]
        self._plan_motion(m, joints)
        self._plan_hinges(joints)
        self._const = {
            b: (torch.tensor(m.body_pos[b], dtype=torch.float32), _mat(m.body_quat[b])) for b in self._bodies
        }
        self._geom_body = [int(m.geom_bodyid[g]) for g in ids]
        self._plan_geoms(m, ids)
        self.width = len(ids) * len(FRACTIONS)

    def _buffers_from(self, **tensors: Tensor) -> None:
        for name, t in tensors.items():
            self.register_buffer(f"_{name}", t, persistent=False)

    def _plan_motion(self, m: mujoco.MjModel, joints: list[_Joint]) -> None:
        """d qpos / dt from (qpos, qvel), as ``qvel @ lin + ((qpos @ ql) * (qvel @ vr)) @ tot``: positions
        move with their velocity, a quaternion q with its local angular velocity ω as ½ q ⊗ (0, ω)."""
        lin = torch.zeros(m.nv, m.nq)
        pairs: list[tuple[int, int, int, float]] = []  # (qpos column, qvel column, output column, sign)
        for j in joints:
            if j.kind in (2, 3):  # slide, hinge
                lin[j.dof, j.qpos] = 1.0
                continue
            quat, omega = (j.qpos + 3, j.dof + 3) if j.kind == 0 else (j.qpos, j.dof)
            if j.kind == 0:
                for i in range(3):
                    lin[j.dof + i, j.qpos + i] = 1.0
            # q ⊗ (0, ω): w' = −x a − y b − z c; x' = w a + y c − z b; y' = w b − x c + z a; z' = w c + x b − y a
            terms = [
                (0, [(1, 0, -1), (2, 1, -1), (3, 2, -1)]),
                (1, [(0, 0, 1), (2, 2, 1), (3, 1, -1)]),
                (2, [(0, 1, 1), (1, 2, -1), (3, 0, 1)]),
                (3, [(0, 2, 1), (1, 1, 1), (2, 0, -1)]),
            ]
            for out, products in terms:
                pairs += [(quat + qi, omega + wi, quat + out, 0.5 * sign) for qi, wi, sign in products]
        ql, vr, tot = (
            torch.zeros(m.nq, len(pairs)),
            torch.zeros(m.nv, len(pairs)),
            torch.zeros(len(pairs), m.nq),
        )
        for c, (qi, wi, out, coef) in enumerate(pairs):
            ql[qi, c], vr[wi, c], tot[c, out] = 1.0, 1.0, coef
        self._turns = bool(pairs)
        self._buffers_from(lin=lin, ql=ql, vr=vr, tot=tot)

    def _plan_hinges(self, joints: list[_Joint]) -> None:
        """All hinge angles in one GEMM; their sines and versines spread over 9 columns each."""
        hinges = [j for j in joints if j.kind == 3]
        self._hinge_at = {j.qpos: k for k, j in enumerate(hinges)}
        ref, spread = torch.zeros(len(hinges)), torch.zeros(len(hinges), 9 * len(hinges))
        sel = torch.zeros(self._qpos_sel.shape[1], len(hinges))
        for k, j in enumerate(hinges):
            sel[j.qpos, k], ref[k] = 1.0, float(j.ref[0])
            spread[k, 9 * k : 9 * k + 9] = 1.0
        self._buffers_from(hinge_sel=sel, hinge_ref=ref, hinge_spread=spread)

    def _plan_geoms(self, m: mujoco.MjModel, ids: list[int]) -> None:
        """Per geom, the (9, 4) map from its body's rotation to the world's z in the geom's axes and the
        height of its centre above the body's origin; the lowest point is then one GEMM away for
        spheres, capsules and boxes (and a mesh's bounding box): ``z − |u| @ reach − lift``."""
        g_count = len(ids)
        self._zrows = []
        reach, lift = torch.zeros(3 * g_count, g_count), torch.zeros(g_count)
        self._curved: list[tuple[int, int, Tensor]] = []  # cylinders and ellipsoids: (geom, kind, size)
        for g, gid in enumerate(ids):
            kind = int(m.geom_type[gid])
            mesh = kind == mujoco.mjtGeom.mjGEOM_MESH
            size = torch.tensor(m.geom_aabb[gid][3:] if mesh else m.geom_size[gid], dtype=torch.float32)
            centre = torch.tensor(m.geom_aabb[gid][:3] if mesh else np.zeros(3), dtype=torch.float32)
            rot = _mat(m.geom_quat[gid])
            zrow = torch.zeros(9, 4)
            zrow[6:9, :3] = rot
            zrow[6:9, 3] = torch.tensor(m.geom_pos[gid], dtype=torch.float32) + rot @ centre
            self._zrows.append(zrow)
            if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
                lift[g] = size[0]
            elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
                reach[3 * g + 2, g], lift[g] = size[1], size[0]
            elif kind in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_ELLIPSOID):
                self._curved.append((g, kind, size))
            else:  # box, mesh
                reach[3 * g : 3 * g + 3, g] = size
        self._buffers_from(reach=reach, lift=lift + self.floor)

    def state_columns(self, g: int) -> set[int]:
        """The state columns (joint positions) on the way from the world to geom ``g``: what moves it."""
        cols: set[int] = set()
        b = self._geom_body[g]
        while b > 0:
            for j in self._joints.get(b, []):
                for k in range(j.qpos, j.qpos + {0: 7, 1: 4}.get(j.kind, 1)):
                    cols.update(int(r) for r in torch.nonzero(self._qpos_sel[:, k]).flatten().tolist())
            b = self._parent.get(b, 0)
        return cols

    # ------------------------------------------------------------------ the graph
    def forward(self, state: Tensor) -> Tensor:
        b = state.shape[0]
        qpos = state @ self._qpos_sel + self._qpos_const
        qvel = state @ self._qvel_sel + self._qvel_const
        rate = qvel @ self._lin
        if self._turns:
            rate = rate + ((qpos @ self._ql) * (qvel @ self._vr)) @ self._tot
        q = torch.cat([qpos if a == 0.0 else qpos + (a * self.horizon) * rate for a in FRACTIONS], dim=0)
        n = q.shape[0]
        theta = q @ self._hinge_sel - self._hinge_ref  # (K·B, H)
        sin9, vers9 = torch.sin(theta) @ self._hinge_spread, (1.0 - torch.cos(theta)) @ self._hinge_spread
        rot: dict[int, Tensor | None] = {0: None}  # the world: identity, at the origin
        pos: dict[int, Tensor | None] = {0: None}
        for body in self._bodies:
            body_pos, body_rot = self._const[body]
            r, p = rot[self._parent[body]], pos[self._parent[body]]
            p = _place(r, p, body_pos, n)
            r = _times_const(r, body_rot, n)
            for j in self._joints[body]:
                if j.kind == 0:  # free
                    p, r = q[:, j.qpos : j.qpos + 3], _quat_matrix(q[:, j.qpos + 3 : j.qpos + 7])
                elif j.kind == 1:  # ball
                    r = _times(r, _quat_matrix(q[:, j.qpos : j.qpos + 4]))
                elif (
                    j.kind == 3
                ):  # hinge, about the axis through its anchor: R·(I + sin θ K + (1 − cos θ) K²)
                    k, anchor = (
                        torch.tensor(_skew(j.axis), dtype=torch.float32),
                        torch.tensor(j.pos, dtype=torch.float32),
                    )
                    h = 9 * self._hinge_at[j.qpos]
                    a = _place(r, p, anchor, n)
                    r_full = r if r is not None else torch.eye(3).reshape(1, 9).expand(n, 9)
                    r = (
                        r_full
                        + sin9[:, h : h + 9] * _times_const(r, k, n)
                        + vers9[:, h : h + 9] * _times_const(r, k @ k, n)
                    )
                    p = a - r @ _apply_matrix(anchor)
                else:  # slide
                    axis = torch.tensor(j.axis, dtype=torch.float32)
                    shift = _place(r, None, axis, n) * (
                        (q[:, j.qpos : j.qpos + 1] - float(j.ref[0])) @ _ONES9[:, :3]
                    )
                    p = shift if p is None else p + shift
            rot[body], pos[body] = r, p
        ups, heights = [], []
        for g, body in enumerate(self._geom_body):
            r, p = rot[body], pos[body]
            assert r is not None and p is not None  # a moving body has a joint above it
            out = r @ self._zrows[g]  # (N, 4): the world's z in the geom's axes, its centre's height
            ups.append(out[:, :3])
            heights.append(p[:, 2:3] + out[:, 3:4])
        up = torch.cat(ups, dim=1)  # (N, 3G)
        low = torch.cat(heights, dim=1) - up.abs() @ self._reach - self._lift  # (N, G)
        for g, kind, size in self._curved:
            u = up[:, 3 * g : 3 * g + 3]
            extra = _reach(kind, u, size)
            low = low - extra[:, None] @ torch.eye(len(self.geoms))[g : g + 1]
        # (K·B, G) fraction-major -> (B, G·K), geom-major
        return low.reshape(len(FRACTIONS), b, -1).permute(1, 2, 0).reshape(b, -1)


def _apply_matrix(v: Tensor) -> Tensor:
    """(9, 3) M with ``R9 @ M == R·v`` for row-major rotations R9 (N, 9) and a constant (3,) vector v."""
    m = torch.zeros(9, 3)
    for i in range(3):
        m[3 * i : 3 * i + 3, i] = v
    return m


def _place(r: Tensor | None, p: Tensor | None, v: Tensor, n: int) -> Tensor:
    """p + r·v for a frame (r, p) (None: the world's identity, origin) and a constant vector v: (N, 3)."""
    moved = v.expand(n, 3) if r is None else r @ _apply_matrix(v)
    return moved if p is None else p + moved


def _times_const(r: Tensor | None, m: Tensor, n: int) -> Tensor:
    """Row-major rotations (N, 9) (None: identity) times a constant (3, 3): (N, 9), one GEMM by I ⊗ M."""
    if r is None:
        return m.reshape(1, 9).expand(n, 9)
    return r @ torch.kron(torch.eye(3), m)


_ONES9 = torch.ones(1, 9)
_PAIRS = [(i, k, j) for i in range(3) for j in range(3) for k in range(3)]


def _times(r: Tensor | None, m: Tensor) -> Tensor:
    """Row-major (N, 9) times (N, 9): the 27 products of pairs by two GEMMs, summed by a third."""
    if r is None:
        return m
    left, right, total = torch.zeros(9, 27), torch.zeros(9, 27), torch.zeros(27, 9)
    for c, (i, k, j) in enumerate(_PAIRS):
        left[3 * i + k, c] = right[3 * k + j, c] = total[c, 3 * i + j] = 1.0
    return ((r @ left) * (m @ right)) @ total


def _mat(quat: np.ndarray) -> Tensor:
    return torch.tensor(_quat_to_mat(quat), dtype=torch.float32)


def _reach(kind: int, up: Tensor, size: Tensor) -> Tensor:
    """How far below its centre a geom reaches along the world's z, given the z axis in the geom's
    frame ``up`` (N, 3)."""
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return size[0].expand(up.shape[0])
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return up[:, 2].abs() * size[1] + size[0]
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return up[:, 2].abs() * size[1] + size[0] * torch.sqrt(torch.clamp(1.0 - up[:, 2] ** 2, min=0.0))
    if kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        return torch.sqrt(((up * size) ** 2).sum(dim=1))
    return (up.abs() * size).sum(dim=1)  # box, and a mesh's bounding box


def _quat_matrix(q: Tensor) -> Tensor:
    """(N, 4) quaternions (w, x, y, z), normalised here -> (N, 9) row-major rotation matrices."""
    q = q / torch.linalg.vector_norm(q, dim=1, keepdim=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=1)
