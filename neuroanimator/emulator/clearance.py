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

The same forward kinematics also gives, after the floor's columns, the distance between the surfaces
of named pairs of geoms (``pairs``, ``neuroanimator.emulator.proximity``: two bodies that touch each other) and
the slack of limited tendons strung through sites (``tendons``: the upper limit less the tendon's
length), each at the same fractions; negative is overlap, or a string pulled past its limit.

Shapes: B batch, S state, G probed geoms, P pairs, T tendons, K = len(FRACTIONS).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import torch
from torch import Tensor, nn

from neuroanimator.emulator import proximity

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

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
TOUCH_M = 0.01  # a geom whose lowest point is this close to the floor touches it
MOVES_M = 0.01  # a geom whose height spans less than this over the data slides on the floor (a planar arm)
TOUCH_SHARE = 0.2  # with at least this share of sampled states touching, the emulator reads the clearance
PROBE_CHUNK = 50_000  # states probed at a time


@dataclass(frozen=True)
class FloorContact:
    """How a model's sampled states meet its floor: the geoms that come within ``NEAR_M`` of it, and the
    share of states (0..1, of ``states``) in which a geom that moves up and down (its height spans
    ``MOVES_M`` or more) touches it (within ``TOUCH_M``); a geom that only slides along it (a planar
    arm) never makes or breaks contact, and does not count."""

    geoms: tuple[str, ...]
    touching: float
    states: int
    floor: bool = True  # False: the model has no floor (``ground_geoms`` finds none)

    @property
    def touches(self) -> bool:
        """Whether the floor is touched often enough that the emulator should read the clearance."""
        return self.touching >= TOUCH_SHARE

    def describe(self) -> str:
        if not self.floor:
            return "the model has no floor"
        if not self.geoms:
            return f"no geom comes within {NEAR_M * 100:.0f} cm of the floor in {self.states} sampled states"
        return (
            f"the floor touched in {self.touching:.0%} of {self.states} sampled states "
            f"(near it: {', '.join(self.geoms)})"
        )


def floor_contact(model: PhysicalModel, states: np.ndarray, horizon: float) -> FloorContact:
    """How ``states`` (N, S) of ``model`` meet its floor over super-steps of ``horizon`` seconds
    (``FloorContact``); no geoms and no touching for a model without a floor."""
    geoms = ground_geoms(model.mj_model)
    if not geoms or not len(states):
        return FloorContact((), 0.0, len(states), floor=bool(geoms))
    clearance = Clearance(model, geoms, horizon)
    lowest = torch.full((len(geoms),), torch.inf)
    highest = torch.full((len(geoms),), -torch.inf)
    lows = []  # (N, G): each state's lowest point of each geom over the super-step
    # in chunks: the forward kinematics holds about 16 kB a state, 26 GB for the runner's 1.6 million
    with torch.no_grad():
        for start in range(0, len(states), PROBE_CHUNK):
            chunk = torch.as_tensor(states[start : start + PROBE_CHUNK], dtype=torch.float32)
            heights = clearance(chunk).reshape(len(chunk), len(geoms), len(FRACTIONS))
            lowest = torch.minimum(lowest, heights.amin(dim=(0, 2)))
            highest = torch.maximum(highest, heights.amax(dim=(0, 2)))
            lows.append(heights.amin(dim=2))
    low = torch.cat(lows)
    moving = (highest - lowest) >= MOVES_M
    touching = (low[:, moving] < TOUCH_M).any(dim=1).float().mean().item() if moving.any() else 0.0
    near = tuple(g for g, h in zip(geoms, lowest.tolist(), strict=True) if h < NEAR_M)
    return FloorContact(near, touching, len(states))


