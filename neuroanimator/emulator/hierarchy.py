"""Hierarchical emulators (thesis 4.4): a global network for the motion of the body's parts as
frames, then one network per part for the part's own state in its frame.

A model whose state groups are partitioned into parts (``model_spec.HierarchyPart``) is emulated in
two stages:

1. the frames: each part's centre c, two axes a and b, and their velocities ċ, ȧ, ḃ are fixed linear
   maps of the state (weights of the parts' points); the **global** network reads every part's frame
   quantities (centres relative to the mean centre, so that the body may be anywhere) and the
   controls, and predicts their change over the super-step;
2. the **local** network of each part reads the part's groups in the part's frame (points relative
   to the centre, in the orthonormal axes R = gram_schmidt(a, b)), its frame quantities and the
   predicted next ones (in the same axes) and the controls, and predicts the part's points in the
   *predicted next* frame, which are mapped back to world points: p' = c' + R' p'_local.

Each network is a ``StructuredEmulator`` over its own layout (normalisation, MLP, linear path,
state change), so that both are trained like any emulator: the global network on the frames' motion,
each local network on its part's motion given the true next frame. The composition is one
``forward``, traced into one ONNX graph by ``neuroanimator.export.onnx``; with networks that predict no
change the step is the identity (the maps to and from the frames are exact inverses).

Shapes: B batch, S state, U controls, K parts, Q = 6·3 frame values per part.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from neuroanimator.core.model_spec import FRAME_QUANTITIES, HierarchyPart
from neuroanimator.core.state import StateGroup, StateLayout
from neuroanimator.emulator.regularizer import SpringRegularization
from neuroanimator.emulator.structured import FrameConfig, StructuredEmulator

GLOBAL = "global"
VECTORS = FRAME_QUANTITIES
FRAME_SIZE = 3 * len(VECTORS)
# what a local network reads besides its part's groups: its frame now (the centre is its origin, so
# left out) and the predicted next frame, both in its current axes
LOCAL_FRAME_INPUTS = tuple(f"frame.{v}" for v in VECTORS[1:]) + tuple(f"next.{v}" for v in VECTORS)
_LOCAL_KINDS = {
    "position": "scalar",
    "world_vector": "scalar",
    "heading": "scalar",
    "quaternion": "local_quaternion",
}


def neighbour_inputs(part: HierarchyPart) -> list[str]:
    """Names of a local network's neighbour inputs, 3 values each: positions, then velocities."""
    return [f"near.{pos}" for pos, _ in part.neighbours] + [f"near.{vel}" for _, vel in part.neighbours]


def frame_layout(parts: Sequence[HierarchyPart]) -> StateLayout:
    """The global network's layout: each part's frame quantities (``<part>.<quantity>``, 3 values)."""
    return StateLayout(
        tuple(
            StateGroup(name=f"{p.name}.{v}", kind="scalar", size=3, source="qpos", address=0)
            for p in parts
            for v in VECTORS
        )
    )


def part_layout(layout: StateLayout, part: HierarchyPart) -> StateLayout:
    """A local network's layout: the part's groups, in the part's order; the root kinds become plain
    ones (a part's network works in the part's frame, not the root's)."""
    by_name = {g.name: g for g in layout}
    groups = []
    for name in part.groups:
        g = by_name[name]
        groups.append(g.model_copy(update={"kind": _LOCAL_KINDS.get(g.kind, g.kind)}))
    return StateLayout(tuple(groups))


def check_parts(layout: StateLayout, parts: Sequence[HierarchyPart]) -> None:
    """Raise ``ValueError`` unless the parts partition the layout's groups and their points and axes
    name groups of 3 values that they own."""
    names = [g.name for g in layout]
    sizes = {g.name: g.size for g in layout}
    owned = [g for p in parts for g in p.groups]
    if sorted(owned) != sorted(names):
        missing, twice = sorted(set(names) - set(owned)), sorted({g for g in owned if owned.count(g) > 1})
        extra = sorted(set(owned) - set(names))
        raise ValueError(
            f"the parts must hold every state group once: missing {missing}, twice {twice}, unknown {extra}"
        )
    positions = {pos for p in parts for pos, _ in p.points}
    points = {pt for p in parts for pt in p.points}
    for p in parts:
        strangers = sorted(f"{pos}/{vel}" for pos, vel in p.neighbours if (pos, vel) not in points)
        own = sorted(f"{pos}/{vel}" for pos, vel in p.neighbours if (pos, vel) in p.points)
        if strangers or own:
            raise ValueError(
                f"part {p.name!r}: neighbours must be other parts' points (not points: {strangers}, its own: {own})"
            )
        if len(p.centre) != len(p.points) or abs(sum(p.centre) - 1.0) > 1e-6:
            raise ValueError(f"part {p.name!r}: centre needs one weight per point, summing to 1")
        for pos, vel in p.points:
            if pos not in p.groups or vel not in p.groups or sizes[pos] != 3 or sizes[vel] != 3:
                raise ValueError(f"part {p.name!r}: point ({pos!r}, {vel!r}) must be two of its groups of 3")
        for axis in (p.axis1, p.axis2):
            unknown = sorted({g for g, _ in axis} - positions)
            if unknown or abs(sum(w for _, w in axis)) > 1e-6:
                raise ValueError(
                    f"part {p.name!r}: an axis weighs points' positions (unknown {unknown}), weights summing to 0"
                )


