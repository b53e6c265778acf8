"""The structured emulator of thesis 4.3 (eq. 4.14), in PyTorch:

    s_{t+Δt} = T^Δ_y T'_y T^σ_y  N^σ  T^σ_x T'_x [s_t, u_t, f_t]

- ``T'_x`` (local frame): subtract the root position, rotate world vectors and the root quaternion
  into the model's frame. Which rotation is a true symmetry depends on gravity: with gravity along
  z only the heading (rotation about z) is removed, so tilt stays an input and the emulator is exact
  under every symmetry of the physics (the thesis' full body-frame rotation is not, under gravity).
  Inputs that are constant after the transform (the root position, the heading) are dropped (App. F.1).
  Hinge angles enter as sin and cos, so a joint that turned a full circle looks the same.
- ``T^σ_x`` / ``T^σ_y``: per-group normalisation to zero mean, unit variance (eqs. 4.9-4.12).
- ``N^σ``: the core MLP (configurable width, depth, activation; the thesis used one sigmoid layer).
- ``T'_y``: state changes back to world axes; ``T^Δ_y``: next state = state + change, with the
  quaternions renormalised.

Everything is traced into one ONNX graph by ``neuroanimator.export.onnx``. Shapes: B batch, S state,
U controls, F forces, D network inputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from torch import Tensor, nn

from neuroanimator.core.state import StateGroup, StateLayout
from neuroanimator.emulator.clearance import Clearance
from neuroanimator.emulator.regularizer import SpringRegularization

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "sigmoid": nn.Sigmoid,
    "tanh": nn.Tanh,
    "silu": nn.SiLU,
    "gelu": nn.GELU,
    "relu": nn.ReLU,
}


def make_core(inputs: int, outputs: int, hidden: Sequence[int], activation: str) -> nn.Sequential:
    """The core network N^σ: Linear → act → … → Linear; (B, inputs) -> (B, outputs)."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    layers: list[nn.Module] = []
    width = inputs
    for h in hidden:
        layers += [nn.Linear(width, h), ACTIVATIONS[activation]()]
        width = h
    layers.append(nn.Linear(width, outputs))
    return nn.Sequential(*layers)


@dataclass(frozen=True)
class JointLimit:
    """A limited hinge or slide joint, seen by the network through its distance to the limits.

    ``position`` and ``velocity`` are state columns, ``low``/``high`` the joint's range. A limit that
    engages inside a super-step makes the step a kink in the state; an MLP of smooth units rounds a
    kink off. So the network also reads, for the joint extrapolated over the super-step at constant
    velocity (``q + a·v·horizon``, a = 0, ½, 1), how far past each limit it would be: ramps that are
    zero away from the limit and carry the kink exactly where the constraint switches on.

    ``margin`` (None: none) keeps every predicted position within ``[low - margin, high + margin]``.
    A network can put a joint past its limit by its error, and an angle past it reads (as sine and
    cosine) like one near the other end of the range, a state the data never held: dm_control's
    reacher's rollouts ran away from there. MuJoCo's limits are soft, so true states pass them a
    little; the margin (``limit_margin``) is wider than any pass in the training data, so it never
    moves a state that MuJoCo could reach.
    """

    position: int
    velocity: int | None
    low: float
    high: float
    margin: float | None = None


def limit_margin(lim: JointLimit, positions: Tensor) -> float:
    """The margin past its range within which ``lim``'s predicted positions are kept, from the
    joint's positions ``(N,)`` in the training data: half as much again as the farthest the data pass
    either limit, and at least 2% of the range."""
    past = max(float((positions - lim.high).max()), float((lim.low - positions).max()), 0.0)
    return max(1.5 * past, 0.02 * (lim.high - lim.low))


LIMIT_FRACTIONS = (0.0, 0.5, 1.0)  # points of the super-step at which each joint is extrapolated


@dataclass(frozen=True)
class FrameConfig:
    """Symmetries used: translation of root-position axes, rotation about z; see PhysicalModel.frame.

    ``body=True`` (a root with a quaternion only) takes the thesis' full body frame instead of the
    heading frame: world vectors are rotated by the root's whole orientation and the direction of
    gravity enters as a body-frame vector. The heading of a body that is upside down is undefined,
    so the heading frame jumps there; the body frame is continuous over every attitude, and exactly
    as equivariant (the body-frame "up" vector is unchanged by rotations about the gravity axis).
    """

    translate: tuple[bool, ...] = ()
    rotate: bool = False
    # (x, y) or (x, y, z) indices of force inputs acting on one body, rotated together
    force_pairs: tuple[tuple[int, ...], ...] = ()
    control_pairs: tuple[tuple[int, ...], ...] = ()  # controls along world axes, turned like force_pairs
    body: bool = False
    # scalar groups of root slides translated away: the network does not read them (``Frame.slides``)
    slides: tuple[str, ...] = ()


@dataclass(frozen=True)
class _PairPlan:
    """Columns rotated together. Every transform of T' is a set of 2-D rotations about z: world
    vectors turn by the heading ψ, and a quaternion's (w, z) and (x, y) pairs turn by ψ/2 (that is
    h* ⊗ q for the heading quaternion h). They are all done at once by ``_Rotation``.
    """

    x: tuple[int, ...] = ()  # column of each pair's first component
    y: tuple[int, ...] = ()  # column of each pair's second component
    half: tuple[int, ...] = ()  # 0: turn by ψ, 1: turn by ψ/2


Frame = Tensor  # (B, 4): cos ψ, sin ψ, cos ψ/2, sin ψ/2 of each state's heading ψ


def select_columns(rows: int, cols: Sequence[int]) -> Tensor:
    """The 0/1 matrix M (rows, len(cols)) with ``(v @ M)[:, j] == v[:, cols[j]]``.

    Column picks are written as products with constant matrices rather than gathers: ONNX Runtime
    runs a small MatMul over a large batch many times faster than a column Gather.
    """
    m = torch.zeros(rows, len(cols))
    for j, c in enumerate(cols):
        m[c, j] = 1.0
    return m


