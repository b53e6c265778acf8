"""Articulated hierarchical emulators (thesis 4.4, Fig. 4.8): a trunk network, then one network per
branch (limb), composed into the core of one ``StructuredEmulator``.

The runner of the thesis is emulated by five networks: a torso network (the root's position,
orientation and velocities, the neck and waist joints) and a network per arm and per leg (its joints'
angles and rates). Here that composition is the core N^σ of a structured emulator, so everything
around it (the root frame T'_x, normalisation T^σ, the state change T^Δ and its quaternion
renormalisation) is the one-network emulator's, and the whole step is one module: one ONNX graph, one
torch path for BPTT.

In normalised local coordinates (the emulator's network inputs x, (B, D), and outputs y, (B, S)):

1. the **trunk** network reads all of x and writes the columns of y that no branch holds;
2. each **branch** network reads the columns of x of its own groups, the trunk's groups and the groups
   it lists in ``reads``, the controls it lists, the joint-limit ramps of its own joints, the ground
   clearance of the geoms its joints move (``neuroanimator.emulator.clearance``), and the trunk's output (its predicted change, in the same frame), and writes its groups' columns of y.

While training (``self.training``) the branches read the trunk's output detached: every network learns
its own outputs only, as the thesis trained each network on its own, and a branch learns from the
trunk prediction it will be given. Each network has its own linear path beside its MLP.

Shapes: B batch, D network inputs, S state (network outputs), T trunk outputs, d_k and o_k a branch's
inputs and outputs.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from neuroanimator.core.model_spec import Branch
from neuroanimator.emulator.clearance import FRACTIONS, Clearance
from neuroanimator.emulator.structured import LIMIT_FRACTIONS, StructuredEmulator, make_core, select_columns

TRUNK = "trunk"


RIDGE = 1e-3  # per example, on unit-variance inputs


def ridge_fit(x: Tensor, y: Tensor) -> Tensor:
    """(d+1, o) affine least squares of y (N, o) on x (N, d) with a small ridge on the weights (not the
    bias): inputs that are almost always zero (a joint-limit ramp that a few examples reach) would
    otherwise get weights that fit those few exactly and blow up on the next."""
    a = torch.cat([x.double(), torch.ones(x.shape[0], 1, dtype=torch.float64)], dim=1)
    reg = torch.eye(a.shape[1], dtype=torch.float64) * (RIDGE * x.shape[0])
    reg[-1, -1] = 0.0
    return torch.linalg.solve(a.T @ a + reg, a.T @ y.double())


class _Net(nn.Module):
    """One network of the hierarchy: an MLP plus a linear path, (B, d) -> (B, o).

    With ``members`` > 1 the MLP is the mean of that many MLPs of the same widths, started apart and
    each trained on its own error (``member_outputs``): an ensemble, whose mean errs less on runs it has
    not seen than one network does (two of the runner's left-leg networks: an eighth less on held-out
    runs, BENCHMARKS.md)."""

    def __init__(
        self, inputs: int, outputs: int, hidden: Sequence[int], activation: str, members: int = 1
    ) -> None:
        super().__init__()
        if members < 1:
            raise ValueError(f"a network needs at least one member, got {members}")
        self.mlp = make_core(inputs, outputs, hidden, activation)
        self.more = nn.ModuleList(make_core(inputs, outputs, hidden, activation) for _ in range(members - 1))
        self.skip = nn.Linear(inputs, outputs)

    @property
    def members(self) -> int:
        return 1 + len(self.more)

    def forward(self, x: Tensor) -> Tensor:
        y = self.mlp(x)
        if len(self.more):
            for m in self.more:
                y = y + m(x)
            y = y / self.members
        return y + self.skip(x)

    def member_outputs(self, x: Tensor) -> Tensor:
        """(K, B, o): what each of the K members predicts on its own (its MLP and the linear path)."""
        s = self.skip(x)
        return torch.stack([s + m(x) for m in (self.mlp, *self.more)])

    def start_from_linear(self, x: Tensor, y: Tensor) -> None:
        """Set the linear path to the ridge fit of y (N, o) on x (N, d) (``ridge_fit``) and quieten every
        member's last layer, so that training starts from the linear model."""
        w = ridge_fit(x, y).float()
        with torch.no_grad():
            self.skip.weight.copy_(w[:-1].T)
            self.skip.bias.copy_(w[-1])
            for mlp in (self.mlp, *self.more):
                last = mlp[-1]
                assert isinstance(last, nn.Linear)
                last.weight.mul_(0.01)
                last.bias.zero_()


