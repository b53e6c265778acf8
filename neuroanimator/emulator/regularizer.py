"""The spring regulariser of thesis 6.1.3 as a torch module, part of an emulator's step.

A mass-spring model's emulator predicts every node freely, so small errors add up to deformations the
springs would never allow. ``SpringRegularization`` follows each emulated super-step with a few
explicit Euler steps of the springs (``model_spec.SpringRegularizer``), which pull the shape back.
Hinged parts that the body's springs hold in line with two of its points (the dolphin's drag plates)
are pulled towards that line too (``HingeAlignment``): a part network that reads such a hinge's world
angle in a frame that hides the body's own pitch cannot tell where the line would hold it, and
without the pull the angle drifts. It is matrix products and elementwise operations only, so the
ONNX export of a step includes it as it is, and BPTT differentiates through it.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from neuroanimator.core.model_spec import SpringRegularizer
from neuroanimator.core.state import StateLayout


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
    springs on the points' columns, then each of ``spec.hinges`` pulled towards its line; every other
    column passes through unchanged.

    The steps run feature-major (``features``: (S, B) -> (S, B)) on one tensor W (3, 2P, B): for each
    axis, the points' coordinates, then their velocities. A spring's tension along its vector r is
    k·r + g·r with g = (c·l̇ − k·l_r)/l, so the k·r part of a symplectic Euler step is linear in W and
    folds into one constant matrix with the g·r part's. What is left per step is one product for every
    spring's r and relative velocity, a few elementwise operations on (1, m, B) and one product back:
    an exported step has 14 nodes whatever B, and no elementwise operation broadcasts over an inner
    axis (which ONNX Runtime runs slowly at large B). (Folding the next step's spring vectors into
    that last product saves a node a step but multiplies its arithmetic by 2.3: slower at B = 1,024.)
    """

    rows: Tensor  # (6P,) the state index of W's rows: per axis, the points' positions, then velocities
    pos_rows: Tensor  # (3P,) the state index of each point's x, y, z
    place: Tensor  # (S,) index into [state, W, hinge angles, hinge rates] of each state value
    spans: Tensor  # (2m, 2P): each spring's vector from the positions, c × its relative velocity
    step: Tensor  # (2P, 2P + m): one step, W' = step @ [W; g·r] (the springs' k·r folded in)
    rest: Tensor  # (1, m, 1) k × rest lengths
    muscle: Tensor  # (m, U) change of k × each spring's rest length per unit of each control
    hinge_lines: Tensor  # (4H, 6P): per hinge, the line's sine and cosine terms, and their rates
    hinge_rows: Tensor  # (2H,) the state index of each hinge's angle, then of each hinge's rate

    def __init__(self, layout: StateLayout, spec: SpringRegularizer, num_controls: int) -> None:
        super().__init__()
        self.spec = spec
        self.steps = spec.steps
        p, m = len(spec.points), len(spec.springs)
        pos_rows: list[int] = []
        vel_rows: list[int] = []
        for pos_group, vel_group in spec.points:
            for g, rows in ((pos_group, pos_rows), (vel_group, vel_rows)):
                sl = layout.slice_of(g)
                if sl.stop - sl.start != 3:
                    raise ValueError(f"regulariser point {g!r}: a group of 3 world values expected")
                rows.extend(range(sl.start, sl.stop))
        # W's rows: axis a's positions (a·2P + i), then its velocities (a·2P + P + i)
        rows = [r[3 * i + a] for a in range(3) for r in (pos_rows, vel_rows) for i in range(p)]
        hinge_rows = self._hinge_rows(layout, spec)
        place = torch.arange(layout.size)
        place[rows] = layout.size + torch.arange(6 * p)
        place[hinge_rows] = layout.size + 6 * p + torch.arange(len(hinge_rows))
        k, c, dt = spec.stiffness, spec.damping, spec.dt
        incidence = _incidence(spec)  # (m, P)
        spans = np.zeros((2 * m, 2 * p))
        spans[:m, :p], spans[m:, p:] = incidence, c * incidence
        # v' = v + δt·a, a = −M⁻¹Dᵀ(k·r + g·r), r = D·x; x' = x + δt·v'
        accel = -dt / np.asarray(spec.masses)[:, None] * incidence.T  # (P, m): g·r -> change of v
        spring = k * accel @ incidence  # (P, P): k·x -> change of v
        eye = np.eye(p)
        update = np.block([[eye + dt * spring, dt * eye], [spring, eye]])
        kick = np.concatenate([dt * accel, accel])
        muscle = torch.zeros(m, max(num_controls, 1))
        for spring_index, control, contracted in spec.muscles:
            if control >= num_controls:
                raise ValueError(f"regulariser muscle on control {control}: the model has {num_controls}")
            muscle[spring_index, control] = k * (contracted - spec.springs[spring_index][2])
        f32 = torch.float32
        self.register_buffer("rows", torch.tensor(rows), persistent=False)
        self.register_buffer("pos_rows", torch.tensor(pos_rows), persistent=False)
        self.register_buffer("place", place, persistent=False)
        self.register_buffer("spans", torch.as_tensor(spans, dtype=f32), persistent=False)
        step = np.concatenate([update, kick], axis=1)
        self.register_buffer("step", torch.as_tensor(step, dtype=f32), persistent=False)
        rest = k * torch.tensor([s[2] for s in spec.springs])[None, :, None]
        self.register_buffer("rest", rest, persistent=False)
        self.register_buffer("muscle", muscle, persistent=False)
        self.register_buffer("hinge_lines", torch.as_tensor(_hinge_lines(spec), dtype=f32), persistent=False)
        self.register_buffer("hinge_rows", torch.tensor(hinge_rows, dtype=torch.long), persistent=False)
        self.has_muscles = bool(spec.muscles) and num_controls > 0
        self.pulls_hinges = bool(spec.hinges) and spec.hinge_pull > 0

    @staticmethod
    def _hinge_rows(layout: StateLayout, spec: SpringRegularizer) -> list[int]:
        angles: list[int] = []
        rates: list[int] = []
        for hinge in spec.hinges if spec.hinge_pull > 0 else []:
            for g, out in ((hinge.angle, angles), (hinge.rate, rates)):
                sl = layout.slice_of(g)
                if sl.stop - sl.start != 1:
                    raise ValueError(f"regulariser hinge {g!r}: a group of one value expected")
                out.append(sl.start)
        return angles + rates

    def forward(self, state: Tensor, controls: Tensor | None = None) -> Tensor:
        if self.steps == 0:
            return state
        return self.features(state.T, None if controls is None else controls.T).T

    def features(self, state: Tensor, controls: Tensor | None = None) -> Tensor:
        """The steps on feature-major values: state (S, B), controls (U, B) -> (S, B). No steps: off,
        hinges included."""
        if self.steps == 0:
            return state
        p2, m = self.step.shape[0], self.rest.shape[1]
        w = state[self.rows].reshape(3, p2, -1)  # (3, 2P, B)
        pull = self.rest  # (1, m, 1), or (1, m, B) with the muscles' activations: k·l_r
        if self.has_muscles and controls is not None:
            pull = pull + (self.muscle @ controls).unsqueeze(0)
        for _ in range(self.steps):
            r, rate = (self.spans @ w).split(m, dim=1)  # (3, m, B) each: r and c·ṙ
            inverse = ((r * r).sum(0, keepdim=True) + 1e-12).pow(-0.5)  # (1, m, B): 1/l
            g = ((r * rate).sum(0, keepdim=True) * inverse - pull) * inverse  # (c·l̇ − k·l_r)/l
            w = self.step @ torch.cat([w, g * r], dim=1)  # (2P, 2P + m) @ (3, 2P + m, B)
        flat = w.reshape(3 * p2, -1)
        if not self.pulls_hinges:
            return torch.cat([state, flat])[self.place]
        return torch.cat([state, flat, self._hinges(state, flat)])[self.place]

    def _hinges(self, state: Tensor, flat: Tensor) -> Tensor:
        """(S, B) state, (6P, B) W -> (2H, B): each hinge's angle and rate moved ``hinge_pull`` of the
        way to its line's. The line's turn θ about the axis since rest has sin θ ∝ s = (n × q₀)·q and
        cos θ ∝ c = q₀⊥·q (q its current vector); θ = 2·atan(s / (ρ + c)), ρ = √(s² + c²) (ONNX has
        no atan2), taken the nearest way round from the state's angle, so an angle past ±π (a body
        that loops) stays continuous; θ̇ = (c·ṡ − s·ċ)/ρ²."""
        h = self.hinge_rows.shape[0] // 2  # split by sizes, not chunk(): a chunk exports as a dozen nodes
        s, c, ds, dc = (self.hinge_lines @ flat).split(h)  # (H, B) each
        now = state[self.hinge_rows]  # (2H, B): the angles, then the rates
        angle, rate = now.split(h)
        rho2 = s * s + c * c + 1e-12
        turn = 2.0 * torch.atan(s / (rho2.sqrt() + c)) - angle
        turn = turn - (2.0 * math.pi) * torch.round(turn * (0.5 / math.pi))
        return now + self.spec.hinge_pull * torch.cat([turn, (c * ds - s * dc) / rho2 - rate])

    def deformation_energy(self, state: Tensor) -> Tensor:
        """(B,S) -> (B,) E_d of the springs at their rest lengths."""
        x = state[:, self.pos_rows].reshape(state.shape[0], -1, 3)
        r = self.spans[: self.rest.shape[1], : x.shape[1]].to(x.dtype) @ x  # the incidence rows
        rest = self.rest[0, :, 0].to(x.dtype) / self.spec.stiffness
        strain = (torch.sqrt((r * r).sum(-1)) - rest) / rest
        return 0.5 * (strain * strain).sum(-1)


