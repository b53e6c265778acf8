"""The spring regulariser of thesis 6.1.3 as a torch module, part of an emulator's step.

A mass-spring model's emulator predicts every node freely, so small errors add up to deformations the
springs would never allow. ``SpringRegularization`` follows each emulated super-step with a few
explicit Euler steps of the springs (``model_spec.SpringRegularizer``), which pull the shape back. It is
matrix products only (an incidence matrix of the springs, placement matrices of the points' columns),
so the ONNX export of a step includes it as it is, and BPTT differentiates through it.
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from neuroanimator.model_spec import SpringRegularizer
from neuroanimator.state import StateLayout


def _incidence(spec: SpringRegularizer) -> NDArray[np.float64]:
    """(m, P): row i is −1 at spring i's point a and +1 at its point b, so D @ x is each spring's vector."""
    d = np.zeros((len(spec.springs), len(spec.points)))
    for i, (a, b, _) in enumerate(spec.springs):
        d[i, a], d[i, b] = -1.0, 1.0
    return d


def deformation_energy(spec: SpringRegularizer, positions: NDArray[np.floating]) -> NDArray[np.float64]:
    """E_d = ½ Σ ((l − l_r)/l_r)² over the springs at their rest lengths (muscles relaxed), thesis 6.1.3.
    positions (..., P, 3) -> (...,)."""
    p = np.asarray(positions, dtype=np.float64)
    r = np.einsum("mp,...pc->...mc", _incidence(spec), p)
    rest = np.asarray([s[2] for s in spec.springs])
    strain = (np.linalg.norm(r, axis=-1) - rest) / rest
    return np.asarray(0.5 * np.sum(strain**2, axis=-1))


class SpringRegularization(nn.Module):
    """``forward(state (B,S), controls (B,U) or None) -> (B,S)``: ``spec.steps`` Euler steps of the
    springs on the points' columns; every other column passes through unchanged.

    The steps run feature-major (``features``: (S, B) -> (S, B)), with the points' coordinates as one
    (P, 3·B) matrix: each spring sum is then one product with the incidence matrix for the whole
    batch, and an exported step keeps a handful of nodes per Euler step whatever B.
    """

    pos_rows: Tensor  # (3P,) the state index of each point's x, y, z
    vel_rows: Tensor  # (3P,) the same for their velocities
    place: Tensor  # (S,) index into [state, new positions, new velocities] of each state value
    incidence: Tensor  # (m, P)
    rest: Tensor  # (m, 1, 1) rest lengths
    muscle: Tensor  # (m, U) change of each spring's rest length per unit of each control
    inv_mass: Tensor  # (P, 1)

    def __init__(self, layout: StateLayout, spec: SpringRegularizer, num_controls: int) -> None:
        super().__init__()
        self.spec = spec
        self.steps = spec.steps
        p = len(spec.points)
        pos_rows: list[int] = []
        vel_rows: list[int] = []
        for pos_group, vel_group in spec.points:
            for g, rows in ((pos_group, pos_rows), (vel_group, vel_rows)):
                sl = layout.slice_of(g)
                if sl.stop - sl.start != 3:
                    raise ValueError(f"regulariser point {g!r}: a group of 3 world values expected")
                rows.extend(range(sl.start, sl.stop))
        place = torch.arange(layout.size)
        place[pos_rows] = layout.size + torch.arange(3 * p)
        place[vel_rows] = layout.size + 3 * p + torch.arange(3 * p)
        muscle = torch.zeros(len(spec.springs), max(num_controls, 1))
        for spring, control, contracted in spec.muscles:
            if control >= num_controls:
                raise ValueError(f"regulariser muscle on control {control}: the model has {num_controls}")
            muscle[spring, control] = contracted - spec.springs[spring][2]
        self.register_buffer("pos_rows", torch.tensor(pos_rows), persistent=False)
        self.register_buffer("vel_rows", torch.tensor(vel_rows), persistent=False)
        self.register_buffer("place", place, persistent=False)
        self.register_buffer(
            "incidence", torch.as_tensor(_incidence(spec), dtype=torch.float32), persistent=False
        )
        self.register_buffer(
            "rest", torch.tensor([s[2] for s in spec.springs])[:, None, None], persistent=False
        )
        self.register_buffer("muscle", muscle, persistent=False)
        self.register_buffer("inv_mass", 1.0 / torch.tensor(spec.masses)[:, None], persistent=False)
        self.has_muscles = bool(spec.muscles) and num_controls > 0

    def forward(self, state: Tensor, controls: Tensor | None = None) -> Tensor:
        if self.steps == 0:
            return state
        return self.features(state.T, None if controls is None else controls.T).T

    def features(self, state: Tensor, controls: Tensor | None = None) -> Tensor:
        """The steps on feature-major values: state (S, B), controls (U, B) -> (S, B)."""
        if self.steps == 0:
            return state
        p = self.inv_mass.shape[0]
        x = state[self.pos_rows].reshape(p, -1)  # (P, 3·B): point i's x, y, z for every row
        v = state[self.vel_rows].reshape(p, -1)
        dt, k, c = self.spec.dt, self.spec.stiffness, self.spec.damping
        pull = k * self.rest  # (m, 1, 1), or (m, 1, B) with the muscles' activations
        if self.has_muscles and controls is not None:
            pull = pull + k * (self.muscle @ controls).unsqueeze(1)
        kick = -dt * self.inv_mass * self.incidence.T  # (P, m): tensions -> change of velocity
        m = self.incidence.shape[0]
        for _ in range(self.steps):
            r = (self.incidence @ x).reshape(m, 3, -1)  # (m, 3, B) spring vectors
            # sums over the 3 axes written out: a reduction over a middle axis is slow at B = 1
            rx, ry, rz = r.split(1, dim=1)
            length = torch.sqrt(rx * rx + ry * ry + rz * rz + 1e-12)
            unit = r / length
            dx, dy, dz = ((self.incidence @ v).reshape(m, 3, -1) * unit).split(1, dim=1)
            rate = dx + dy + dz  # (m, 1, B) lengthening speed
            tension = k * length + c * rate - pull  # > 0 pulls the ends together
            v = v + kick @ (tension * unit).reshape(m, -1)
            x = x + dt * v
        return torch.cat([state, x.reshape(3 * p, -1), v.reshape(3 * p, -1)])[self.place]

    def deformation_energy(self, state: Tensor) -> Tensor:
        """(B,S) -> (B,) E_d of the springs at their rest lengths."""
        x = state[:, self.pos_rows].reshape(state.shape[0], -1, 3)
        r = self.incidence @ x
        strain = (torch.sqrt((r * r).sum(-1)) - self.rest[:, 0, 0]) / self.rest[:, 0, 0]
        return 0.5 * (strain * strain).sum(-1)


def regularization(
    layout: StateLayout, spec: SpringRegularizer | None, num_controls: int, steps: int | None = None
) -> SpringRegularization | None:
    """The module for ``spec`` with ``steps`` Euler steps (None: the spec's), or None when off."""
    if spec is None:
        return None
    if steps is not None:
        spec = spec.model_copy(update={"steps": steps})
    return SpringRegularization(layout, spec, num_controls) if spec.steps > 0 else None