def own_geoms(clr: Clearance, columns: set[int]) -> list[int]:
    """The probed geoms (indices of ``clr.geoms``) that joints at these state columns move."""
    return [g for g in range(len(clr.geoms)) if clr.state_columns(g) & columns]


def branch_geoms(emu: StructuredEmulator, b: Branch) -> list[str]:
    """The geoms whose ground clearance branch ``b``'s network reads, by name."""
    if emu.clearance is None:
        return []
    own = {c for g, sl in emu.layout.group_slices() if g.name in b.groups for c in range(sl.start, sl.stop)}
    return [emu.clearance.geoms[g] for g in own_geoms(emu.clearance, own)]


def trunk_groups(names: Sequence[str], branches: Sequence[Branch]) -> list[str]:
    """The state groups the trunk writes: those no branch holds, in the layout's order."""
    held = {g for b in branches for g in b.groups}
    return [n for n in names if n not in held]


def check_branches(emu: StructuredEmulator, branches: Sequence[Branch], control_names: Sequence[str]) -> None:
    """Raise ``ValueError`` unless the branches hold distinct, known groups, leave the trunk some, read
    known groups and controls, and the controls are one block (no world-axis control vectors)."""
    names = [g.name for g in emu.layout]
    held = [g for b in branches for g in b.groups]
    unknown = sorted(set(held) - set(names))
    twice = sorted({g for g in held if held.count(g) > 1})
    if unknown or twice:
        raise ValueError(f"branches must hold known state groups once each: unknown {unknown}, twice {twice}")
    if not trunk_groups(names, branches):
        raise ValueError("the branches hold every state group: the trunk network would write nothing")
    if len({b.name for b in branches}) != len(branches) or TRUNK in {b.name for b in branches}:
        raise ValueError(f"branch names must be distinct and not {TRUNK!r}")
    for b in branches:
        bad = sorted(set(b.reads) - set(names))
        if bad:
            raise ValueError(f"branch {b.name!r} reads unknown state groups {bad}")
        bad = sorted(set(b.controls or []) - set(control_names))
        if bad:
            raise ValueError(f"branch {b.name!r} reads unknown controls {bad}")
    if emu.frame.control_pairs:
        raise ValueError("an articulated hierarchy needs controls that are not world-axis vectors")