def _select_or_zero(rows: int, cols: Sequence[int]) -> Tensor:
    """Like ``select_columns``, but a column index of -1 gives a column of zeros."""
    m = torch.zeros(rows, len(cols))
    for j, c in enumerate(cols):
        if c >= 0:
            m[c, j] = 1.0
    return m


def _rotation_from_quaternion() -> tuple[Tensor, Tensor]:
    """Constants (A (16, 9), I (9,)) with ``R = (q ⊗ q) @ A + I`` the row-major rotation matrix of a
    unit quaternion q = [w, x, y, z], where ``q ⊗ q`` is the flattened outer product (B, 16)."""
    a = torch.zeros(16, 9)

    def at(i: int, j: int) -> int:
        return 4 * i + j

    w, x, y, z = range(4)
    for (i, j), col, coef in [
        ((y, y), 0, -2), ((z, z), 0, -2),
        ((x, y), 1, 2), ((w, z), 1, -2),
        ((x, z), 2, 2), ((w, y), 2, 2),
        ((x, y), 3, 2), ((w, z), 3, 2),
        ((x, x), 4, -2), ((z, z), 4, -2),
        ((y, z), 5, 2), ((w, x), 5, -2),
        ((x, z), 6, 2), ((w, y), 6, -2),
        ((y, z), 7, 2), ((w, x), 7, 2),
        ((x, x), 8, -2), ((y, y), 8, -2),
    ]:  # fmt: skip
        a[at(i, j), col] = float(coef)
    return a, torch.eye(3).flatten()


def _pair_expansions() -> tuple[Tensor, Tensor]:
    """Constants (E₁, E₂), each (4, 16), with ``(q @ E₁) * (p @ E₂)`` the flattened outer product
    q pᵀ (B, 16): entry 4i + j is q_i p_j. Two products and a multiplication, where unsqueezing and
    reshaping would be four graph nodes."""
    e1, e2 = torch.zeros(4, 16), torch.zeros(4, 16)
    for i in range(4):
        for j in range(4):
            e1[i, 4 * i + j] = e2[j, 4 * i + j] = 1.0
    return e1, e2


def _product_table() -> Tensor:
    """Constant T (16, 4) with ``outer(q, p) @ T == q ⊗ p`` (the Hamilton product of [w, x, y, z]
    quaternions), ``outer`` flattened as in ``_pair_expansions``: the product is bilinear."""
    left = _left_product()  # q @ left = L(q) row-major, L(q)[i][j] = Σ_k q_k left[k, 4i + j]
    t = torch.zeros(16, 4)
    for k in range(4):
        for i in range(4):
            for j in range(4):
                t[4 * k + j, i] += left[k, 4 * i + j]
    return t


def _left_product() -> Tensor:
    """Constant C (4, 16) with ``q @ C`` the row-major 4×4 matrix L(q) such that q ⊗ p = L(q) p."""
    signs = [  # L(q)[i][j] = sign * q[k]
        [(1, 0), (-1, 1), (-1, 2), (-1, 3)],
        [(1, 1), (1, 0), (-1, 3), (1, 2)],
        [(1, 2), (1, 3), (1, 0), (-1, 1)],
        [(1, 3), (-1, 2), (1, 1), (1, 0)],
    ]
    c = torch.zeros(4, 16)
    for i, row in enumerate(signs):
        for j, (sign, k) in enumerate(row):
            c[k, 4 * i + j] = float(sign)
    return c


class _Rotation(nn.Module):
    """Turn the planned pairs of a (B, K) tensor by -ψ (``inverse=False``) or +ψ: returns
    (B, 2P) = [x'_1..x'_P, y'_1..y'_P] with x' = C x ± S y, y' = C y ∓ S x.

    C and S per pair come from the frame table (B, 4) through constant matrices, so the whole
    rotation is four matrix products, two multiplications and an addition, whatever the model.
    """

    xy: Tensor  # (K, 2P) selects [x..., y...]
    yx: Tensor  # (K, 2P) selects [y..., x...]
    cos: Tensor  # (4, 2P)
    sin: Tensor  # (4, 2P)

    def __init__(self, width: int, plan: _PairPlan) -> None:
        super().__init__()
        p = len(plan.x)
        self.register_buffer("xy", select_columns(width, plan.x + plan.y), persistent=False)  # (K, 2P)
        self.register_buffer("yx", select_columns(width, plan.y + plan.x), persistent=False)
        cos = torch.zeros(4, 2 * p)  # picks cos ψ or cos ψ/2 for each output column
        sin = torch.zeros(4, 2 * p)  # picks ±sin ψ or ±sin ψ/2 (sign of the local transform)
        for k, h in enumerate(plan.half):
            cos[2 * h, k] = cos[2 * h, p + k] = 1.0
            sin[2 * h + 1, k], sin[2 * h + 1, p + k] = 1.0, -1.0
        self.register_buffer("cos", cos, persistent=False)
        self.register_buffer("sin", sin, persistent=False)

    def forward(self, frame: Tensor, values: Tensor, inverse: bool) -> Tensor:
        c = frame @ self.cos  # (B, 2P)
        s = frame @ self.sin
        if inverse:
            s = -s
        return c * (values @ self.xy) + s * (values @ self.yx)


def _turns_as_vector(g: StateGroup, translate: tuple[bool, ...]) -> bool:
    """Whether the local frame turns state group ``g`` as a world vector: a world vector, or a root
    position of two or three axes whose horizontal axes are not translated away."""
    return (g.kind == "position" and g.size >= 2 and not any(translate[:2])) or g.kind == "world_vector"


