"""A hierarchical emulator's step with its local networks stacked: the graph that ONNX serves.

``HierarchicalEmulator.forward`` runs the parts one by one: for each part its frame maps, its
network and the map back to world values, about a thousand small graph nodes for the dolphin. At a
batch of one, ONNX Runtime's fixed cost per node is most of the step. ``StackedStep`` computes the same
map with the K parts on a leading axis, so each stage is a few nodes whatever K:

1. every part's vectors (its points relative to its centre, its frame and the predicted next one,
   its neighbours) are two gathers of ``z = [state, frames, next frames]`` and a difference, shaped
   (K, V, 3, B) with each part padded to the widest, and turned into the part's axes by three
   elementwise products;
2. each part's network reads its rows of ``X = [turned vectors, kept values, controls]`` (K, E, B):
   the map from X to a network's own inputs, its normalisation and its linear path are folded into
   stacked weights (K, H, E), so the K networks are batched matrix products;
3. the outputs (the part's next values in the next frame, the state change already added) are
   turned back by the next frames' axes, the next centres added, and one gather puts every value in
   its place in the state; the regulariser's Euler steps (``SpringRegularization.features``) follow.

The values run feature-major, (features, B), from the first transpose of the state to the last:
moving values is then a gather of whole rows (ONNX Runtime copies a row of B values at once; a gather
of columns moves one value at a time and cost more than the seven networks at B = 1,024). Pads read
a zero row or meet zero weights, so they never reach a value. The map equals
``HierarchicalEmulator.forward`` (``tests/test_hierarchy.py`` checks both in torch and in ONNX); the
torch emulator stays the one that trains and that BPTT differentiates.

Shapes: B batch, S state, U controls, K parts, Q = 18 frame values per part, V vectors per part,
E = 3V + C stacked input columns, O stacked output columns, H hidden units.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from neuroanimator.emulator.folding import fold_normalization
from neuroanimator.emulator.hierarchy import FRAME_SIZE, HierarchicalEmulator
from neuroanimator.emulator.regularizer import SpringRegularization
from neuroanimator.emulator.structured import StructuredEmulator

# rows of a part's frame block (FRAME_SIZE values): centre, axis1, axis2, centre_vel, axis1_rate, axis2_rate
_CENTRE, _CENTRE_VEL = 0, 9


def stackable(emu: HierarchicalEmulator) -> bool:
    """True when every local network is plain: no frame of its own, no angles or limits, and the same
    hidden layers (what ``StackedStep`` folds). Its "forces" are the frame and neighbour inputs."""
    nets = [net for _, net in emu.networks[1:]]
    return all(
        net._rot_in is None
        and net._rot_out is None
        and not net._body
        and not net._angles
        and not net.limits
        and net.hidden == nets[0].hidden
        and net.activation == nets[0].activation
        for net in nets
    )


def _folded_layers(net: StructuredEmulator) -> tuple[list[nn.Linear], nn.Linear | None]:
    """The network's layers with its normalisation folded in (``export.fold_normalization``), and its
    folded linear path (None without one)."""

    folded = fold_normalization(net)
    skip = None if isinstance(folded, nn.Sequential) else folded.skip
    core = folded if skip is None else folded.core
    return [mod for mod in core if isinstance(mod, nn.Linear)], skip


def _frozen(t: Tensor) -> nn.Parameter:
    return nn.Parameter(t.detach().clone(), requires_grad=False)


def _axes(frames: Tensor) -> Tensor:
    """Feature-major frames (K, 6, 3, B) -> each part's axes R (K, 3, 3, B): R[k, i, j] is the i-th
    component of axis e_j (Gram-Schmidt of axis1 and axis2, as ``hierarchy._basis``)."""
    a, b = frames[:, 1], frames[:, 2]  # (K, 3, B)
    e1 = a / torch.sqrt((a * a).sum(dim=1, keepdim=True) + 1e-12)
    b = b - (b * e1).sum(dim=1, keepdim=True) * e1
    e2 = b / torch.sqrt((b * b).sum(dim=1, keepdim=True) + 1e-12)
    e3 = e1[:, [1, 2, 0]] * e2[:, [2, 0, 1]] - e1[:, [2, 0, 1]] * e2[:, [1, 2, 0]]
    return torch.stack([e1, e2, e3], dim=2)


def _turn(v: Tensor, r: Tensor) -> Tensor:
    """Vectors (K, V, 3, B) as rows times their part's matrix (K, 3, 3, B): vᵀR, (K, V, 3, B).

    Three products and two sums written out: a sum over a middle axis of size 3 is one of ONNX
    Runtime's slow reductions at a batch of one."""
    v0, v1, v2 = v.split(1, dim=2)
    r0, r1, r2 = r.split(1, dim=1)  # (K, 1, 3, B): row i of each R
    return v0 * r0 + v1 * r1 + v2 * r2