class ArticulatedCore(nn.Module):
    """N^σ of an articulated hierarchy: normalised inputs (B, D) -> normalised local changes (B, S)."""

    _trunk_out: Tensor  # (T, S) places the trunk's outputs
    _place: list[Tensor]

    def __init__(
        self,
        emu: StructuredEmulator,
        branches: Sequence[Branch],
        control_names: Sequence[str],
        trunk_hidden: Sequence[int],
        branch_hidden: Sequence[int],
        activation: str,
        members: int = 1,
    ) -> None:
        super().__init__()
        check_branches(emu, branches, control_names)
        self.members = members
        self.branches = tuple(branches)
        self.trunk_hidden, self.branch_hidden = tuple(trunk_hidden), tuple(branch_hidden)
        lay = emu.layout
        names = [g.name for g in lay]
        self.trunk_writes = trunk_groups(names, branches)
        # where each input group sits among the D network inputs
        at, in_cols = 0, {}
        for name, width in emu.input_groups:
            in_cols[name] = list(range(at, at + width))
            at += width
        d = self.input_size = at
        out_cols = {g.name: list(range(sl.start, sl.stop)) for g, sl in lay.group_slices()}
        trunk_out = [c for g in self.trunk_writes for c in out_cols[g]]
        self.register_buffer(
            "_trunk_out", select_columns(lay.size, trunk_out).T.contiguous(), persistent=False
        )
        self.trunk = _Net(d, len(trunk_out), trunk_hidden, activation, members)
        nets, self.inputs = [], []
        for k, b in enumerate(branches):
            groups = [*b.groups, *self.trunk_writes, *(g for g in b.reads if g not in b.groups)]
            cols = [c for g in groups if g in in_cols for c in in_cols[g]]
            if "controls" in in_cols:
                wanted = control_names if b.controls is None else b.controls
                cols += [in_cols["controls"][list(control_names).index(c)] for c in wanted]
            cols += self._own_limit_columns(emu, b, in_cols, out_cols)
            cols += self._own_clearance_columns(emu, b, in_cols, out_cols)
            outs = [c for g in b.groups for c in out_cols[g]]
            self.register_buffer(f"_idx{k}", torch.tensor(cols, dtype=torch.long), persistent=False)
            self.register_buffer(
                f"_place{k}", select_columns(lay.size, outs).T.contiguous(), persistent=False
            )
            self.inputs.append(len(cols) + len(trunk_out))
            nets.append(_Net(len(cols) + len(trunk_out), len(outs), branch_hidden, activation, members))
        self.nets = nn.ModuleList(nets)

    @staticmethod
    def _own_limit_columns(
        emu: StructuredEmulator, b: Branch, in_cols: dict[str, list[int]], out_cols: dict[str, list[int]]
    ) -> list[int]:
        """The input columns of the limit ramps of the branch's own joints (see ``structured``'s
        ``_plan_limits``: for fraction i and limit j of L, column i·L + j, upper ramps then lower)."""
        if "limits" not in in_cols:
            return []
        own = {c for g in b.groups for c in out_cols[g]}
        lims = emu.limits
        first, k = in_cols["limits"][0], len(LIMIT_FRACTIONS)
        cols = []
        for side in range(2):
            for i in range(k):
                for j, lim in enumerate(lims):
                    if lim.position in own:
                        cols.append(first + side * k * len(lims) + i * len(lims) + j)
        return cols

    @staticmethod
    def _own_clearance_columns(
        emu: StructuredEmulator, b: Branch, in_cols: dict[str, list[int]], out_cols: dict[str, list[int]]
    ) -> list[int]:
        """The input columns of the ground clearance and contact ramps of the geoms the branch's joints
        move (a leg's thigh, shank, foot and toes): column g·K + k of each block for geom g."""
        clr = emu.clearance
        if clr is None or "clearance" not in in_cols:
            return []
        own = {c for g in b.groups for c in out_cols[g]}
        k = len(FRACTIONS)
        mine = own_geoms(clr, own)
        return [
            in_cols[block][g * k + i] for block in ("clearance", "contact") for g in mine for i in range(k)
        ]

    def selection(self, k: int) -> Tensor:
        """(D, d_k − T) the 0/1 matrix that picks branch k's inputs (``pick`` gathers them)."""
        return select_columns(self.input_size, self.input_columns(k))

    def input_columns(self, k: int) -> list[int]:
        """The emulator's input columns that branch k reads, in order."""
        idx = getattr(self, f"_idx{k}")
        assert isinstance(idx, Tensor)
        return [int(c) for c in idx.tolist()]

    def pick(self, x: Tensor, k: int) -> Tensor:
        """(B, d_k − T) branch k's inputs of x (B, D): ``x @ selection(k)``, gathered rather than
        multiplied (a tenth of the time: the product was a twentieth of a training step)."""
        idx = getattr(self, f"_idx{k}")
        assert isinstance(idx, Tensor)
        return x.index_select(1, idx)

    def placement(self, k: int) -> Tensor:
        """(o_k, S) the 0/1 matrix that places branch k's outputs."""
        place = getattr(self, f"_place{k}")
        assert isinstance(place, Tensor)
        return place

    def branch_net(self, k: int) -> _Net:
        net = self.nets[k]
        assert isinstance(net, _Net)
        return net

    def forward(self, x: Tensor) -> Tensor:
        yt = self.trunk(x)
        feed = yt.detach() if self.training else yt
        y = yt @ self._trunk_out
        for k in range(len(self.branches)):
            y = y + self.branch_net(k)(torch.cat([self.pick(x, k), feed], dim=1)) @ self.placement(k)
        return y

    def training_loss(self, x: Tensor, y: Tensor) -> Tensor:
        """The loss of a batch x (B, D), y (B, S): the mean squared error over B·S, every member of every
        network on its own outputs (each learns as if alone; the branches read the mean of the trunk's
        members, detached, as in ``forward``). With one member each it is ``mean((self(x) − y)²)``."""
        trunk = self.trunk.member_outputs(x)  # (K, B, T)
        sq = ((trunk - y @ self._trunk_out.T) ** 2).mean(dim=0).sum()
        feed = trunk.mean(dim=0).detach()
        for k in range(len(self.branches)):
            out = self.branch_net(k).member_outputs(torch.cat([self.pick(x, k), feed], dim=1))
            sq = sq + ((out - y @ self.placement(k).T) ** 2).mean(dim=0).sum()
        return sq / y.numel()

    def start_from_linear(self, x: Tensor, y: Tensor) -> None:
        """Every network's linear path from least squares on normalised data x (N, D), y (N, S); the
        branches' trunk input is the true trunk change."""
        yt = y @ self._trunk_out.T
        self.trunk.start_from_linear(x, yt)
        for k in range(len(self.branches)):
            xk = torch.cat([self.pick(x, k), yt], dim=1)
            self.branch_net(k).start_from_linear(xk, y @ self.placement(k).T)

    def output_columns(self) -> dict[str, list[int]]:
        """Every network's output columns of S, by name: the trunk's, then each branch's."""
        out = {TRUNK: self._trunk_out.argmax(dim=1).tolist()}
        for k, b in enumerate(self.branches):
            out[b.name] = self.placement(k).argmax(dim=1).tolist()
        return out

    def network_inputs(self, x: Tensor, y: Tensor | None = None) -> dict[str, Tensor]:
        """Every network's inputs for normalised inputs x (B, D), by name; with y (B, S) given, the
        branches read the true trunk change instead of the trunk's prediction (for linear baselines)."""
        yt = self.trunk(x) if y is None else y @ self._trunk_out.T
        out = {TRUNK: x}
        for k, b in enumerate(self.branches):
            out[b.name] = torch.cat([self.pick(x, k), yt], dim=1)
        return out