def near_geoms(model: PhysicalModel, states: np.ndarray, horizon: float) -> list[str]:
    """The geoms of ``ground_geoms`` whose lowest point comes within ``NEAR_M`` of the floor in some of
    ``states`` (N, S) (a runner's feet and toes, not its hands): the others never touch it."""
    return list(floor_contact(model, states, horizon).geoms)


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
    """(B, S) states -> (B, (G + P + T)·K) clearances: for geom g (the order of ``geoms``) and fraction
    k, column g·K + k is the height of the geom's lowest point above the floor, the state extrapolated
    by ``FRACTIONS[k]`` of ``horizon`` seconds at constant velocity; then, in the same layout, the
    distance between each of ``pairs``' two geoms and the slack of each of ``tendons``.

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
    _pair_fixed: Tensor
    _pair_c1: Tensor
    _pair_d1: Tensor
    _pair_c2: Tensor
    _pair_d2: Tensor
    _pair_radii: Tensor
    _pair_total: Tensor
    _seg_sum: Tensor
    _tendon_high: Tensor

    def __init__(
        self,
        model: PhysicalModel,
        geoms: Sequence[str],
        horizon: float,
        pairs: Sequence[tuple[str, str]] = (),
        tendons: Sequence[str] = (),
    ) -> None:
        super().__init__()
        m = model.mj_model
        floor = floor_height(m)
        if floor is None and geoms:
            raise ValueError(f"model {model.name}: no floor (an upward-facing plane of the world body)")
        self.floor = floor or 0.0
        self.geoms = tuple(geoms)
        self.pairs = tuple((a, b) for a, b in pairs)
        self.tendons = tuple(tendons)
        self.horizon = float(horizon)
        ids, pair_ids, segments, high = self._probed(m)
        self._plan_state_columns(model)
        joints = self._plan_bodies(m, ids, pair_ids, segments)
        self._plan_motion(m, joints)
        self._const = {
            b: (torch.tensor(m.body_pos[b], dtype=torch.float32), _mat(m.body_quat[b])) for b in self._bodies
        }
        self._plan_levels(joints)
        self._geom_body = [int(m.geom_bodyid[g]) for g in ids]
        self._plan_geoms(m, ids)
        self._plan_pairs(m, [(("geom", i), ("geom", j)) for i, j in pair_ids] + segments)
        self._plan_tendons(m, len(segments), high)
        self.width = (len(ids) + len(pair_ids) + len(self.tendons)) * len(FRACTIONS)

    def _probed(
        self, m: mujoco.MjModel
    ) -> tuple[list[int], list[tuple[int, int]], list[tuple[Anchor, Anchor]], list[float]]:
        """The ids of the probed geoms and of the pairs' geoms, the straight segments of the limited
        tendons through sites (each a pair of points) and each tendon's upper limit; checked: the geoms
        are on moving bodies, there is something to probe, and each pair has a moving geom."""
        ids = [_geom_id(m, g) for g in self.geoms]
        bad = [g for g, i in zip(self.geoms, ids, strict=True) if m.geom_bodyid[i] == 0]
        if bad or not (ids or self.pairs or self.tendons):
            raise ValueError(f"clearance needs geoms of moving bodies; {bad or 'none'} given")
        pair_ids = [(_geom_id(m, a), _geom_id(m, b)) for a, b in self.pairs]
        # a limited tendon through sites: its straight segments, each a pair of points
        segments, high = tendon_segments(m, self.tendons)
        still = [
            f"{a}-{b}"
            for (a, b), (i, j) in zip(self.pairs, pair_ids, strict=True)
            if not (m.geom_bodyid[i] or m.geom_bodyid[j])
        ]
        if still:
            raise ValueError(f"proximity needs a moving geom in each pair; {still} are both fixed")
        return ids, pair_ids, segments, high

    def _plan_state_columns(self, model: PhysicalModel) -> None:
        """``state @ _qpos_sel + _qpos_const`` (B, nq) is qpos: the state's column of each entry, the
        model's reference value of those the state does not hold (full physics: time, qpos, qvel, ...);
        the same for qvel (B, nv)."""
        m, S, index, template = model.mj_model, model.state_size, model._state_index, model._template

        def picks(first: int, n: int) -> tuple[Tensor, Tensor]:
            sel, const = torch.zeros(S, n), torch.zeros(n)
            for j in range(n):
                cols = np.flatnonzero(index == first + j)
                if cols.size:
                    sel[int(cols[0]), j] = 1.0
                else:
                    const[j] = float(template[first + j])
            return sel, const

        qpos_sel, qpos_const = picks(1, m.nq)
        qvel_sel, qvel_const = picks(1 + m.nq, m.nv)
        self._buffers_from(qpos_sel=qpos_sel, qpos_const=qpos_const, qvel_sel=qvel_sel, qvel_const=qvel_const)

    def _plan_bodies(
        self,
        m: mujoco.MjModel,
        ids: list[int],
        pair_ids: list[tuple[int, int]],
        segments: list[tuple[Anchor, Anchor]],
    ) -> list[_Joint]:
        """The bodies on the way from the world to each probed geom and point, parents first, their
        parents and their joints; returns the joints, in the bodies' order."""
        need: set[int] = set()
        anchors = [("geom", g) for pair in pair_ids for g in pair] + [a for seg in segments for a in seg]
        for b in [int(m.geom_bodyid[g]) for g in ids] + [_anchor_body(m, a) for a in anchors]:
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
        return [j for b in self._bodies for j in self._joints[b]]

    def _plan_tendons(self, m: mujoco.MjModel, num_segments: int, high: list[float]) -> None:
        """``slack = high - lengths @ _seg_sum``: ``_seg_sum`` (segments, T) adds up each tendon's
        segments, ``_tendon_high`` (T,) its upper limit."""
        seg_sum = torch.zeros(num_segments, len(self.tendons))
        at = 0
        for t, name in enumerate(self.tendons):
            count = len(tendon_segments(m, [name])[0])
            seg_sum[at : at + count, t] = 1.0
            at += count
        self._buffers_from(seg_sum=seg_sum, tendon_high=torch.tensor(high, dtype=torch.float32))

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

    def _plan_geoms(self, m: mujoco.MjModel, ids: list[int]) -> None:
        """Per geom, the (9, 4) map from its body's rotation to the world's z in the geom's axes and the
        height of its centre above the body's origin; the lowest point is then one GEMM away for
        spheres, capsules and boxes (and a mesh's bounding box): ``z − |u| @ reach − lift``."""
        g_count = len(ids)
        self._zrows = []
        reach, lift = torch.zeros(3 * g_count, g_count), torch.zeros(g_count)
        # cylinders and ellipsoids: (geom, kind, size, the (1, G) row that puts their term in place)
        self._curved: list[tuple[int, int, Tensor, Tensor]] = []
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
                self._curved.append((g, kind, size, torch.eye(g_count)[g : g + 1]))
            else:  # box, mesh
                reach[3 * g : 3 * g + 3, g] = size
        self._buffers_from(reach=reach, lift=lift + self.floor)
        # per level with geoms: (9·C, 4G) from its rotations and (3·C, 4G) from its positions
        self._geom_maps: list[tuple[int, Tensor, Tensor]] = []
        widths = {lv + 1: lvl.c for lv, lvl in enumerate(self._levels)}
        for lv in sorted({self._frame_of[self._geom_body[g]][0] for g in range(g_count)}):
            from_rot, from_pos = (
                torch.zeros(9 * widths[lv], 4 * g_count),
                torch.zeros(3 * widths[lv], 4 * g_count),
            )
            for g in range(g_count):
                at, col = self._frame_of[self._geom_body[g]]
                if at != lv:
                    continue
                from_rot[9 * col : 9 * col + 9, 3 * g : 3 * g + 3] = self._zrows[g][:, :3]
                from_rot[9 * col : 9 * col + 9, 3 * g_count + g] = self._zrows[g][:, 3]
                from_pos[3 * col + 2, 3 * g_count + g] = 1.0
            self._geom_maps.append((lv, from_rot, from_pos))

    def _plan_pairs(self, m: mujoco.MjModel, pairs: list[tuple[Anchor, Anchor]]) -> None:
        """Per level, the (9·C, 6H) and (3·C, 6H) maps from its frames to the world centre (3) and
        half-extent (3) of each of the H geoms or sites in some pair (``proximity.swept``; a site is a
        point), a (6H,) constant for the world's own, and the selections from those to the pairs' two
        sides."""
        unique = sorted({a for pair in pairs for a in pair})
        h_count, p_count = len(unique), len(pairs)
        at = {a: h for h, a in enumerate(unique)}
        shapes = [proximity.swept(m, a[1]) if a[0] == "geom" else proximity.POINT for a in unique]
        fixed = torch.zeros(6 * h_count)
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        widths = {lv + 1: lvl.c for lv, lvl in enumerate(self._levels)}
        maps: dict[int, tuple[Tensor, Tensor]] = {}
        for h, (a, sw) in enumerate(zip(unique, shapes, strict=True)):
            kind, i = a
            rot = _mat(m.geom_quat[i] if kind == "geom" else m.site_quat[i])
            pos = m.geom_pos[i] if kind == "geom" else m.site_pos[i]
            centre = torch.tensor(pos, dtype=torch.float32) + rot @ torch.tensor(
                sw.centre, dtype=torch.float32
            )
            half = rot @ torch.tensor(sw.axis * sw.half, dtype=torch.float32)
            body = _anchor_body(m, a)
            if body == 0:  # fixed in the world: its pose at any configuration
                xpos, xmat = (
                    (d.geom_xpos[i], d.geom_xmat[i]) if kind == "geom" else (d.site_xpos[i], d.site_xmat[i])
                )
                world = torch.tensor(xmat.reshape(3, 3), dtype=torch.float32)
                fixed[3 * h : 3 * h + 3] = torch.tensor(xpos, dtype=torch.float32) + world @ torch.tensor(
                    sw.centre, dtype=torch.float32
                )
                fixed[3 * h_count + 3 * h : 3 * h_count + 3 * h + 3] = world @ torch.tensor(
                    sw.axis * sw.half, dtype=torch.float32
                )
                continue
            lv, col = self._frame_of[body]
            if lv not in maps:
                maps[lv] = (
                    torch.zeros(9 * widths[lv], 6 * h_count),
                    torch.zeros(3 * widths[lv], 6 * h_count),
                )
            from_rot, from_pos = maps[lv]
            from_rot[9 * col : 9 * col + 9, 3 * h : 3 * h + 3] = _apply_matrix(centre)
            from_rot[9 * col : 9 * col + 9, 3 * h_count + 3 * h : 3 * h_count + 3 * h + 3] = _apply_matrix(
                half
            )
            from_pos[3 * col : 3 * col + 3, 3 * h : 3 * h + 3] = torch.eye(3)
        self._pair_maps = sorted((lv, r, p) for lv, (r, p) in maps.items())
        side = {k: torch.zeros(6 * h_count, 3 * p_count) for k in ("c1", "d1", "c2", "d2")}
        radii = torch.zeros(p_count)
        for p, (one, two) in enumerate(pairs):
            for k in range(3):
                side["c1"][3 * at[one] + k, 3 * p + k] = side["c2"][3 * at[two] + k, 3 * p + k] = 1.0
                side["d1"][3 * h_count + 3 * at[one] + k, 3 * p + k] = 1.0
                side["d2"][3 * h_count + 3 * at[two] + k, 3 * p + k] = 1.0
            radii[p] = shapes[at[one]].radius + shapes[at[two]].radius
        self._buffers_from(
            pair_fixed=fixed, pair_c1=side["c1"], pair_d1=side["d1"], pair_c2=side["c2"], pair_d2=side["d2"],
            pair_radii=radii, pair_total=proximity.sum_matrix(p_count),
        )  # fmt: skip

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
    def _plan_levels(self, joints: list[_Joint]) -> None:
        """Group the frames into levels computed together. Every joint is a step from one frame to the
        next (a body's first joint also applies the body's offset from its parent; a body without
        joints is one step of its offset); a step's level is one more than its input's, the world being
        level 0. The steps of one level (the hips of both legs and the shoulders, say) are one GEMM of
        the level before's rotations by a constant block matrix and a few elementwise operations on all
        of them at once, so the graph grows with the depth of the tree, not its size."""
        steps: list[dict[str, object]] = []  # in body order: a parent's steps come before its children's
        last: dict[int, int] = {}  # body -> index of its last step (its frame)
        for body in self._bodies:
            pos, rot = self._const[body]
            parent = self._parent[body]
            source = last.get(parent, -1)
            offset, turn = pos, rot
            for j in self._joints[body] or [None]:  # type: ignore[list-item]
                level = 1 + (steps[source]["level"] if source >= 0 else 0)  # type: ignore[operator]
                kind = "weld" if j is None else {0: "free", 1: "ball", 2: "slide", 3: "hinge"}[j.kind]
                steps.append(
                    {"kind": kind, "joint": j, "rot": turn, "offset": offset, "input": source, "level": level}
                )
                source = len(steps) - 1
                offset, turn = torch.zeros(3), torch.eye(3)
            last[body] = source
        depth = max(int(st["level"]) for st in steps)  # type: ignore[call-overload]
        cols: dict[int, tuple[int, int]] = {}  # step -> (level, column within its level)
        per_level: list[list[int]] = [[] for _ in range(depth + 1)]
        for i, st in enumerate(steps):
            lv = int(st["level"])  # type: ignore[call-overload]
            cols[i] = (lv, len(per_level[lv]))
            per_level[lv].append(i)
        nq = self._qpos_sel.shape[1]
        # hinge angles ordered by level, so that a level's sines are one slice of all of them
        hinges = [i for lv in per_level for i in lv if steps[i]["kind"] == "hinge"]
        hsel, href = torch.zeros(nq, len(hinges)), torch.zeros(len(hinges))
        spread = torch.zeros(len(hinges), 9 * len(hinges))
        for h, i in enumerate(hinges):
            hinge = steps[i]["joint"]
            assert isinstance(hinge, _Joint)
            hsel[hinge.qpos, h], href[h] = 1.0, float(hinge.ref[0])
            spread[h, 9 * h : 9 * h + 9] = 1.0
        self._buffers_from(hinge_sel=hsel, hinge_ref=href, hinge_spread=spread)
        self._levels: list[_Level] = []
        hinge_at = 0
        for lv in range(1, depth + 1):
            ids = per_level[lv]
            c, c_in = len(ids), len(per_level[lv - 1]) if lv > 1 else 0
            lvl = _Level(c, c_in, nq)
            for k, i in enumerate(ids):
                lvl.add(k, steps[i], cols[int(steps[i]["input"])][1] if int(steps[i]["input"]) >= 0 else -1)  # type: ignore[call-overload]
            lvl.hinges = (9 * hinge_at, 9 * (hinge_at + sum(1 for i in ids if steps[i]["kind"] == "hinge")))
            # a level's hinges are in the order of its columns; the spread of all puts each in its column
            order = [k for k, i in enumerate(ids) if steps[i]["kind"] == "hinge"]
            lvl.hinge_place = torch.zeros(9 * len(order), 9 * c)
            for h, k in enumerate(order):
                lvl.hinge_place[9 * h : 9 * h + 9, 9 * k : 9 * k + 9] = torch.eye(9)
            hinge_at += len(order)
            lvl.finish()
            self._levels.append(lvl)
        self._frame_of = {body: cols[last[body]] for body in self._bodies}

    def forward(self, state: Tensor) -> Tensor:
        b = state.shape[0]
        qpos = state @ self._qpos_sel + self._qpos_const
        qvel = state @ self._qvel_sel + self._qvel_const
        rate = qvel @ self._lin
        if self._turns:
            rate = rate + ((qpos @ self._ql) * (qvel @ self._vr)) @ self._tot
        q = torch.cat([qpos if a == 0.0 else qpos + (a * self.horizon) * rate for a in FRACTIONS], dim=0)
        n = q.shape[0]
        theta = q @ self._hinge_sel - self._hinge_ref  # (K·B, H), ordered by level
        sin9, vers9 = torch.sin(theta) @ self._hinge_spread, (1.0 - torch.cos(theta)) @ self._hinge_spread
        r: Tensor | None = None  # the world: identity, at the origin
        p: Tensor | None = None
        frames: list[tuple[Tensor, Tensor]] = []
        for lvl in self._levels:
            r, p = lvl.step(r, p, q, sin9, vers9, n)
            frames.append((r, p))
        parts = []
        if self.geoms:
            parts.append(self._heights(frames))
        if self.pairs or self.tendons:
            gaps = self._gaps(frames, n)
            p_count = len(self.pairs)
            if p_count:
                parts.append(gaps[:, :p_count])
            if self.tendons:  # how much slack is left before the limit: negative past it
                parts.append(self._tendon_high - gaps[:, p_count:] @ self._seg_sum)
        out = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
        # (K·B, G + P + T) fraction-major -> (B, (G + P + T)·K), geom-major
        return out.reshape(len(FRACTIONS), b, -1).permute(1, 2, 0).reshape(b, -1)

    def _heights(self, frames: list[tuple[Tensor, Tensor]]) -> Tensor:
        """(N, G) heights of the probed geoms' lowest points above the floor."""
        # every geom's [world z in its axes (3) | centre height (1)], (N, 4G), a GEMM or two per level
        acc: Tensor | None = None
        for lv, from_rot, from_pos in self._geom_maps:
            r, p = frames[lv - 1]
            part = r @ from_rot + p @ from_pos
            acc = part if acc is None else acc + part
        assert acc is not None
        g_count = len(self.geoms)
        up = acc[:, : 3 * g_count]
        low = acc[:, 3 * g_count :] - up.abs() @ self._reach - self._lift  # (N, G)
        for g, shape, size, place in self._curved:
            low = low - _reach(shape, up[:, 3 * g : 3 * g + 3], size)[:, None] @ place
        return low

    def _gaps(self, frames: list[tuple[Tensor, Tensor]], n: int) -> Tensor:
        """(N, P) distances between the surfaces of each pair's two geoms (negative: overlapping)."""
        acc = self._pair_fixed.expand(n, -1)
        for lv, from_rot, from_pos in self._pair_maps:
            r, p = frames[lv - 1]
            acc = acc + r @ from_rot + p @ from_pos
        return proximity.segment_gap(
            acc @ self._pair_c1, acc @ self._pair_d1, acc @ self._pair_c2, acc @ self._pair_d2,
            self._pair_radii, self._pair_total,
        )  # fmt: skip