def _part_vectors(emu: HierarchicalEmulator, k: int, plus: Tensor, minus: Tensor) -> tuple[Tensor, Tensor]:
    """Fill part k's vectors (V, 3) as rows of z = [state, frames, next frames, 0]: vector j is
    ``z[plus[j]] - z[minus[j]]``, in the order [points' positions, points' velocities, frame rows 1-5,
    next frame rows 0-5, neighbours' positions, neighbours' velocities], points and neighbours relative
    to the part's centre (positions) or its centre's velocity (velocities). Returns the state rows
    (3p,) of the points' positions and of their velocities."""
    S, K, Q = emu.layout.size, len(emu.parts), FRAME_SIZE
    m = emu.part_map(k)
    p, n = m.points, m.neighbours
    centre, centre_vel = S + Q * k + _CENTRE, S + Q * k + _CENTRE_VEL
    nxt = S + K * Q + Q * k

    def put(j: int, rows: Tensor, less: int | None) -> None:
        """Vector j: the rows ``rows`` (3,) of z, less the frame vector at ``less``."""
        plus[j] = rows
        if less is not None:
            minus[j] = torch.arange(less, less + 3)

    pos_rows = (m.pick @ m.pos).argmax(dim=0)  # (3p,) state index of each point value
    vel_rows = (m.pick @ m.vel).argmax(dim=0)
    for i in range(p):
        put(i, pos_rows[3 * i : 3 * i + 3], centre)
        put(p + i, vel_rows[3 * i : 3 * i + 3], centre_vel)
    for r in range(1, 6):  # the frame now, its centre left out (it is the origin)
        put(2 * p + r - 1, torch.arange(S + Q * k + 3 * r, S + Q * k + 3 * r + 3), None)
    for r in range(6):  # the next frame; its centre relative to this one
        put(2 * p + 5 + r, torch.arange(nxt + 3 * r, nxt + 3 * r + 3), centre if r == 0 else None)
    npos, nvel = m.near_pos.argmax(dim=0), m.near_vel.argmax(dim=0)
    for i in range(n):
        put(2 * p + 11 + i, npos[3 * i : 3 * i + 3], centre)
        put(2 * p + 11 + n + i, nvel[3 * i : 3 * i + 3], centre_vel)
    return pos_rows, vel_rows


def _part_io(emu: HierarchicalEmulator, k: int, V: int, P: int, C_state: int) -> tuple[Tensor, Tensor]:
    """Part k's maps, float64: ``to_net`` (E, S_k + U + extra) from the stacked input columns
    X = [turned vectors (3V), kept state values (C_state), controls (U)] to its network's own input
    columns [part values (S_k), controls, extra (its frame and neighbour vectors)], and ``to_out``
    (S_k, 6P + C_state) from its values to the stacked output columns [points' positions, points'
    velocities (6P), kept values]."""
    m = emu.part_map(k)
    U, p, s_k = emu.num_controls, m.points, m.keep.shape[0]
    extra = 3 * (11 + 2 * m.neighbours)
    to_net = torch.zeros(3 * V + C_state + U, s_k + U + extra, dtype=torch.float64)
    to_out = torch.zeros(s_k, 6 * P + C_state, dtype=torch.float64)
    slot = 0
    for j in range(s_k):
        pos_hit, vel_hit = m.pos[j].nonzero(), m.vel[j].nonzero()
        if len(pos_hit):
            i3 = int(pos_hit[0, 0])  # 3·point + axis
            to_net[i3, j] = to_out[j, i3] = 1.0
        elif len(vel_hit):
            i3 = int(vel_hit[0, 0])
            to_net[3 * p + i3, j] = to_out[j, 3 * P + i3] = 1.0
        else:
            to_net[3 * V + slot, j] = to_out[j, 6 * P + slot] = 1.0
            slot += 1
    for i in range(U):
        to_net[3 * V + C_state + i, s_k + i] = 1.0
    for e in range(extra):
        to_net[3 * (2 * p) + e, s_k + U + e] = 1.0
    return to_net, to_out


