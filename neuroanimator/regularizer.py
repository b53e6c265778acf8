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
    springs on the points' columns; every other column passes through unchanged."""

    pos_cols: Tensor  # (3P, S) places the points' positions (P points × xyz) in the state
    vel_cols: Tensor  # (3P, S) the same for their velocities
    incidence: Tensor  # (m, P)
    rest: Tensor  # (m,) rest lengths
    muscle: Tensor  # (U, m) change of each spring's rest length per unit of each control
    inv_mass: Tensor  # (P, 1)

    def __init__(self, layout: StateLayout, spec: SpringRegularizer, num_controls: int) -> None:
        super().__init__()
        self.spec = spec
        self.steps = spec.steps
        p = len(spec.points)
        pos = torch.zeros(3 * p, layout.size)
        vel = torch.zeros(3 * p, layout.size)
        for k, (pos_group, vel_group) in enumerate(spec.points):
            for axis, (g, target) in (
                (a, gt) for a in range(3) for gt in ((pos_group, pos), (vel_group, vel))
            ):
                sl = layout.slice_of(g)
                if sl.stop - sl.start != 3:
                    raise ValueError(f"regulariser point {g!r}: a group of 3 world values expected")
                target[3 * k + axis, sl.start + axis] = 1.0
        muscle = torch.zeros(max(num_controls, 1), len(spec.springs))
        for spring, control, contracted in spec.muscles:
            if control >= num_controls:
                raise ValueError(f"regulariser muscle on control {control}: the model has {num_controls}")
            muscle[control, spring] = contracted - spec.springs[spring][2]
        self.register_buffer("pos_cols", pos, persistent=False)
        self.register_buffer("vel_cols", vel, persistent=False)
        self.register_buffer(
            "incidence", torch.as_tensor(_incidence(spec), dtype=torch.float32), persistent=False
        )
        self.register_buffer("rest", torch.tensor([s[2] for s in spec.springs]), persistent=False)
        self.register_buffer("muscle", muscle, persistent=False)
        self.register_buffer("inv_mass", 1.0 / torch.tensor(spec.masses)[:, None], persistent=False)
        self.has_muscles = bool(spec.muscles) and num_controls > 0

    def forward(self, state: Tensor, controls: Tensor | None = None) -> Tensor:
        if self.steps == 0:
            return state
        b = state.shape[0]
        x0 = (state @ self.pos_cols.T).reshape(b, -1, 3)  # (B, P, 3)
        v0 = (state @ self.vel_cols.T).reshape(b, -1, 3)
        rest = self.rest + controls @ self.muscle if self.has_muscles and controls is not None else self.rest
        dt, k, c = self.spec.dt, self.spec.stiffness, self.spec.damping
        x, v = x0, v0
        for _ in range(self.steps):
            r = self.incidence @ x  # (B, m, 3) spring vectors
            length = torch.sqrt((r * r).sum(-1) + 1e-12)
            unit = r / length[..., None]
            rate = ((self.incidence @ v) * unit).sum(-1)  # (B, m) lengthening speed
            tension = k * (length - rest) + c * rate  # > 0 pulls the ends together
            force = -(self.incidence.T @ (tension[..., None] * unit))  # (B, P, 3): towards b at a, back at b
            v = v + dt * force * self.inv_mass
            x = x + dt * v
        return state + (x - x0).reshape(b, -1) @ self.pos_cols + (v - v0).reshape(b, -1) @ self.vel_cols

    def deformation_energy(self, state: Tensor) -> Tensor:
        """(B,S) -> (B,) E_d of the springs at their rest lengths."""
        x = (state @ self.pos_cols.T).reshape(state.shape[0], -1, 3)
        r = self.incidence @ x
        strain = (torch.sqrt((r * r).sum(-1)) - self.rest) / self.rest
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