def _hinge_lines(spec: SpringRegularizer) -> NDArray[np.float64]:
    """(4H, 6P): the rows of W's flattened form that give each hinge's s, c, ṡ, ċ (``_hinges``)."""
    p = len(spec.points)
    hinges = spec.hinges if spec.hinge_pull > 0 else []
    out = np.zeros((4, len(hinges), 6 * p))
    for h, hinge in enumerate(hinges):
        axis, rest = np.asarray(hinge.axis), np.asarray(hinge.rest)
        sine, cosine = np.cross(axis, rest), rest - (rest @ axis) * axis
        for a in range(3):
            for row, weights, offset in ((0, sine, 0), (1, cosine, 0), (2, sine, p), (3, cosine, p)):
                out[row, h, a * 2 * p + offset + hinge.target] += weights[a]
                out[row, h, a * 2 * p + offset + hinge.anchor] -= weights[a]
    return out.reshape(4 * len(hinges), 6 * p)


def regularization(
    layout: StateLayout, spec: SpringRegularizer | None, num_controls: int, steps: int | None = None
) -> SpringRegularization | None:
    """The module for ``spec`` with ``steps`` Euler steps (None: the spec's), or None when off."""
    if spec is None:
        return None
    if steps is not None:
        spec = spec.model_copy(update={"steps": steps})
    return SpringRegularization(layout, spec, num_controls) if spec.steps > 0 else None