@dataclass(frozen=True)
class _InputColumns:
    """The blocks of T'_x's unplaced input columns (B, E), in order: the base [state (S), controls (U),
    forces (F)], the heading-rotated pairs (all x', then all y': 2P) from ``rot_at``, sin and cos of
    the angles (A each) from ``sin_at`` and ``cos_at``, the body-rotated vectors (3 columns each) from
    ``vec_at``, the body-frame up (3) from ``up_at``, the joint-limit ramps (all "past high", then all
    "past low") from ``lim_at``, the ground clearances and then how far below the floor each is from
    ``clr_at``."""

    pairs: list[tuple[int, int, int]]  # heading frame: (x, y, half) base columns turned together
    vecs: list[tuple[int, int, int]]  # body frame: (x, y, z) base columns, -1 for a zero
    vec_of: dict[int, int]  # first base column of a body-rotated vector -> its index in ``vecs``
    angles: list[int]  # state columns of the hinge angles
    replaced: dict[int, int]  # base column -> its index in the heading-rotated block
    rot_at: int
    sin_at: int
    cos_at: int
    vec_at: int
    up_at: int
    lim_at: int
    lim_width: int
    clr_at: int
    clr_width: int

    @property
    def width(self) -> int:
        """E, the number of unplaced columns."""
        return self.clr_at + 2 * self.clr_width

    def col(self, c: int) -> int:
        """The column base column ``c`` is read from: its rotated copy where it has one."""
        return self.rot_at + self.replaced[c] if c in self.replaced else c

    def vec_cols(self, first: int) -> list[int]:
        """The three columns of the body-rotated vector whose first base column is ``first``."""
        k = self.vec_of[first]
        return [self.vec_at + 3 * k + i for i in range(3)]

    def inputs_between(self, lo: int, hi: int) -> list[int]:
        """The columns read for base columns ``lo`` to ``hi`` (the controls or the forces): those in no
        body-rotated vector, then the rotated vectors that start among them."""
        in_a_vec = {c for v in self.vecs for c in v if lo <= c < hi}
        picked = [self.col(c) for c in range(lo, hi) if c not in in_a_vec]
        for first in sorted(f for f in self.vec_of if lo <= f < hi):
            picked += self.vec_cols(first)
        return picked