class NormalizedCore(nn.Module):
    """The exported core of an articulated emulator: unplaced input columns (B, E) -> local changes
    (B, S), ``T^σ_y N^σ T^σ_x (cols @ placement)``. A one-network core folds its normalisation into its
    first and last layers (``export.fold_normalization``); a composed one keeps it around."""

    def __init__(self, emu: StructuredEmulator) -> None:
        super().__init__()
        self.emu = emu

    def forward(self, cols: Tensor) -> Tensor:
        emu = self.emu
        return emu.denormalize_outputs(emu.core(emu.normalize_inputs(cols @ emu.input_placement)))


def make_articulated(
    emu: StructuredEmulator,
    branches: Sequence[Branch],
    control_names: Sequence[str],
    trunk_hidden: Sequence[int],
    branch_hidden: Sequence[int],
    members: int = 1,
) -> StructuredEmulator:
    """Turn a structured emulator (built without a linear path) into an articulated hierarchy: its core
    becomes an ``ArticulatedCore`` whose networks have ``members`` MLPs each; returns the same emulator."""
    if emu.skip is not None:
        raise ValueError("build the emulator without a linear path: every network has its own")
    emu.core = ArticulatedCore(  # type: ignore[assignment]
        emu, branches, control_names, trunk_hidden, branch_hidden, emu.activation, members
    )
    emu.hidden = tuple(trunk_hidden)
    return emu


def articulated_core(emu: StructuredEmulator) -> ArticulatedCore | None:
    """The emulator's core if it is an articulated hierarchy, else None."""
    return emu.core if isinstance(emu.core, ArticulatedCore) else None