Anchor = tuple[str, int]  # ("geom" or "site", id)


def _anchor_body(m: mujoco.MjModel, a: Anchor) -> int:
    return int(m.geom_bodyid[a[1]] if a[0] == "geom" else m.site_bodyid[a[1]])


def limited_site_tendons(m: mujoco.MjModel) -> list[str]:
    """The limited spatial tendons whose path runs through sites only (a string from a ball to a cup):
    their length is a sum of straight segments. An unnamed tendon is ``tendon<id>``."""
    out = []
    for t in range(m.ntendon):
        wraps = m.wrap_type[m.tendon_adr[t] : m.tendon_adr[t] + m.tendon_num[t]]
        if m.tendon_limited[t] and len(wraps) >= 2 and (wraps == mujoco.mjtWrap.mjWRAP_SITE).all():
            out.append(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TENDON, t) or f"tendon{t}")
    return out


def tendon_segments(
    m: mujoco.MjModel, names: Sequence[str]
) -> tuple[list[tuple[Anchor, Anchor]], list[float]]:
    """The straight segments (pairs of sites) of each named tendon of ``limited_site_tendons``, in
    order, and each tendon's upper limit (metres)."""
    segments: list[tuple[Anchor, Anchor]] = []
    high = []
    for name in names:
        t = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, name)
        if t < 0 and name.startswith("tendon") and name[6:].isdigit():
            t = int(name[6:])
        if t < 0 or name not in limited_site_tendons(m):
            raise ValueError(f"no limited tendon through sites named {name!r} in the model")
        sites = [int(s) for s in m.wrap_objid[m.tendon_adr[t] : m.tendon_adr[t] + m.tendon_num[t]]]
        segments += [(("site", a), ("site", b)) for a, b in itertools.pairwise(sites)]
        high.append(float(m.tendon_range[t][1]))
    return segments, high