class StructuredEmulator(nn.Module):
    """One super-step of a model: ``forward(state (B,S), controls (B,U), forces (B,F)) -> (B,S)``."""

    x_mean: Tensor  # (D,) T^σ_x statistics
    x_std: Tensor
    y_mean: Tensor  # (S,) T^σ_y statistics
    y_std: Tensor
    # Constant selection matrices (buffers, not saved): see _plan for their shapes.
    _angle_sel: Tensor
    _in_place: Tensor
    _out_place: Tensor
    _quat_sel: Tensor
    _keep: Tensor
    _quat_place: Tensor
    _frame_sel: Tensor
    _half_to_table: Tensor
    _swap: Tensor
    _vec_in_sel: Tensor
    _vec_out_sel: Tensor
    _outer_to_r: Tensor
    _r_offset: Tensor
    _left: Tensor
    _identity_q: Tensor
    _pair_first: Tensor
    _pair_second: Tensor
    _product: Tensor
    _limit_sel: Tensor
    _limit_low: Tensor
    _limit_high: Tensor
    _range_at: Tensor
    _range_low: Tensor
    _range_high: Tensor

    def __init__(
        self,
        layout: StateLayout,
        num_controls: int,
        num_forces: int,
        frame: FrameConfig,
        hidden: Sequence[int] = (64, 64),
        activation: str = "tanh",
        skip: bool = False,
        limits: Sequence[JointLimit] = (),
        horizon: float = 0.0,
        clearance: Clearance | None = None,
    ) -> None:
        super().__init__()
        self.layout = layout
        self.limits = tuple(limits)
        # ground clearance of the geoms that can touch the floor (``neuroanimator.emulator.clearance``)
        self.clearance = clearance
        self.horizon = float(horizon)  # seconds of one super-step, for the limit extrapolation
        self.num_controls = num_controls
        self.num_forces = num_forces
        self.frame = frame
        self.hidden = tuple(hidden)
        self.activation = activation
        self._plan()
        self.core = make_core(self.input_size, layout.size, hidden, activation)
        # thesis 6.1.3: a mass-spring model's step ends with a few Euler steps of its springs
        self.regularizer: SpringRegularization | None = None
        # A linear path beside the MLP: in a good local frame most of a step is close to linear (the
        # lander's body-frame least-squares fit leaves 1% of the variance), so the MLP only has to learn
        # the remainder. Initialised from the least-squares fit by the trainer.
        self.skip = nn.Linear(self.input_size, layout.size) if skip else None
        # normalisation statistics (T^σ), set from training data by ``set_normalization``
        self.register_buffer("x_mean", torch.zeros(self.input_size))
        self.register_buffer("x_std", torch.ones(self.input_size))
        self.register_buffer("y_mean", torch.zeros(layout.size))
        self.register_buffer("y_std", torch.ones(layout.size))

    # ------------------------------------------------------------------ static plan
    def _plan(self) -> None:
        """Decide, once, which columns go where, as constant 0/1 matrices (tracing sees constants).

        Network inputs are picked from ``[state, controls, forces, heading-rotated pairs, sin(angles),
        cos(angles), body-rotated vectors, body-frame up, joint-limit ramps, ground clearances and
        contact ramps]`` and world state changes
        from ``[delta, heading-rotated pairs, body-rotated vectors, root quaternion increment]``, so each transform
        is a handful of graph nodes whatever the model (a small graph is what makes one ONNX call
        cheap).
        """
        self._plan_root_frame()
        cols = self._input_columns()
        gather, groups = self._input_gather(cols)
        self._plan_limits(self.layout.size)
        self._place_inputs(cols, gather, groups)
        self._plan_outputs()
        self._plan_quaternions()
        self._plan_frame()

    def _plan_root_frame(self) -> None:
        """Find the root's orientation in the state and choose the local frame: the body frame (a root
        quaternion and ``FrameConfig.body``), the heading frame (a root quaternion or heading angle and
        ``FrameConfig.rotate``), or none."""
        self._quat: tuple[int, int] | None = None  # columns of the root quaternion's w and z
        self._heading: int | None = None
        for g, sl in self.layout.group_slices():
            if g.kind == "quaternion":
                self._quat = (sl.start, sl.start + 3)
            elif g.kind == "heading":
                self._heading = sl.start
        fr = self.frame
        self._body = bool(fr.body and fr.rotate and self._quat is not None)
        self._rotate = fr.rotate and (self._quat is not None or self._heading is not None) and not self._body

    # ---- T'_x: the network inputs, picked from the base [state (S), controls (U), forces (F)] and what the
    # frame and the features add to it
    def _input_columns(self) -> _InputColumns:
        """Where each block of T'_x's unplaced input columns starts (see ``_InputColumns``)."""
        S, U, F = self.layout.size, self.num_controls, self.num_forces
        pairs = self._heading_pairs()
        vecs, vec_of = self._body_vectors()
        angles = [
            c for g, sl in self.layout.group_slices() if g.kind == "angle" for c in range(sl.start, sl.stop)
        ]
        replaced: dict[int, int] = {}  # base column -> index in the rotated block
        for k, (ix, iy, _h) in enumerate(pairs):
            replaced[ix] = k
            replaced[iy] = len(pairs) + k
        rot_at = S + U + F  # rotated columns follow the base: first all x', then all y'
        sin_at = rot_at + 2 * len(pairs)
        cos_at = sin_at + len(angles)
        vec_at = cos_at + len(angles)  # body frame: the rotated vectors, 3 columns each
        up_at = vec_at + 3 * len(vecs)  # body frame: the up direction in the body frame
        lim_at = up_at + (
            3 if self._body else 0
        )  # joint-limit ramps: first all "past high", then all "past low"
        lim_width = 2 * len(LIMIT_FRACTIONS) * len(self.limits)
        return _InputColumns(
            pairs, vecs, vec_of, angles, replaced,
            rot_at=rot_at, sin_at=sin_at, cos_at=cos_at, vec_at=vec_at, up_at=up_at,
            lim_at=lim_at, lim_width=lim_width,
            clr_at=lim_at + lim_width,  # ground clearances, then how far below the floor each is
            clr_width=0 if self.clearance is None else self.clearance.width,
        )  # fmt: skip

    def _heading_pairs(self) -> list[tuple[int, int, int]]:
        """The heading frame's pairs of base columns turned together, (x, y, half) each: root positions,
        world vectors, the root quaternion's (w, z) and (x, y) (turned by ψ/2), world-axis controls and
        forces. None without a heading frame."""
        if not self._rotate:
            return []
        S, U, translate = self.layout.size, self.num_controls, self.frame.translate
        pairs: list[tuple[int, int, int]] = []
        for g, sl in self.layout.group_slices():
            a = sl.start
            if _turns_as_vector(g, translate):
                pairs.append((a, a + 1, 0))
            elif g.kind == "quaternion":
                pairs += [(a, a + 3, 1), (a + 1, a + 2, 1)]  # (w, z) and (x, y)
        for pair in self.frame.control_pairs:
            pairs.append((S + pair[0], S + pair[1], 0))
        for pair in self.frame.force_pairs:
            pairs.append((S + U + pair[0], S + U + pair[1], 0))
        return pairs

    def _body_vectors(self) -> tuple[list[tuple[int, int, int]], dict[int, int]]:
        """The body frame's vectors of base columns, (x, y, z) each with -1 for a zero (a planar vector):
        root positions, world vectors, world-axis controls and forces; and the index of each by its first
        column. None without a body frame."""
        vecs: list[tuple[int, int, int]] = []
        vec_of: dict[int, int] = {}
        if not self._body:
            return vecs, vec_of
        S, U, translate = self.layout.size, self.num_controls, self.frame.translate
        for g, sl in self.layout.group_slices():
            a = sl.start
            if _turns_as_vector(g, translate):
                vec_of[a] = len(vecs)
                vecs.append((a, a + 1, a + 2 if g.size == 3 else -1))
        for vec in self.frame.control_pairs:
            vec_of[S + vec[0]] = len(vecs)
            vecs.append(tuple(S + c for c in vec) + ((-1,) if len(vec) == 2 else ()))  # type: ignore[arg-type]
        for vec in self.frame.force_pairs:
            vec_of[S + U + vec[0]] = len(vecs)
            vecs.append(tuple(S + U + c for c in vec) + ((-1,) if len(vec) == 2 else ()))  # type: ignore[arg-type]
        return vecs, vec_of

    def _input_gather(self, cols: _InputColumns) -> tuple[list[int], list[tuple[str, int]]]:
        """The unplaced column of each network input, in order, and the input groups (name, width) for
        the normalisation: the state groups, the controls, the forces, the limit ramps, the clearances
        and the contact ramps."""
        S, U, F = self.layout.size, self.num_controls, self.num_forces
        gather: list[int] = []
        groups: list[tuple[str, int]] = []
        for g, sl in self.layout.group_slices():
            picked = self._group_inputs(g, sl, cols)
            if picked:
                gather += picked
                groups.append((g.name, len(picked)))
        for name, lo, hi in (("controls", S, S + U), ("forces", S + U, S + U + F)):
            if hi > lo:
                picked = cols.inputs_between(lo, hi)
                gather += picked
                groups.append((name, len(picked)))
        if cols.lim_width:
            gather += list(range(cols.lim_at, cols.lim_at + cols.lim_width))
            groups.append(("limits", cols.lim_width))
        if cols.clr_width:
            gather += list(range(cols.clr_at, cols.width))
            groups += [("clearance", cols.clr_width), ("contact", cols.clr_width)]
        return gather, groups

    def _group_inputs(self, g: StateGroup, sl: slice, cols: _InputColumns) -> list[int]:
        """The unplaced columns the network reads for state group ``g`` (state columns ``sl``)."""
        body, rot, translate = self._body, self._rotate, self.frame.translate
        if body and sl.start in cols.vec_of:
            return cols.vec_cols(sl.start)
        if g.name in self.frame.slides:
            return []  # how far it has slid: translated away, as a free root's x and y
        if g.kind == "position":
            kept = [i for i in range(g.size) if not (translate and translate[i])]
            return [cols.col(sl.start + i) for i in kept]  # translated axes are 0: dropped (App. F.1)
        if g.kind == "heading":
            return [] if rot else [sl.start]  # the heading defines the frame: 0, dropped
        if g.kind == "quaternion" and body:
            return [cols.up_at, cols.up_at + 1, cols.up_at + 2]  # the attitude, as the direction of "up"
        if g.kind == "quaternion" and rot:
            return [
                cols.col(sl.start),
                cols.col(sl.start + 1),
                cols.col(sl.start + 2),
            ]  # z' is exactly 0: dropped
        if g.kind == "angle":
            idx = [cols.angles.index(c) for c in range(sl.start, sl.stop)]
            return [cols.sin_at + i for i in idx] + [cols.cos_at + i for i in idx]
        return [cols.col(c) for c in range(sl.start, sl.stop)]

    def _place_inputs(self, cols: _InputColumns, gather: list[int], groups: list[tuple[str, int]]) -> None:
        """Keep T'_x's constants: the heading rotation, the angle and body-vector selections (B, S+U+F) ->
        (B, A) and (B, 3K), and the placement of the unplaced columns (E, D)."""
        S, U, F = self.layout.size, self.num_controls, self.num_forces
        in_plan = _PairPlan(*map(tuple, zip(*cols.pairs, strict=True))) if cols.pairs else _PairPlan()
        self._rot_in = _Rotation(S + U + F, in_plan) if cols.pairs else None
        self._angles = tuple(cols.angles)
        self._num_in_vecs = len(cols.vecs)
        self.register_buffer("_angle_sel", select_columns(S, cols.angles), persistent=False)  # (S, A)
        self.register_buffer(
            "_vec_in_sel", _select_or_zero(S + U + F, [c for v in cols.vecs for c in v]), persistent=False
        )  # (S+U+F, 3K)
        self.register_buffer("_in_place", select_columns(cols.width, gather), persistent=False)
        self.input_groups = groups
        self.input_size = len(gather)

    # ---- T'_y: state changes, rotated back to world axes
    def _plan_outputs(self) -> None:
        """``[delta (S), heading-rotated pairs (2Q), body-rotated vectors (3K'), root quaternion increment
        (4, body frame)] @ _out_place`` (W, S) is the world state change; a column that no rotation
        touches is read from ``delta`` as it is."""
        S, rot, body = self.layout.size, self._rotate, self._body
        out_pairs: list[tuple[int, int, int]] = []
        out_vecs: list[tuple[int, int, int]] = []
        for g, sl in self.layout.group_slices():
            a = sl.start
            if g.kind in ("position", "world_vector") and g.size >= 2:
                if rot:
                    out_pairs.append((a, a + 1, 0))
                elif body:
                    out_vecs.append((a, a + 1, a + 2 if g.size == 3 else -1))
            elif g.kind == "quaternion" and rot:
                out_pairs += [(a, a + 3, 1), (a + 1, a + 2, 1)]
        q = len(out_pairs)
        out_gather = list(range(S))
        for k, (ix, iy, _h) in enumerate(out_pairs):
            out_gather[ix] = S + k
            out_gather[iy] = S + q + k
        vec_out_at = S + 2 * q
        for k, vec in enumerate(out_vecs):
            for i, c in enumerate(vec):
                if c >= 0:
                    out_gather[c] = vec_out_at + 3 * k + i
        quat_out_at = vec_out_at + 3 * len(out_vecs)
        if body:
            assert self._quat is not None
            for i in range(4):
                out_gather[self._quat[0] + i] = quat_out_at + i
        out_plan = _PairPlan(*map(tuple, zip(*out_pairs, strict=True))) if out_pairs else _PairPlan()
        self._rot_out = _Rotation(S, out_plan) if out_pairs else None
        self._num_out_vecs = len(out_vecs)
        self.register_buffer(
            "_vec_out_sel", _select_or_zero(S, [c for v in out_vecs for c in v]), persistent=False
        )  # (S, 3K')
        out_width = quat_out_at + (4 if body else 0)
        self.register_buffer("_out_place", select_columns(out_width, out_gather), persistent=False)  # (W, S)

    def _plan_quaternions(self) -> None:
        """Quaternion renormalisation: next = nxt @ keep + normalised(nxt @ quat) @ place."""
        S = self.layout.size
        quats = [sl for g, sl in self.layout.group_slices() if g.kind in ("quaternion", "local_quaternion")]
        self.quaternion_slices = quats
        qcols = [c for sl in quats for c in range(sl.start, sl.stop)]
        self._num_quats = len(quats)
        self.register_buffer("_quat_sel", select_columns(S, qcols), persistent=False)  # (S, 4k)
        keep = torch.eye(S)
        for c in qcols:
            keep[c, c] = 0.0
        self.register_buffer("_keep", keep, persistent=False)  # (S, S): every column but the quaternions
        self.register_buffer(
            "_quat_place", select_columns(S, qcols).T.contiguous(), persistent=False
        )  # (4k, S)

    def _plan_frame(self) -> None:
        """The frame's constants: the state columns it is read from (the root quaternion's (w, z), the
        heading angle, or the whole root quaternion) and the tables of ``frame_of`` and ``_map_delta_body``."""
        S = self.layout.size
        if self._body:
            assert self._quat is not None
            self.register_buffer(
                "_frame_sel", select_columns(S, range(self._quat[0], self._quat[0] + 4)), persistent=False
            )  # (S, 4)
        elif self._quat is not None:
            self.register_buffer("_frame_sel", select_columns(S, self._quat), persistent=False)  # (S, 2)
        elif self._heading is not None:
            self.register_buffer("_frame_sel", select_columns(S, [self._heading]), persistent=False)  # (S, 1)
        # [h², h·swap(h), h] (B, 6) -> [cos ψ, sin ψ, cos ψ/2, sin ψ/2] (B, 4) for h = (cos ψ/2, sin ψ/2)
        table = torch.zeros(6, 4)
        table[0, 0], table[1, 0] = 1.0, -1.0  # cos ψ = ch² - sh²
        table[2, 1] = table[3, 1] = 1.0  # sin ψ = 2 ch sh
        table[4, 2] = table[5, 3] = 1.0
        self.register_buffer("_half_to_table", table, persistent=False)
        self.register_buffer("_swap", torch.tensor([[0.0, 1.0], [1.0, 0.0]]), persistent=False)
        outer_to_r, r_offset = _rotation_from_quaternion()
        self.register_buffer("_outer_to_r", outer_to_r, persistent=False)  # (16, 9)
        self.register_buffer("_r_offset", r_offset, persistent=False)  # (9,)
        self.register_buffer("_left", _left_product(), persistent=False)  # (4, 16)
        self.register_buffer("_identity_q", torch.tensor([1.0, 0.0, 0.0, 0.0]), persistent=False)
        e1, e2 = _pair_expansions()
        self.register_buffer("_pair_first", e1, persistent=False)  # (4, 16)
        self.register_buffer("_pair_second", e2, persistent=False)  # (4, 16)
        self.register_buffer("_product", _product_table(), persistent=False)  # (16, 4)

    def _plan_limits(self, S: int) -> None:
        """``state @ _limit_sel`` (S, K·L) is every limited joint extrapolated to each fraction of the
        super-step; ``_limit_high``/``_limit_low`` (K·L,) the limits repeated to match."""
        k, lims = len(LIMIT_FRACTIONS), self.limits
        sel = torch.zeros(S, k * len(lims))
        high, low = torch.zeros(k * len(lims)), torch.zeros(k * len(lims))
        for j, lim in enumerate(lims):
            for i, a in enumerate(LIMIT_FRACTIONS):
                c = i * len(lims) + j
                sel[lim.position, c] = 1.0
                if lim.velocity is not None:
                    sel[lim.velocity, c] = a * self.horizon
                high[c], low[c] = lim.high, lim.low
        self.register_buffer("_limit_sel", sel, persistent=False)
        self.register_buffer("_limit_high", high, persistent=False)
        self.register_buffer("_limit_low", low, persistent=False)
        self._plan_ranges(S)

    def _plan_ranges(self, S: int) -> None:
        """``state @ _range_at`` (S, M) is the position of each limited joint with a margin, and
        ``_range_low``/``_range_high`` (M,) the range widened by it (see ``JointLimit``)."""
        kept = [lim for lim in self.limits if lim.margin is not None]
        at = torch.zeros(S, len(kept))
        for j, lim in enumerate(kept):
            at[lim.position, j] = 1.0
        self._ranged = bool(kept)
        self.register_buffer("_range_at", at, persistent=False)
        self.register_buffer(
            "_range_low", torch.tensor([lim.low - (lim.margin or 0.0) for lim in kept]), persistent=False
        )
        self.register_buffer(
            "_range_high", torch.tensor([lim.high + (lim.margin or 0.0) for lim in kept]), persistent=False
        )

    def set_limit_margins(self, states: Tensor) -> None:
        """Keep each limited joint's predicted positions within a margin of its range, the margin
        taken from ``states`` (N, S), the training data's states and next states (``limit_margin``)."""
        self.limits = tuple(
            replace(lim, margin=limit_margin(lim, states[:, lim.position])) for lim in self.limits
        )
        self._plan_ranges(self.layout.size)

    def _within_ranges(self, state: Tensor) -> Tensor:
        """(B, S) states with every limited joint that has a margin kept within it."""
        z = state @ self._range_at  # (B, M)
        inside = torch.minimum(torch.maximum(z, self._range_low), self._range_high)
        return state + (inside - z) @ self._range_at.T

    def output_groups(self) -> list[tuple[str, int]]:
        return [(g.name, g.size) for g in self.layout]

    # ------------------------------------------------------------------ frame helpers
    def frame_of(self, state: Tensor) -> Frame:
        """The local frame of each state: in the body frame the root's rotation matrix (B, 9), row-major
        from the unit root quaternion; else the heading table (B, 4): cos ψ, sin ψ, cos ψ/2, sin ψ/2."""
        if self._body:
            q = self._root_quaternion(state)
            outer = (q @ self._pair_first) * (q @ self._pair_second)  # (B, 16): q qᵀ flattened
            return outer @ self._outer_to_r + self._r_offset
        if self._quat is not None:
            wz = state @ self._frame_sel  # (B, 2)
            h = wz / torch.sqrt((wz * wz).sum(dim=1, keepdim=True) + 1e-12)  # twist of q about z
            return torch.cat([h * h, h * (h @ self._swap), h], dim=1) @ self._half_to_table
        psi = state @ self._frame_sel  # (B, 1)
        return torch.cat([torch.cos(psi), torch.sin(psi), torch.cos(0.5 * psi), torch.sin(0.5 * psi)], dim=1)

    def _root_quaternion(self, state: Tensor) -> Tensor:
        """The root quaternion (B, 4), normalised (a client may send one that is not quite unit)."""
        q = state @ self._frame_sel
        return q / (torch.linalg.vector_norm(q, dim=1, keepdim=True) + 1e-12)

    def local_frame(self, state: Tensor) -> Frame | None:
        """The frame of each state if this emulator uses one, else None; compute once per step."""
        return self.frame_of(state) if (self._rotate or self._body) else None

    # ------------------------------------------------------------------ T'_x and T'_y
    def local_inputs(
        self,
        state: Tensor,
        controls: Tensor | None,
        forces: Tensor | None,
        frame: Frame | None = None,
        *,
        place: bool = True,
    ) -> Tensor:
        """T'_x: (B,S), (B,U), (B,F) -> network inputs in the local frame, (B, D), before T^σ_x.

        ``place=False`` returns the unplaced columns (B, E) with ``x = ext @ input_placement``, for an
        export that folds the placement into the first layer.
        """
        parts = [state]
        if self.num_controls:
            assert controls is not None
            parts.append(controls)
        if self.num_forces:
            assert forces is not None
            parts.append(forces)
        base = torch.cat(parts, dim=1) if len(parts) > 1 else state
        ext = [base]
        if self._rot_in is not None:
            ext.append(self._rot_in(self.frame_of(state) if frame is None else frame, base, inverse=False))
        if self._angles:
            a = state @ self._angle_sel
            ext += [torch.sin(a), torch.cos(a)]
        if self._body:
            r = (self.frame_of(state) if frame is None else frame).reshape(-1, 3, 3)
            if self._num_in_vecs:
                vecs = (base @ self._vec_in_sel).reshape(-1, self._num_in_vecs, 3)
                ext.append((vecs @ r).reshape(-1, 3 * self._num_in_vecs))  # rows v^T R = (R^T v)^T
            ext.append(r[:, 2, :])  # R^T e_z: the world's up in the body frame
        if self.limits:
            z = state @ self._limit_sel  # (B, K·L) extrapolated joint positions
            ext += [torch.relu(z - self._limit_high), torch.relu(self._limit_low - z)]
        if self.clearance is not None:
            c = self.clearance(state)  # (B, G·K) heights above the floor
            ext += [c, torch.relu(-c)]
        cols = torch.cat(ext, dim=1) if len(ext) > 1 else base
        return cols @ self._in_place if place else cols

    @property
    def input_placement(self) -> Tensor:
        """(E, D) 0/1 matrix from the unplaced input columns to the network inputs."""
        return self._in_place

    def delta_to_local(self, state: Tensor, delta: Tensor) -> Tensor:
        """(T'_y)^-1: world state changes (B,S) -> local changes (B,S), for building training targets.

        In the body frame the root quaternion's change is the increment q⁻¹ ⊗ q' − 1 in the body frame.
        q' keeps the sign the simulation gave it (MuJoCo integrates the quaternion continuously), so
        the increment is (cos φ/2, sin φ/2 · axis) less the identity (1, 0, 0, 0) for the whole turn φ:
        continuous up to a full turn. Choosing w ≥ 0 instead would jump from +axis to −axis at φ = π, which a tumbling body
        passes within one long super-step (N^100 of the quadrotor: 7% of the examples).
        """
        return self._map_delta(state, delta, inverse=False)

    def delta_to_world(self, state: Tensor, delta_local: Tensor) -> Tensor:
        """T'_y: local state changes (B,S) -> world changes (B,S); translations are not applied to changes."""
        return self._map_delta(state, delta_local, inverse=True)

    def _map_delta(self, state: Tensor, delta: Tensor, inverse: bool, frame: Frame | None = None) -> Tensor:
        if self._body:
            return self._map_delta_body(state, delta, inverse, frame)
        if self._rot_out is None:
            return delta
        rotated = self._rot_out(self.frame_of(state) if frame is None else frame, delta, inverse)
        return torch.cat([delta, rotated], dim=1) @ self._out_place

    def _map_delta_body(self, state: Tensor, delta: Tensor, inverse: bool, frame: Frame | None) -> Tensor:
        r = (self.frame_of(state) if frame is None else frame).reshape(-1, 3, 3)
        parts = [delta]
        if self._num_out_vecs:
            vecs = (delta @ self._vec_out_sel).reshape(-1, self._num_out_vecs, 3)
            turned = vecs @ r.transpose(1, 2) if inverse else vecs @ r  # rows (R v)^T or (R^T v)^T
            parts.append(turned.reshape(-1, 3 * self._num_out_vecs))
        q = self._root_quaternion(state)
        dq = delta @ self._frame_sel  # (B, 4)
        if inverse:  # increment -> change of q: q ⊗ (1 + d) − q = q ⊗ d, bilinear in (q, d)
            parts.append(((q @ self._pair_first) * (dq @ self._pair_second)) @ self._product)
        else:  # change of q -> increment: L(q)ᵀ q' − 1, with q' on the side of q
            left = (q @ self._left).reshape(-1, 4, 4)  # L(q): q ⊗ p = L(q) p
            inc = (left.transpose(1, 2) @ (q + dq).unsqueeze(2)).squeeze(2)
            parts.append(inc - self._identity_q)
        return torch.cat(parts, dim=1) @ self._out_place

    # ------------------------------------------------------------------ T^σ
    def normalize_inputs(self, x: Tensor) -> Tensor:
        return (x - self.x_mean) / self.x_std

    def denormalize_outputs(self, y: Tensor) -> Tensor:
        return y * self.y_std + self.y_mean

    def set_normalization(self, x_local: Tensor, y_local: Tensor, mode: str = "group") -> None:
        """Fit T^σ from training data: inputs (N, D) and local state changes (N, S), eqs. 4.10-4.11.

        ``mode="group"`` shares one mean and deviation per group, as in the thesis; ``"variable"``
        normalises every variable on its own.
        """
        xm, xs = _group_stats(x_local, self.input_groups, mode)
        ym, ys = _group_stats(y_local, self.output_groups(), mode)
        self.x_mean.copy_(xm)
        self.x_std.copy_(xs)
        self.y_mean.copy_(ym)
        self.y_std.copy_(ys)

    # ------------------------------------------------------------------ the step
    def network_targets(self, state: Tensor, next_state: Tensor) -> Tensor:
        """(T^σ_y)^-1 (T'_y)^-1 (T^Δ_y)^-1: what N^σ must output for this transition, (B, S)."""
        return (self.delta_to_local(state, next_state - state) - self.y_mean) / self.y_std

    def network_inputs(
        self, state: Tensor, controls: Tensor | None = None, forces: Tensor | None = None
    ) -> Tensor:
        """T^σ_x T'_x: (B, D) normalised local inputs."""
        return self.normalize_inputs(self.local_inputs(state, controls, forces))

    def finish(self, state: Tensor, y: Tensor) -> Tensor:
        """T^Δ_y T'_y T^σ_y: network output (B,S) -> next state (B,S), quaternions renormalised."""
        return self.apply_delta(state, self.denormalize_outputs(y))

    def apply_delta(self, state: Tensor, delta_local: Tensor, frame: Frame | None = None) -> Tensor:
        """T^Δ_y T'_y: local state change (B,S) -> next state (B,S), quaternions renormalised and
        limited joints kept within their margins (``JointLimit.margin``)."""
        nxt = state + self._map_delta(state, delta_local, inverse=True, frame=frame)
        if self._ranged:
            nxt = self._within_ranges(nxt)
        if not self._num_quats:
            return nxt
        if self._num_quats == 1:  # (B, 4) as it is: two reshapes fewer in the graph
            q = nxt @ self._quat_sel
            q = q / torch.linalg.vector_norm(q, dim=1, keepdim=True)
            return nxt @ self._keep + q @ self._quat_place
        qs = (nxt @ self._quat_sel).reshape(-1, self._num_quats, 4)
        qs = qs / torch.linalg.vector_norm(qs, dim=2, keepdim=True)
        return nxt @ self._keep + qs.reshape(-1, 4 * self._num_quats) @ self._quat_place

    def forward(self, state: Tensor, controls: Tensor | None = None, forces: Tensor | None = None) -> Tensor:
        frame = self.local_frame(state)
        x = self.normalize_inputs(self.local_inputs(state, controls, forces, frame))
        nxt = self.apply_delta(state, self.denormalize_outputs(self.network(x)), frame)
        return nxt if self.regularizer is None else self.regularizer(nxt, controls)

    def network(self, x: Tensor) -> Tensor:
        """N^σ: normalised inputs (B, D) -> normalised local state changes (B, S)."""
        y = self.core(x)
        return y + self.skip(x) if self.skip is not None else y

    def architecture(self) -> dict[str, object]:
        return {
            "hidden": list(self.hidden),
            "activation": self.activation,
            "input_size": self.input_size,
            "input_groups": [list(g) for g in self.input_groups],
            "output_size": self.layout.size,
            "weights": sum(p.numel() for p in self.parameters()),
            "skip": self.skip is not None,
            "limits": len(self.limits),
            "clearance": [] if self.clearance is None else list(self.clearance.geoms),
            "proximity": [] if self.clearance is None else [list(p) for p in self.clearance.pairs],
            "tendons": [] if self.clearance is None else list(self.clearance.tendons),
            "frame": {
                "translate": list(self.frame.translate),
                "rotate": self.frame.rotate,
                "force_pairs": [list(p) for p in self.frame.force_pairs],
                "control_pairs": [list(p) for p in self.frame.control_pairs],
                "body": self._body,
                "slides": list(self.frame.slides),
            },
        }


