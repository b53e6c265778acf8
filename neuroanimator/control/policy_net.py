"""The policy network: ``π(state, goal, time_left) → controls``, the form it is trained, exported and
served in.

Inputs are made scale-free before the network sees them (``PolicyFeatures``): angles as their sine
and cosine (a hinge or a heading that has turned once more is the same pose to the controller),
quaternions as they are, every other variable centred and divided by its spread in the model's
typical motion; then the goal's offset from the state (angles wrapped to [-π, π), divided by the
goal's spread) and, where the model has a heading, the planar part of that offset in the heading's
frame (a truck steers by what is ahead and to its left, not by where north is). The output is
squashed into each control's useful range (``u = c + h·tanh(a)``) and clipped to the actuator's
hard limits, as MuJoCo clips a limited actuator's control.

Shapes: B batch, S state, G goal variables, U controls. Every operation exports to ONNX.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from neuroanimator.core.state import LayoutGroup

ANGLE_KINDS = ("angle", "heading")
QUATERNION_KINDS = ("quaternion", "local_quaternion")


@dataclass(frozen=True)
class PolicyShape:
    """Everything needed to rebuild a policy network (saved beside its weights).

    ``mean``/``scale`` (S,) centre and scale the state's plain variables; ``angle_columns`` are taken
    as sine and cosine, ``goal_columns`` (G,) the state variables the goal sets, ``goal_scale`` (G,)
    their spread and ``goal_angles`` which of them wrap; ``heading`` the heading column (or -1) and
    ``planar`` the goal's indices of the root's x and y (or empty), rotated into the heading's frame.
    ``low``/``high`` (U,) the controls' useful range, ``limit_low``/``limit_high`` their hard limits.
    A free body's ``quat`` (its quaternion's first column, or -1) gives the body frame: the world's up
    in it, and in it the goal's ``spatial`` part (the goal's indices of the root's x, y, z) and the
    ``world_velocity`` columns (a drone steers by what is ahead of it and how it moves in its own frame).
    """

    state_size: int
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    angle_columns: tuple[int, ...]
    plain_columns: tuple[int, ...]
    goal_columns: tuple[int, ...]
    goal_scale: tuple[float, ...]
    goal_angles: tuple[bool, ...]
    heading: int
    planar: tuple[int, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    limit_low: tuple[float, ...]
    limit_high: tuple[float, ...]
    timed: bool
    hidden: tuple[int, ...]
    quat: int = -1
    spatial: tuple[int, ...] = ()
    world_velocity: tuple[int, ...] = ()

    @property
    def num_controls(self) -> int:
        return len(self.low)

    @property
    def goal_size(self) -> int:
        return len(self.goal_columns)

    @property
    def num_features(self) -> int:
        return (
            2 * len(self.angle_columns)
            + len(self.plain_columns)
            + self.goal_size
            + (2 if self.planar else 0)
            + (3 if self.quat >= 0 else 0)
            + (3 if self.quat >= 0 and self.spatial else 0)
            + (3 if self.quat >= 0 and self.world_velocity else 0)
            + (1 if self.timed else 0)
        )

    def to_dict(self) -> dict[str, object]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> PolicyShape:
        fields = dict(data)
        for k, v in fields.items():
            if isinstance(v, list):
                fields[k] = tuple(v)
        return cls(**fields)  # type: ignore[arg-type]


def describe_columns(
    layout: Sequence[LayoutGroup], goal_columns: Sequence[int]
) -> tuple[list[int], list[int], list[bool], int, list[int]]:
    """From a layout: the angle columns, the plain ones, which goal columns are angles, the heading's
    column (-1 without one) and the goal's indices of the root position's x and y (empty unless the
    model has a heading and the goal sets both)."""
    angles: list[int] = []
    plain: list[int] = []
    heading = -1
    root_xy: list[int] = []
    for g in layout:
        cols = list(range(g.offset, g.offset + g.size))
        if g.kind in ANGLE_KINDS:
            angles += cols
            if g.kind == "heading":
                heading = g.offset
        else:
            plain += cols
        if g.kind == "position" and not root_xy and g.size >= 2:
            root_xy = cols[:2]
    goal_angles = [c in angles for c in goal_columns]
    planar = (
        [list(goal_columns).index(c) for c in root_xy]
        if heading >= 0 and all(c in goal_columns for c in root_xy) and root_xy
        else []
    )
    return angles, plain, goal_angles, heading, planar


def describe_body_frame(
    layout: Sequence[LayoutGroup], goal_columns: Sequence[int]
) -> tuple[int, list[int], list[int]]:
    """From a layout: the first quaternion's column (-1 without one), the goal's indices of the root
    position's x, y, z (empty unless the goal sets all three) and the columns of the first world-frame
    velocity of three values (empty without one)."""
    quat = -1
    root: list[int] = []
    velocity: list[int] = []
    for g in layout:
        cols = list(range(g.offset, g.offset + g.size))
        if g.kind in QUATERNION_KINDS and quat < 0:
            quat = g.offset
        if g.kind == "position" and g.size == 3 and not root:
            root = cols
        if g.kind == "world_vector" and g.size == 3 and not velocity:
            velocity = cols
    if quat < 0:
        return -1, [], []
    spatial = (
        [list(goal_columns).index(c) for c in root] if root and all(c in goal_columns for c in root) else []
    )
    return quat, spatial, velocity


def rotate_into(q: Tensor, v: Tensor) -> Tensor:
    """World vectors v (B,3) in the frame of unit quaternions q (B,4) [w, x, y, z]: R(q)ᵀ v."""
    w, u = q[:, 0:1], -q[:, 1:4]  # the conjugate's vector part
    t = 2 * torch.linalg.cross(u, v, dim=1)
    return v + w * t + torch.linalg.cross(u, t, dim=1)


def wrap(x: Tensor) -> Tensor:
    """Angles wrapped to [-π, π) (exports as Floor, not as an Atan2 ONNX lacks)."""
    return x - 2 * math.pi * torch.floor((x + math.pi) / (2 * math.pi))


class PolicyFeatures(nn.Module):
    """``(state (B,S), goal (B,G), time_left (B,1)) → (B, D)``: the scale-free inputs (module doc)."""

    mean: Tensor
    scale: Tensor
    plain: Tensor
    angles: Tensor
    goal_cols: Tensor
    goal_scale: Tensor
    goal_wrap: Tensor

    def __init__(self, shape: PolicyShape) -> None:
        super().__init__()
        self.shape = shape

        def buf(name: str, values: Sequence[float] | Sequence[int], dtype: torch.dtype) -> None:
            self.register_buffer(name, torch.tensor(list(values), dtype=dtype), persistent=False)

        buf("mean", [shape.mean[c] for c in shape.plain_columns], torch.float32)
        buf("scale", [shape.scale[c] for c in shape.plain_columns], torch.float32)
        buf("plain", shape.plain_columns, torch.long)
        buf("angles", shape.angle_columns, torch.long)
        buf("goal_cols", shape.goal_columns, torch.long)
        buf("goal_scale", shape.goal_scale, torch.float32)
        buf("goal_wrap", [1.0 if a else 0.0 for a in shape.goal_angles], torch.float32)

    def plain_index(self, column: int) -> int:
        """Where a plain state column's scale is kept."""
        return self.shape.plain_columns.index(column)

    def forward(self, state: Tensor, goal: Tensor, time_left: Tensor) -> Tensor:
        s = self.shape
        parts: list[Tensor] = []
        if s.angle_columns:
            a = state[:, self.angles]
            parts += [torch.sin(a), torch.cos(a)]
        parts.append((state[:, self.plain] - self.mean) / self.scale)
        offset = goal - state[:, self.goal_cols]
        offset = offset + self.goal_wrap * (wrap(offset) - offset)  # wrapped where the variable is an angle
        parts.append(offset / self.goal_scale)
        if s.planar:
            h = state[:, s.heading : s.heading + 1]
            dx, dy = offset[:, s.planar[0] : s.planar[0] + 1], offset[:, s.planar[1] : s.planar[1] + 1]
            c, si = torch.cos(h), torch.sin(h)
            scale = self.goal_scale[s.planar[0]]
            parts += [(c * dx + si * dy) / scale, (-si * dx + c * dy) / scale]
        if s.quat >= 0:
            q = state[:, s.quat : s.quat + 4]
            q = q / torch.sqrt((q * q).sum(dim=1, keepdim=True) + 1e-12)
            parts.append(rotate_into(q, torch.tensor([[0.0, 0.0, 1.0]]).expand(q.shape[0], 3)))
            if s.spatial:
                d = torch.cat([offset[:, i : i + 1] for i in s.spatial], dim=1)
                parts.append(rotate_into(q, d) / self.goal_scale[s.spatial[0]])
            if s.world_velocity:
                v = state[:, s.world_velocity[0] : s.world_velocity[0] + 3]
                parts.append(rotate_into(q, v) / self.scale[self.plain_index(s.world_velocity[0])])
        if s.timed:
            parts.append(time_left)
        return torch.cat(parts, dim=1)