class _Level:
    """The steps of one level as constant matrices (see ``Clearance._plan_levels``): for its C steps
    reading the C_in frames of the level before, rotations R' = R·(A + sin θ·A K + (1 − cos θ)·A K²)
    (A the step's constant rotation, K a hinge's axis) and positions p' = p + R·u + d·R·e − R'·w (u the
    offset to the anchor, w the anchor, e a slide's axis, d its coordinate)."""

    def __init__(self, c: int, c_in: int, nq: int) -> None:
        w = max(c_in, 1)  # a first level reads the world: constant rows instead
        self.c = c
        self.a, self.ak, self.akk = (
            torch.zeros(9 * w, 9 * c),
            torch.zeros(9 * w, 9 * c),
            torch.zeros(9 * w, 9 * c),
        )
        self.u, self.e = torch.zeros(9 * w, 3 * c), torch.zeros(9 * w, 3 * c)
        self.pick = torch.zeros(3 * w, 3 * c)  # the input frame's position, per step
        self.w = torch.zeros(9 * c, 3 * c)
        self.slide, self.slide_ref = torch.zeros(nq, 3 * c), torch.zeros(3 * c)
        self.free: list[tuple[int, int]] = []  # (column, qpos address)
        self.balls: list[tuple[int, int]] = []
        self.first = c_in == 0
        self.hinges = (0, 0)
        self.hinge_place = torch.zeros(0, 9 * c)

    def add(self, k: int, step: dict[str, object], source: int) -> None:
        kind, j = step["kind"], step["joint"]
        rot, offset = step["rot"], step["offset"]
        assert isinstance(rot, Tensor) and isinstance(offset, Tensor)
        i = max(source, 0)
        if kind == "free":
            assert isinstance(j, _Joint)
            self.free.append((k, j.qpos))
            return
        blk = slice(9 * i, 9 * i + 9)
        self.a[blk, 9 * k : 9 * k + 9] = _kron3(rot)
        self.u[blk, 3 * k : 3 * k + 3] = _apply_matrix(offset)
        if source >= 0:
            self.pick[3 * i : 3 * i + 3, 3 * k : 3 * k + 3] = torch.eye(3)
        if kind == "hinge":
            assert isinstance(j, _Joint)
            axis = torch.tensor(_skew(j.axis), dtype=torch.float32)
            anchor = torch.tensor(j.pos, dtype=torch.float32)
            self.ak[blk, 9 * k : 9 * k + 9] = _kron3(rot @ axis)
            self.akk[blk, 9 * k : 9 * k + 9] = _kron3(rot @ axis @ axis)
            self.u[blk, 3 * k : 3 * k + 3] = _apply_matrix(offset + rot @ anchor)
            self.w[9 * k : 9 * k + 9, 3 * k : 3 * k + 3] = _apply_matrix(anchor)
        elif kind == "slide":
            assert isinstance(j, _Joint)
            self.e[blk, 3 * k : 3 * k + 3] = _apply_matrix(rot @ torch.tensor(j.axis, dtype=torch.float32))
            self.slide[j.qpos, 3 * k : 3 * k + 3] = 1.0
            self.slide_ref[3 * k : 3 * k + 3] = float(j.ref[0])
        elif kind == "ball":
            assert isinstance(j, _Joint)
            self.balls.append((k, j.qpos))

    def finish(self) -> None:
        """The products of constants, made once (``step`` is traced: it must hold only the graph)."""
        self.ak_h = self.ak @ self.hinge_place.T  # (9·C_in, 9·H_level): only the hinges' columns
        self.akk_h = self.akk @ self.hinge_place.T
        self.has_slides, self.has_anchors = bool(self.e.any()), bool(self.w.any())
        self.free_place = [(at, _column(9, k, self.c), _column(3, k, self.c)) for k, at in self.free]
        self.ball_place = [(k, at, _column(9, k, self.c)) for k, at in self.balls]

    def step(
        self, r: Tensor | None, p: Tensor | None, q: Tensor, sin9: Tensor, vers9: Tensor, n: int
    ) -> tuple[Tensor, Tensor]:
        """The level's (N, 9C) rotations and (N, 3C) positions from the level before's (None: the world)."""
        r_in = _EYE9.expand(n, 9) if r is None else r
        new = r_in @ self.a
        lo, hi = self.hinges
        if hi > lo:  # the hinges' columns only, placed back among the level's
            turn = sin9[:, lo:hi] * (r_in @ self.ak_h) + vers9[:, lo:hi] * (r_in @ self.akk_h)
            new = new + turn @ self.hinge_place
        for at, place9, _ in self.free_place:
            new = new + _quat_matrix(q[:, at + 3 : at + 7]) @ place9
        for k, at, place9 in self.ball_place:
            block = new[:, 9 * k : 9 * k + 9]
            new = new + (_times(block, _quat_matrix(q[:, at : at + 4])) - block) @ place9
        pos = r_in @ self.u
        if p is not None:
            pos = pos + p @ self.pick
        if self.has_slides:
            pos = pos + (r_in @ self.e) * (q @ self.slide - self.slide_ref)
        if self.has_anchors:
            pos = pos - new @ self.w
        for at, _, place3 in self.free_place:
            pos = pos + q[:, at : at + 3] @ place3
        return new, pos


def _column(width: int, k: int, c: int) -> Tensor:
    """(width, width·C) places a (N, width) block at block column k of C."""
    m = torch.zeros(width, width * c)
    m[:, width * k : width * k + width] = torch.eye(width)
    return m


def _kron3(m: Tensor) -> Tensor:
    """(9, 9) I ⊗ M: a row-major rotation R (as a (N, 9) row) times it is R·M."""
    return torch.kron(torch.eye(3), m)


def _apply_matrix(v: Tensor) -> Tensor:
    """(9, 3) M with ``R9 @ M == R·v`` for row-major rotations R9 (N, 9) and a constant (3,) vector v."""
    m = torch.zeros(9, 3)
    for i in range(3):
        m[3 * i : 3 * i + 3, i] = v
    return m


_EYE9 = torch.eye(3).reshape(1, 9)
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