# Input groups that are ramps: zero until a constraint engages (a joint past its limit, a geom below the
# floor or into another), so most of their values are zero. A deviation over all rows is then small and
# puts the few engaged values tens of deviations out (the runner's limit ramps reached 120, its contact
# ramps 40), where a network extrapolates; so zero stays zero and the engaged values are scaled by their
# own root mean square.
RAMP_GROUPS = ("limits", "contact")


def _ramp_scale(block: Tensor) -> Tensor:
    """(W,) the root mean square of each column's nonzero values of a ramp block (N, W); 1 where none."""
    count = (block != 0).sum(dim=0)
    rms = torch.sqrt((block**2).sum(dim=0) / count.clamp_min(1))
    return torch.where(count > 0, rms, torch.ones_like(rms))


def _group_stats(data: Tensor, groups: Sequence[tuple[str, int]], mode: str) -> tuple[Tensor, Tensor]:
    if mode not in ("group", "variable"):
        raise ValueError(f"normalization must be 'group' or 'variable', got {mode!r}")
    means, stds = [], []
    at = 0
    for name, width in groups:
        block = data[:, at : at + width].double()
        at += width
        if name in RAMP_GROUPS:
            scale = _ramp_scale(block.reshape(-1, 1)).expand(width) if mode == "group" else _ramp_scale(block)
            means.append(torch.zeros(width, dtype=torch.float64))
            stds.append(scale)
        elif mode == "group":
            m = block.mean()
            s = block.std() if block.numel() > 1 else torch.tensor(0.0, dtype=torch.float64)
            means.append(m.expand(width))
            stds.append(s.expand(width))
        else:
            means.append(block.mean(dim=0))
            stds.append(block.std(dim=0) if block.shape[0] > 1 else torch.zeros(width, dtype=torch.float64))
    mean = torch.cat(means).float()
    std = torch.cat(stds).float()
    # a constant variable carries no information: leave it unscaled rather than divide by ~0
    std = torch.where(std > 1e-8, std, torch.ones_like(std))
    return mean, std
