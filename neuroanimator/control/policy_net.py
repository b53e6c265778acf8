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


def _rotation_forms() -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Constant maps for turning world vectors into a body's frame with products and sums only.

    ``pick_a``, ``pick_b`` (4, 10): q (B,4) ↦ the two factors of the ten products q_i·q_j (i ≤ j);
    ``form`` (10, 12): the products ↦ Rᵀ(q)·|q|² row-major (9) beside the world's up in the body's
    frame, Rᵀe_z·|q|² (3); ``norm`` (10, 1): the products ↦ |q|² (each entry of R is a quadratic form
    in q = [w, x, y, z], exact for a quaternion of any norm once divided by |q|²)."""
    pairs = [(i, j) for i in range(4) for j in range(i, 4)]
    pick_a, pick_b = torch.zeros(4, 10), torch.zeros(4, 10)
    for k, (i, j) in enumerate(pairs):
        pick_a[i, k], pick_b[j, k] = 1.0, 1.0
    w, x, y, z = range(4)
    entries = {  # R[a][b] = Σ coefficient · q_i q_j
        (0, 0): [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)],
        (0, 1): [(x, y, 2), (w, z, -2)],
        (0, 2): [(x, z, 2), (w, y, 2)],
        (1, 0): [(x, y, 2), (w, z, 2)],
        (1, 1): [(w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)],
        (1, 2): [(y, z, 2), (w, x, -2)],
        (2, 0): [(x, z, 2), (w, y, -2)],
        (2, 1): [(y, z, 2), (w, x, 2)],
        (2, 2): [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
    }
    form = torch.zeros(10, 12)
    for (a, b), terms in entries.items():
        for i, j, c in terms:
            k = pairs.index((min(i, j), max(i, j)))
            form[k, 3 * b + a] += c  # Rᵀ[b][a] = R[a][b]
    form[:, 9:] = form[:, [2, 5, 8]]  # Rᵀ e_z: the last column of Rᵀ
    norm = torch.zeros(10, 1)
    for k, (i, j) in enumerate(pairs):
        if i == j:
            norm[k, 0] = 1.0
    return pick_a, pick_b, form, norm


PICK_A, PICK_B, ROTATION_FORM, NORM_FORM = _rotation_forms()
NORM_EPS = torch.tensor([1e-12])
REPEAT = torch.kron(torch.ones(1, 3), torch.eye(3))  # (3, 9): v ↦ [v, v, v], beside each row of Rᵀ
ROW_SUMS = torch.kron(torch.eye(3), torch.ones(3, 1))  # (9, 3): sums of each row's three products


def rotation_transposed(q: Tensor) -> tuple[Tensor, Tensor]:
    """Quaternions q (B,4) [w, x, y, z], of any norm → R(q)ᵀ row-major (B,9) (world vectors into the
    body's frame) and the world's up in the body's frame (B,3). Matrix products and same-shape
    products only: ONNX Runtime runs these at large batches far faster than gathers, slices and
    broadcasts, which would otherwise cost a small policy as much as the emulator it drives."""
    return rotation_from_products((q @ PICK_A.to(q.dtype)) * (q @ PICK_B.to(q.dtype)))


def rotation_from_products(products: Tensor) -> tuple[Tensor, Tensor]:
    """The ten products q_i·q_j (i ≤ j) of quaternions (B,10) → ``rotation_transposed``'s pair."""
    # (|q|² + ε as one product with a bias: a Gemm, where a sum after the product is a pass of its own)
    norm = nn.functional.linear(products, NORM_FORM.T.to(products.dtype), NORM_EPS.to(products.dtype))
    scaled = (products @ ROTATION_FORM.to(products.dtype)) / norm
    return scaled[:, :9], scaled[:, 9:]


def turn(rt: Tensor, v: Tensor) -> Tensor:
    """Rᵀ (B,9) row-major applied to vectors v (B,3)."""
    return (rt * (v @ REPEAT.to(v.dtype))) @ ROW_SUMS.to(v.dtype)


def rotate_into(q: Tensor, v: Tensor) -> Tensor:
    """World vectors v (B,3) in the frame of quaternions q (B,4) [w, x, y, z]: R(q)ᵀ v."""
    return turn(rotation_transposed(q)[0], v)


def wrap(x: Tensor) -> Tensor:
    """Angles wrapped to [-π, π) (exports as Floor, not as an Atan2 ONNX lacks)."""
    return x - 2 * math.pi * torch.floor((x + math.pi) / (2 * math.pi))


class PolicyFeatures(nn.Module):
    """``(state (B,S), goal (B,G), time_left (B,1)) → (B, D)``: the scale-free inputs (module doc).

    Every linear part (picking columns, centring and scaling, the goal's offset) is one constant
    matrix applied to ``[state, goal]``, so that the exported graph is a few matrix products: its
    cost at large batches stays well under the emulator's."""

    plain_map: Tensor
    plain_shift: Tensor
    offset_map: Tensor
    angle_map: Tensor
    inv_goal_scale: Tensor
    goal_wrap: Tensor
    quat_map: Tensor
    spatial_map: Tensor
    velocity_map: Tensor
    heading_map: Tensor
    quat_a: Tensor
    quat_b: Tensor
    spatial_repeat: Tensor
    velocity_repeat: Tensor
    linear_map: Tensor
    linear_shift: Tensor

    def __init__(self, shape: PolicyShape) -> None:
        super().__init__()
        self.shape = shape
        size, goals = shape.state_size, shape.goal_size
        width = size + goals

        def buf(name: str, value: Tensor) -> None:
            self.register_buffer(name, value.to(torch.float32), persistent=False)

        def picks(columns: Sequence[int], scales: Sequence[float] | None = None) -> Tensor:
            m = torch.zeros(width, len(columns))
            for k, c in enumerate(columns):
                m[c, k] = 1.0 / (scales[k] if scales is not None else 1.0)
            return m

        plain_scale = [shape.scale[c] for c in shape.plain_columns]
        buf("plain_map", picks(shape.plain_columns, plain_scale))
        buf("plain_shift", torch.tensor([-shape.mean[c] / shape.scale[c] for c in shape.plain_columns]))
        offset = torch.zeros(width, goals)
        for j, c in enumerate(shape.goal_columns):
            offset[size + j, j], offset[c, j] = 1.0, -1.0
        buf("offset_map", offset)
        buf("angle_map", picks(shape.angle_columns))
        buf("inv_goal_scale", 1.0 / torch.tensor(shape.goal_scale, dtype=torch.float32))
        buf("goal_wrap", torch.tensor([1.0 if a else 0.0 for a in shape.goal_angles]))
        buf("heading_map", picks([shape.heading] if shape.heading >= 0 else []))
        buf("quat_map", picks(range(shape.quat, shape.quat + 4) if shape.quat >= 0 else []))
        spatial = offset[:, list(shape.spatial)] / (
            shape.goal_scale[shape.spatial[0]] if shape.spatial else 1.0
        )
        buf("spatial_map", spatial)
        v_cols = (
            list(range(shape.world_velocity[0], shape.world_velocity[0] + 3)) if shape.world_velocity else []
        )
        v_scale = shape.scale[shape.world_velocity[0]] if shape.world_velocity else 1.0
        buf("velocity_map", picks(v_cols, [v_scale] * len(v_cols)))
        # products of constant maps folded into one each, so that the graph makes fewer passes over
        # the batch: the quaternion's two factors, each vector repeated beside Rᵀ's rows, and (no
        # angle in the goal, no heading) the plain columns beside the goal's scaled offset
        buf("quat_a", self.quat_map @ PICK_A if shape.quat >= 0 else torch.zeros(width, 0))
        buf("quat_b", self.quat_map @ PICK_B if shape.quat >= 0 else torch.zeros(width, 0))
        buf("spatial_repeat", self.spatial_map @ REPEAT if shape.spatial else torch.zeros(width, 0))
        buf("velocity_repeat", self.velocity_map @ REPEAT if v_cols else torch.zeros(width, 0))
        self.fused = not any(shape.goal_angles) and not shape.planar
        buf("linear_map", torch.cat([self.plain_map, self.offset_map * self.inv_goal_scale], dim=1))
        buf("linear_shift", torch.cat([self.plain_shift, torch.zeros(goals)]))

    def forward(self, state: Tensor, goal: Tensor, time_left: Tensor) -> Tensor:
        s = self.shape
        z = torch.cat([state, goal], dim=1)
        parts: list[Tensor] = []
        if s.angle_columns:
            a = z @ self.angle_map
            parts += [torch.sin(a), torch.cos(a)]
        if self.fused:  # the plain columns and the goal's scaled offset: one product
            parts.append(z @ self.linear_map + self.linear_shift)
        else:
            parts.append(z @ self.plain_map + self.plain_shift)
            offset = z @ self.offset_map
            if any(s.goal_angles):  # wrapped where the variable is an angle
                offset = offset + self.goal_wrap * (wrap(offset) - offset)
            parts.append(offset * self.inv_goal_scale)
        if s.planar:
            h = z @ self.heading_map
            dx, dy = offset[:, s.planar[0] : s.planar[0] + 1], offset[:, s.planar[1] : s.planar[1] + 1]
            c, si = torch.cos(h), torch.sin(h)
            scale = s.goal_scale[s.planar[0]]
            parts += [(c * dx + si * dy) / scale, (-si * dx + c * dy) / scale]
        if s.quat >= 0:  # the world's up, the goal's offset and the velocity in the body's frame
            rt, up = rotation_from_products((z @ self.quat_a) * (z @ self.quat_b))
            parts.append(up)
            if s.spatial:
                parts.append((rt * (z @ self.spatial_repeat)) @ ROW_SUMS.to(z.dtype))
            if s.world_velocity:
                parts.append((rt * (z @ self.velocity_repeat)) @ ROW_SUMS.to(z.dtype))
        if s.timed:
            parts.append(time_left)
        return torch.cat(parts, dim=1)


class PolicyNet(nn.Module):
    """``π(state (B,S), goal (B,G), time_left (B,1)) → controls (B,U)`` within the hard limits."""

    centre: Tensor
    span: Tensor
    spread: Tensor
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
        self.register_buffer("spread", torch.diag(self.span), persistent=False)  # (U, U)
        self.register_buffer("limit_low", torch.tensor(shape.limit_low), persistent=False)
        self.register_buffer("limit_high", torch.tensor(shape.limit_high), persistent=False)
        # the squashed output never leaves the useful range: where that lies within the hard limits
        # (the usual case) the clip is left out of the graph (two fewer operations a call)
        self.clips = any(lo < lim for lo, lim in zip(shape.low, shape.limit_low, strict=True)) or any(
            hi > lim for hi, lim in zip(shape.high, shape.limit_high, strict=True)
        )

    def forward(self, state: Tensor, goal: Tensor, time_left: Tensor) -> Tensor:
        a = self.mlp(self.features(state, goal, time_left))
        # c + h·tanh(a) as one product with a bias (a Gemm): ONNX Runtime's broadcast sum and
        # product over a large batch cost as much as a layer each
        u = nn.functional.linear(torch.tanh(a), self.spread, self.centre)
        if not self.clips:
            return u
        return torch.minimum(torch.maximum(u, self.limit_low), self.limit_high)

    def output_range(self) -> tuple[list[float], list[float]]:
        """(U,) lows and highs the controls never leave: the useful range within the hard limits."""
        s = self.shape
        return (
            [max(lo, lim) for lo, lim in zip(s.low, s.limit_low, strict=True)],
            [min(hi, lim) for hi, lim in zip(s.high, s.limit_high, strict=True)],
        )

    def normalised(self, controls: Tensor) -> Tensor:
        """Controls (B,U) in units of each one's half range, 0 at its centre (for the effort term)."""
        return (controls - self.centre) / self.span