class StackedStep(nn.Module):
    """``forward(state (B,S), controls (B,U)) -> (B,S)``: the hierarchy's step, parts stacked."""

    _frames: Tensor  # (K·Q, S) every part's frame quantities
    _shift: Tensor  # (K·Q, S) the mean of the parts' centres, in every part's centre rows
    _vec_plus: Tensor  # (K·V·3,) row of z for each vector value
    _vec_minus: Tensor  # (K·V·3,) row of z subtracted from it (the zero row where none)
    _kept: Tensor  # (K·C,) row of [state, controls, 0] in each part's kept block
    _offset: Tensor  # (K·2P·3,) row of [next frames, 0] added to each turned-back point value
    _quats: Tensor  # (4n,) the quaternions' rows in the output values
    _place: Tensor  # (S,) row of [output values, renormalised quaternions] for each state value

    def __init__(self, emu: HierarchicalEmulator) -> None:
        super().__init__()
        if not stackable(emu):
            raise ValueError("the local networks cannot be stacked (a frame of their own, angles or limits)")
        dtype = emu.glob.x_mean.dtype
        emu = copy.deepcopy(emu).double().eval()  # the folded weights are made in float64
        with torch.no_grad():
            self._build(emu)
        self.to(dtype)

    def _build(self, emu: HierarchicalEmulator) -> None:
        self.num_parts, self.num_controls = len(emu.parts), emu.num_controls
        self._build_global(emu)
        point_rows, kept_rows = self._build_vectors(emu)
        self._build_networks(emu)
        self._build_placement(emu, point_rows, kept_rows)
        self.regularizer: SpringRegularization | None = emu.regularizer

    def _build_global(self, emu: HierarchicalEmulator) -> None:
        """The global stage: the global network with its normalisation folded, on frames minus the mean
        centre."""
        self.register_buffer("_frames", emu._frames.T.contiguous(), persistent=False)
        self.register_buffer("_shift", emu._shift.T.contiguous(), persistent=False)
        glob_layers, glob_skip = _folded_layers(emu.glob)
        self.glob_w = nn.ParameterList(_frozen(lin.weight) for lin in glob_layers)  # (out, in)
        self.glob_b = nn.ParameterList(_frozen(lin.bias[:, None]) for lin in glob_layers)
        self.glob_skip_w = _frozen(glob_skip.weight) if glob_skip is not None else None
        self.glob_skip_b = _frozen(glob_skip.bias[:, None]) if glob_skip is not None else None

    def _build_vectors(
        self, emu: HierarchicalEmulator
    ) -> tuple[list[tuple[Tensor, Tensor]], list[list[int]]]:
        """Stage 1's gathers: each part's vectors as rows of z (``_part_vectors``), each padded to the
        widest part's V, and each part's kept block [its kept state values (padded), the controls] as rows
        of [state, controls, 0]. Returns, per part, its points' position and velocity rows (3p,) each
        and the state rows it keeps."""
        S, U, K = emu.layout.size, emu.num_controls, len(emu.parts)
        maps = [emu.part_map(k) for k in range(K)]
        V = max(2 * m.points + 11 + 2 * m.neighbours for m in maps)
        zero_z = S + 2 * K * FRAME_SIZE  # the zero row appended to z = [state, frames, next frames]
        plus = torch.full((K, V, 3), zero_z, dtype=torch.long)
        minus = torch.full((K, V, 3), zero_z, dtype=torch.long)
        point_rows = [_part_vectors(emu, k, plus[k], minus[k]) for k in range(K)]
        kept_rows: list[list[int]] = []  # per part: the state values it keeps as they are
        for m in maps:
            keep_diag = torch.diagonal(m.keep) > 0.5
            kept_rows.append([int(m.pick[:, j].argmax()) for j in range(m.keep.shape[0]) if keep_diag[j]])
        self.V, self.P = V, max(m.points for m in maps)
        self.register_buffer("_vec_plus", plus.reshape(-1), persistent=False)
        self.register_buffer("_vec_minus", minus.reshape(-1), persistent=False)
        C_state = max(len(c) for c in kept_rows)
        C = C_state + U  # each part's kept block: its kept state values (padded), then the controls
        kept = torch.full((K, C), S + U, dtype=torch.long)  # of [state, controls, 0]: pads read the zero
        for k, rows in enumerate(kept_rows):
            kept[k, : len(rows)] = torch.tensor(rows, dtype=torch.long)
            kept[k, C_state:] = torch.arange(S, S + U)
        self.C = C
        self.register_buffer("_kept", kept.reshape(-1), persistent=False)
        return point_rows, kept_rows

    def _build_networks(self, emu: HierarchicalEmulator) -> None:
        """Stage 2: the K networks' folded weights stacked, each reading X (E) through its map to its own
        input columns (``_part_io``) and writing its outputs, the state change added to its values and its
        linear path, to the stacked output columns O."""
        C_state = self.C - emu.num_controls
        firsts, firsts_b, mids, mids_b, outs, outs_b = [], [], [], [], [], []
        for k, (_, net) in enumerate(emu.networks[1:]):
            to_net, to_out = _part_io(emu, k, self.V, self.P, C_state)
            s_k = emu.part_map(k).keep.shape[0]
            layers, skip = _folded_layers(net)
            firsts.append((to_net @ layers[0].weight.T).T)  # (H, E)
            firsts_b.append(layers[0].bias[:, None])
            mids.append([layer.weight for layer in layers[1:-1]])
            mids_b.append([layer.bias[:, None] for layer in layers[1:-1]])
            w_h = layers[-1].weight.T @ to_out  # (H, O)
            # X -> output: the part's own values (the state change is added to them) and the linear path
            w_x = to_net[:, :s_k] @ to_out
            bias: Tensor = layers[-1].bias
            if skip is not None:
                w_x = w_x + to_net @ skip.weight.T @ to_out
                bias = bias + skip.bias
            outs.append(torch.cat([w_h, w_x], dim=0).T)  # (O, H + E)
            outs_b.append((bias @ to_out)[:, None])
        self.first_w, self.first_b = _frozen(torch.stack(firsts)), _frozen(torch.stack(firsts_b))
        self.mid_w = nn.ParameterList(_frozen(torch.stack([w[i] for w in mids])) for i in range(len(mids[0])))
        self.mid_b = nn.ParameterList(
            _frozen(torch.stack([b[i] for b in mids_b])) for i in range(len(mids[0]))
        )
        self.out_w, self.out_b = _frozen(torch.stack(outs)), _frozen(torch.stack(outs_b))
        self.act = emu.networks[1][1].core[1]  # the shared activation module

    def _build_placement(
        self, emu: HierarchicalEmulator, point_rows: list[tuple[Tensor, Tensor]], kept_rows: list[list[int]]
    ) -> None:
        """Stage 3: output values [turned points (K·6P), kept (K·C_state)] -> state values: the next
        centre row added to each turned-back point value, the quaternions' rows, and the row of
        [output values, renormalised quaternions] each state value is read from."""
        S, K, Q, P = emu.layout.size, self.num_parts, FRAME_SIZE, self.P
        C_state = self.C - self.num_controls
        O_vec = 6 * P
        offset = torch.full((K, 2 * P, 3), K * Q, dtype=torch.long)  # of [next frames, 0]
        place = torch.full((S,), -1, dtype=torch.long)
        for k, ((pos_rows, vel_rows), rows) in enumerate(zip(point_rows, kept_rows, strict=True)):
            for i in range(emu.part_map(k).points):
                offset[k, i] = torch.arange(Q * k + _CENTRE, Q * k + _CENTRE + 3)
                offset[k, P + i] = torch.arange(Q * k + _CENTRE_VEL, Q * k + _CENTRE_VEL + 3)
                place[pos_rows[3 * i : 3 * i + 3]] = k * O_vec + torch.arange(3 * i, 3 * i + 3)
                place[vel_rows[3 * i : 3 * i + 3]] = k * O_vec + torch.arange(3 * (P + i), 3 * (P + i) + 3)
            for slot, r in enumerate(rows):
                place[r] = K * O_vec + k * C_state + slot
        qrows = [r for sl in emu.quaternion_slices for r in range(sl.start, sl.stop)]
        self.num_quats = len(qrows) // 4
        quats = place[qrows].clone()  # where each quaternion value sits in the output values
        place[qrows] = K * (O_vec + C_state) + torch.arange(len(qrows))  # ... and after renormalisation
        assert (place >= 0).all(), "every state value is some part's"
        self.register_buffer("_offset", offset.reshape(-1), persistent=False)
        self.register_buffer("_quats", quats, persistent=False)
        self.register_buffer("_place", place, persistent=False)

    def _global(self, cols: Tensor) -> Tensor:
        """The folded global network, feature-major: (D, B) -> change of the frames (K·Q, B)."""
        h = cols
        for w, b in zip(self.glob_w[:-1], self.glob_b[:-1], strict=True):
            h = self.act(w @ h + b)
        out = self.glob_w[-1] @ h + self.glob_b[-1]
        if self.glob_skip_w is not None and self.glob_skip_b is not None:
            out = out + self.glob_skip_w @ cols + self.glob_skip_b
        return out

    def forward(self, state: Tensor, controls: Tensor | None = None) -> Tensor:
        K, V, P = self.num_parts, self.V, self.P
        s = state.T  # (S, B): feature-major from here on
        u = controls.T if controls is not None and self.num_controls else None
        zero = s[:1] * 0.0  # (1, B) the row that pads read
        frames = self._frames @ s
        glob_in = frames - self._shift @ s
        next_frames = frames + self._global(torch.cat([glob_in, u]) if u is not None else glob_in)

        # stage 1: vectors in the parts' axes, and the kept values
        z = torch.cat([s, frames, next_frames, zero])
        vectors = (z[self._vec_plus] - z[self._vec_minus]).reshape(K, V, 3, -1)
        # the axes now and next in one go (the parts' frames stacked twice over)
        axes = _axes(torch.cat([frames, next_frames]).reshape(2 * K, 6, 3, -1))
        turned = _turn(vectors, axes[:K])  # (K, V, 3, B): each vᵀR
        base = torch.cat([s, u, zero]) if u is not None else torch.cat([s, zero])
        x = torch.cat([turned.reshape(K, 3 * V, -1), base[self._kept].reshape(K, self.C, -1)], dim=1)

        # stage 2: the K networks as batched products, (K, ·, E) @ (K, E, B)
        h = self.act(self.first_w @ x + self.first_b)
        for w, b in zip(self.mid_w, self.mid_b, strict=True):
            h = self.act(w @ h + b)
        y = self.out_w @ torch.cat([h, x], dim=1) + self.out_b  # (K, O, B)

        # stage 3: back to world values by the next frames' axes, the next centres added, placed
        local = y[:, : 6 * P].reshape(K, 2 * P, 3, -1)
        pts = _turn(local, axes[K:].transpose(1, 2))  # each R'v
        pts = pts.reshape(K * 6 * P, -1)
        pts = pts + torch.cat([next_frames, zero])[self._offset]
        values = torch.cat([pts, y[:, 6 * P :].reshape(-1, pts.shape[1])])  # (K·O, B)
        if self.num_quats:
            q = values[self._quats].reshape(self.num_quats, 4, -1)
            qw, qx, qy, qz = q.split(1, dim=1)
            q = q / torch.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            values = torch.cat([values, q.reshape(4 * self.num_quats, -1)])
        nxt = values[self._place]
        if self.regularizer is not None:
            nxt = self.regularizer.features(nxt, u)
        return nxt.T