class PolicyNet(nn.Module):
    """``π(state (B,S), goal (B,G), time_left (B,1)) → controls (B,U)`` within the hard limits."""

    centre: Tensor
    span: Tensor
    limit_low: Tensor
    limit_high: Tensor

    def __init__(self, shape: PolicyShape) -> None:
        super().__init__()
        self.shape = shape
        self.features = PolicyFeatures(shape)
        layers: list[nn.Module] = []
        width = shape.num_features
        for h in shape.hidden:
            layers += [nn.Linear(width, h), nn.Tanh()]
            width = h
        last = nn.Linear(width, shape.num_controls)
        nn.init.zeros_(last.bias)
        nn.init.uniform_(last.weight, -1e-3, 1e-3)  # starts at the middle of every control's range
        self.mlp = nn.Sequential(*layers, last)
        low, high = torch.tensor(shape.low), torch.tensor(shape.high)
        self.register_buffer("centre", 0.5 * (low + high), persistent=False)
        self.register_buffer("span", 0.5 * (high - low), persistent=False)
        self.register_buffer("limit_low", torch.tensor(shape.limit_low), persistent=False)
        self.register_buffer("limit_high", torch.tensor(shape.limit_high), persistent=False)

    def forward(self, state: Tensor, goal: Tensor, time_left: Tensor) -> Tensor:
        a = self.mlp(self.features(state, goal, time_left))
        u = self.centre + self.span * torch.tanh(a)
        return torch.minimum(torch.maximum(u, self.limit_low), self.limit_high)

    def normalised(self, controls: Tensor) -> Tensor:
        """Controls (B,U) in units of each one's half range, 0 at its centre (for the effort term)."""
        return (controls - self.centre) / self.span