def _basis(a: Tensor, b: Tensor) -> Tensor:
    """Gram-Schmidt: (B, 3) axes a, b -> (B, 3, 3) with columns e1 ∥ a, e2 in the plane of a and b, e3."""
    e1 = a / torch.sqrt((a * a).sum(dim=1, keepdim=True) + 1e-12)
    b = b - (b * e1).sum(dim=1, keepdim=True) * e1
    e2 = b / torch.sqrt((b * b).sum(dim=1, keepdim=True) + 1e-12)
    e3 = e1[:, [1, 2, 0]] * e2[:, [2, 0, 1]] - e1[:, [2, 0, 1]] * e2[:, [1, 2, 0]]
    return torch.stack([e1, e2, e3], dim=2)


class _PartMap(nn.Module):
    """A part's groups to and from its frame: ``state (B,S) -> local (B,S_k)`` and back to world
    values placed in a state vector."""

    pick: Tensor  # (S, S_k) the part's groups, in the part's order
    place: Tensor  # (S_k, S)
    keep: Tensor  # (S_k, S_k) every column but the points'
    pos: Tensor  # (S_k, 3n) the points' positions
    vel: Tensor  # (S_k, 3n) the points' velocities
    near_pos: Tensor  # (S, 3m) the neighbours' positions
    near_vel: Tensor  # (S, 3m) the neighbours' velocities

    def __init__(self, layout: StateLayout, part: HierarchyPart, index: int) -> None:
        super().__init__()
        self.index = index
        cols = [
            c for name in part.groups for c in range(layout.slice_of(name).start, layout.slice_of(name).stop)
        ]
        s_k = len(cols)
        pick = torch.zeros(layout.size, s_k)
        for j, c in enumerate(cols):
            pick[c, j] = 1.0
        local = part_layout(layout, part)
        pos = torch.zeros(s_k, 3 * len(part.points))
        vel = torch.zeros(s_k, 3 * len(part.points))
        for i, (p, v) in enumerate(part.points):
            for axis in range(3):
                pos[local.slice_of(p).start + axis, 3 * i + axis] = 1.0
                vel[local.slice_of(v).start + axis, 3 * i + axis] = 1.0
        keep = torch.eye(s_k) - pos @ pos.T - vel @ vel.T
        m = len(part.neighbours)
        near_pos = torch.zeros(layout.size, 3 * m)
        near_vel = torch.zeros(layout.size, 3 * m)
        for i, (p, v) in enumerate(part.neighbours):
            for axis in range(3):
                near_pos[layout.slice_of(p).start + axis, 3 * i + axis] = 1.0
                near_vel[layout.slice_of(v).start + axis, 3 * i + axis] = 1.0
        self.neighbours = m
        self.register_buffer("near_pos", near_pos, persistent=False)
        self.register_buffer("near_vel", near_vel, persistent=False)
        self.points = len(part.points)
        self.register_buffer("pick", pick, persistent=False)
        self.register_buffer("place", pick.T.contiguous(), persistent=False)
        self.register_buffer("keep", keep, persistent=False)
        self.register_buffer("pos", pos, persistent=False)
        self.register_buffer("vel", vel, persistent=False)

    def frame(self, frames: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """This part's centre (B, 3), centre velocity (B, 3) and axes R (B, 3, 3) from all frames (B, K·Q)."""
        f = frames[:, FRAME_SIZE * self.index : FRAME_SIZE * (self.index + 1)]
        return f[:, 0:3], f[:, 9:12], _basis(f[:, 3:6], f[:, 6:9])

    def to_local(self, state: Tensor, frames: Tensor) -> Tensor:
        """The part's groups (B, S_k) with its points relative to its centre, in its axes."""
        c, v, r = self.frame(frames)
        part = state @ self.pick
        p = ((part @ self.pos).reshape(-1, self.points, 3) - c.unsqueeze(1)) @ r
        w = ((part @ self.vel).reshape(-1, self.points, 3) - v.unsqueeze(1)) @ r
        return (
            part @ self.keep
            + p.reshape(-1, 3 * self.points) @ self.pos.T
            + w.reshape(-1, 3 * self.points) @ self.vel.T
        )

    def to_world(self, local: Tensor, frames: Tensor) -> Tensor:
        """Inverse of ``to_local`` for the frames ``frames``, placed in a state vector (B, S) (zero
        outside the part)."""
        c, v, r = self.frame(frames)
        rt = r.transpose(1, 2)
        p = (local @ self.pos).reshape(-1, self.points, 3) @ rt + c.unsqueeze(1)
        w = (local @ self.vel).reshape(-1, self.points, 3) @ rt + v.unsqueeze(1)
        part = (
            local @ self.keep
            + p.reshape(-1, 3 * self.points) @ self.pos.T
            + w.reshape(-1, 3 * self.points) @ self.vel.T
        )
        return part @ self.place

    def frame_inputs(self, state: Tensor, frames: Tensor, next_frames: Tensor) -> Tensor:
        """What the local network reads besides its groups (B, 33 + 6m): this frame's axes and
        velocities and the next frame's quantities (its centre relative to this one), then each
        neighbour's position and velocity relative to the centre's; all in this frame's axes."""
        c, v, r = self.frame(frames)
        now = frames[:, FRAME_SIZE * self.index : FRAME_SIZE * (self.index + 1)].reshape(-1, len(VECTORS), 3)
        nxt = next_frames[:, FRAME_SIZE * self.index : FRAME_SIZE * (self.index + 1)]
        nxt = torch.cat([nxt[:, :3] - c, nxt[:, 3:]], dim=1).reshape(-1, len(VECTORS), 3)
        rows = [now[:, 1:], nxt]
        if self.neighbours:
            rows.append((state @ self.near_pos).reshape(-1, self.neighbours, 3) - c.unsqueeze(1))
            rows.append((state @ self.near_vel).reshape(-1, self.neighbours, 3) - v.unsqueeze(1))
        turned = torch.cat(rows, dim=1) @ r  # rows v^T R: each vector in the frame's axes
        return turned.reshape(turned.shape[0], -1)


class HierarchicalEmulator(nn.Module):
    """One super-step of a model emulated by a hierarchy: ``forward(state (B,S), controls (B,U)) -> (B,S)``.

    ``glob`` is the global network (a ``StructuredEmulator`` over ``frame_layout``), ``parts_nets`` the
    local networks in the order of ``parts``.
    """

    _frames: Tensor  # (S, K·Q) the frame quantities of every part
    _shift: Tensor  # (S, K·Q) the mean centre, in every part's centre columns

    def __init__(
        self,
        layout: StateLayout,
        num_controls: int,
        parts: Sequence[HierarchyPart],
        global_hidden: Sequence[int] = (64,),
        local_hidden: Sequence[int] = (64,),
        activation: str = "tanh",
        skip: bool = False,
        num_forces: int = 0,
    ) -> None:
        super().__init__()
        if num_forces:
            raise ValueError("a hierarchical emulator of a model with external forces is not supported")
        check_parts(layout, parts)
        self.layout = layout
        self.parts = tuple(parts)
        self.num_controls = num_controls
        self.num_forces = 0
        self.quaternion_slices = [
            sl for g, sl in layout.group_slices() if g.kind in ("quaternion", "local_quaternion")
        ]
        self._plan_frames()
        self.glob = StructuredEmulator(
            frame_layout(parts), num_controls, 0, FrameConfig(), global_hidden, activation, skip=skip
        )
        nets = []
        for p in parts:
            extra = [*LOCAL_FRAME_INPUTS, *neighbour_inputs(p)]
            net = StructuredEmulator(
                part_layout(layout, p), num_controls, 3 * len(extra), FrameConfig(),
                local_hidden, activation, skip=skip,
            )  # fmt: skip
            # the frame and neighbour inputs are normalised per quantity, not as one block of "forces"
            net.input_groups = [g for g in net.input_groups if g[0] != "forces"] + [
                (name, 3) for name in extra
            ]
            nets.append(net)
        self.parts_nets = nn.ModuleList(nets)
        self.maps = nn.ModuleList(_PartMap(layout, p, k) for k, p in enumerate(parts))
        # thesis 6.1.3: a mass-spring model's step ends with a few Euler steps of its springs (set after
        # training; the networks learn the physics alone)
        self.regularizer: SpringRegularization | None = None

    def _plan_frames(self) -> None:
        lay = self.layout
        pos_to_vel = {pos: vel for p in self.parts for pos, vel in p.points}
        frames = torch.zeros(lay.size, FRAME_SIZE * len(self.parts))
        shift = torch.zeros(lay.size, FRAME_SIZE * len(self.parts))

        def add(col: int, group: str, weight: float, target: Tensor = frames) -> None:
            start = lay.slice_of(group).start
            for axis in range(3):
                target[start + axis, col + axis] += weight

        for k, p in enumerate(self.parts):
            at = FRAME_SIZE * k
            for (pos, vel), w in zip(p.points, p.centre, strict=True):
                add(at, pos, w)
                add(at + 9, vel, w)
                for j in range(len(self.parts)):  # minus the mean centre, in every part's centre
                    add(FRAME_SIZE * j, pos, w / len(self.parts), shift)
            for offset, axis in ((3, p.axis1), (6, p.axis2)):
                for group, w in axis:
                    add(at + offset, group, w)
                    add(at + offset + 9, pos_to_vel[group], w)
        self.register_buffer("_frames", frames, persistent=False)
        self.register_buffer("_shift", shift, persistent=False)

    def part_map(self, k: int) -> _PartMap:
        """Part k's map to and from its frame."""
        m = self.maps[k]
        assert isinstance(m, _PartMap)
        return m

    # ------------------------------------------------------------------ the stages
    @property
    def frame_map(self) -> Tensor:
        """(S, K·Q) the linear map from a state to every part's frame quantities."""
        return self._frames

    def frames_of(self, state: Tensor) -> Tensor:
        """Every part's frame quantities (B, K·Q), world values."""
        return state @ self._frames

    def global_step(self, state: Tensor, controls: Tensor | None = None) -> Tensor:
        """The global network: state (B,S) -> predicted next frame quantities (B, K·Q), world values."""
        shift = state @ self._shift
        return self.glob(state @ self._frames - shift, controls) + shift

    def global_inputs(self, state: Tensor, next_state: Tensor) -> tuple[Tensor, Tensor]:
        """The global network's input state and its target next state for a transition (training)."""
        shift = state @ self._shift
        return state @ self._frames - shift, next_state @ self._frames - shift

    def local_inputs(
        self, k: int, state: Tensor, next_frames: Tensor, frames: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Part k's local network inputs: its groups in its frame (B, S_k) and its frame and neighbour
        inputs (B, 33 + 6m)."""
        m = self.part_map(k)
        frames = self.frames_of(state) if frames is None else frames
        return m.to_local(state, frames), m.frame_inputs(state, frames, next_frames)

    def local_target(self, k: int, next_state: Tensor) -> Tensor:
        """Part k's next groups in the true next frame (B, S_k): a local network's target."""
        m = self.part_map(k)
        return m.to_local(next_state, self.frames_of(next_state))

    def compose(self, state: Tensor, controls: Tensor | None, next_frames: Tensor) -> Tensor:
        """The local stage: every part's network given the next frames (B, K·Q) -> next state (B, S)."""
        frames = self.frames_of(state)
        out: Tensor | None = None
        for net, m in zip(self.parts_nets, self.maps, strict=True):
            assert isinstance(m, _PartMap)
            local = net(m.to_local(state, frames), controls, m.frame_inputs(state, frames, next_frames))
            world = m.to_world(local, next_frames)
            out = world if out is None else out + world
        assert out is not None
        return out

    def forward(self, state: Tensor, controls: Tensor | None = None, forces: Tensor | None = None) -> Tensor:
        nxt = self.compose(state, controls, self.global_step(state, controls))
        return nxt if self.regularizer is None else self.regularizer(nxt, controls)

    @property
    def networks(self) -> list[tuple[str, StructuredEmulator]]:
        """Every network by name: the global one, then one per part."""
        nets: list[tuple[str, StructuredEmulator]] = [(GLOBAL, self.glob)]
        for p, net in zip(self.parts, self.parts_nets, strict=True):
            assert isinstance(net, StructuredEmulator)
            nets.append((p.name, net))
        return nets
