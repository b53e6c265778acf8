"""The control objective (thesis eqs. 5.2-5.3) and its library of trajectory terms, in torch.

    J = μ_u/2 Σ_k Σ_i (u_ki / r_i)²  +  μ_s/2 ‖W (s_K − s_d)‖²  +  Σ_terms weight · term

over held controls u (B, K, U) and the trajectory s (B, K+1, S) (s_0 is the initial state).
``r_i`` is the largest magnitude of control i's useful range, so each control counts in units of
its own range (a lander's 16 N·10 main jet and its ±1 attitude jets alike).

The state distance ‖W (s − s_d)‖² respects what each variable is (from the layout):

- hinge angles and a planar heading use 2(1 − cos Δ) (≈ Δ² near the goal), so a goal and the same
  goal a full turn away are equally good and the error has no jump at ±π;
- quaternions use 1 − ⟨q̂, q̂_d⟩² (≈ θ²/4 for a rotation θ, like the component difference near the
  goal), which is the same for q and −q, the same orientation;
- everything else the plain difference.

Terms are named in a job (``terms.py`` has the catalogue and the validation); every function is
batched over B so one call scores a whole population (the gradient-free baselines) and all of it
is differentiable for backpropagation through time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from neuroanimator.core.state import QUATERNION_KINDS, LayoutGroup, labels_of
from neuroanimator.goals.criteria import SuccessCheck
from neuroanimator.goals.spec import JobSpec
from neuroanimator.goals.terms import (
    ControlEffortTerm,
    ControlSmoothnessTerm,
    FinalStateTerm,
    FinalVelocityTerm,
    ForwardDistanceTerm,
    PathTargetTerm,
    StayWithinBoundsTerm,
    SuccessMarginTerm,
    Term,
)


class StateDistance:
    """``‖W (s − s_d)‖²`` for states (..., S), respecting angles and quaternions (see module doc)."""

    def __init__(self, layout: Sequence[LayoutGroup], size: int) -> None:
        plain: list[int] = []
        angles: list[int] = []
        quats: list[int] = []
        for g in layout:
            a, n = g.offset, g.size
            if g.kind in ("angle", "heading"):
                angles.extend(range(a, a + n))
            elif g.kind in QUATERNION_KINDS:
                quats.append(a)
            else:
                plain.extend(range(a, a + n))
        self.size = size
        self.plain = torch.tensor(plain, dtype=torch.long)
        self.angles = torch.tensor(angles, dtype=torch.long)
        self.quats = torch.tensor([[a + i for i in range(4)] for a in quats], dtype=torch.long).reshape(-1, 4)

    def __call__(self, states: Tensor, target: Tensor, weights: Tensor) -> Tensor:
        """states (..., S), target (S,), weights (S,) -> (...,) squared weighted distance."""
        w2 = weights.to(states.dtype) ** 2
        tgt = target.to(states.dtype)
        total = torch.zeros(states.shape[:-1], dtype=states.dtype)
        if self.plain.numel():
            d = states[..., self.plain] - tgt[self.plain]
            total = total + (w2[self.plain] * d * d).sum(-1)
        if self.angles.numel():
            d = states[..., self.angles] - tgt[self.angles]
            total = total + (w2[self.angles] * 2.0 * (1.0 - torch.cos(d))).sum(-1)
        if self.quats.numel():
            q = states[..., self.quats]  # (..., G, 4)
            qd = tgt[self.quats]  # (G, 4)
            qd = qd / qd.norm(dim=-1, keepdim=True)
            dot = (q * qd).sum(-1) / torch.sqrt((q * q).sum(-1) + 1e-12)
            wq = w2[self.quats].mean(-1)  # (G,): one weight per orientation
            total = total + (wq * (1.0 - dot * dot)).sum(-1)
        return total

    def residuals(self, states: Tensor, target: Tensor, weights: Tensor) -> Tensor:
        """states (..., S) -> (..., R) with ``(r²).sum(-1)`` equal to ``self(states, target, weights)``.

        Smooth everywhere, for Gauss-Newton: a plain variable gives ``w·Δ``, an angle ``w·2 sin(Δ/2)``
        (its square is 2(1 − cos Δ)), a quaternion the part of q̂ orthogonal to the unit target,
        ``√w̄·(q̂ − ⟨q̂, q̂_d⟩ q̂_d)`` (its squared length is 1 − ⟨q̂, q̂_d⟩²).
        """
        w = weights.to(states.dtype)
        tgt = target.to(states.dtype)
        parts: list[Tensor] = []
        if self.plain.numel():
            parts.append(w[self.plain] * (states[..., self.plain] - tgt[self.plain]))
        if self.angles.numel():
            d = states[..., self.angles] - tgt[self.angles]
            parts.append(w[self.angles].abs() * 2.0 * torch.sin(0.5 * d))
        if self.quats.numel():
            q = states[..., self.quats]
            q = q / torch.sqrt((q * q).sum(-1, keepdim=True) + 1e-12)
            qd = tgt[self.quats]
            qd = qd / qd.norm(dim=-1, keepdim=True)
            ortho = q - (q * qd).sum(-1, keepdim=True) * qd  # (..., G, 4)
            wq = torch.sqrt((w[self.quats] ** 2).mean(-1))  # (G,)
            parts.append((wq[:, None] * ortho).flatten(-2))
        return torch.cat(parts, dim=-1) if parts else states[..., :0]


class CheckPenalty:
    """Σ_checks max(0, r − margin)² on final states (B, S): the success checks (``criteria.py``) as a
    smooth penalty, zero while every check is met with room to spare.

    r is a check's measure over its bound, squared, in a form with a gradient everywhere (no square
    roots, no arccos): a distance or norm ``Σ e²/max²``; per variable of an abs check ``e²/max²``
    and of an angle check ``(1 − cos e)/(1 − cos max)``; an orientation ``(1 − ⟨q̂, q_d⟩²)/sin²(max/2)``
    (the sine of half the rotation, squared); a range check its violation of the range shrunk by
    (1 − √margin)/2 of its width on each side (of a one-sided range: the bound itself), over the
    width (or 1).
    """

    def __init__(
        self, checks: Sequence[SuccessCheck], layout: Sequence[LayoutGroup], target: list[float]
    ) -> None:
        in_order = sorted(layout, key=lambda g: g.offset)
        labels = labels_of(in_order)
        self.items: list[tuple[SuccessCheck, Tensor, Tensor]] = []
        for c in checks:
            idx = torch.tensor([labels.index(n) for n in c.variables], dtype=torch.long)
            tgt = c.target if c.target is not None else [target[int(i)] for i in idx]
            self.items.append((c, idx, _tensor(list(tgt))))

    def __call__(self, final: Tensor, margin: float) -> Tensor:
        r = self.residuals(final, margin)
        return (r * r).sum(-1)

    def residuals(self, final: Tensor, margin: float, targets: Tensor | None = None) -> Tensor:
        """final (..., S) -> (..., C): each check's ``max(0, r − margin)`` (a range check's scaled
        violation per variable), whose squares sum to the penalty; ``targets`` (..., S), where given,
        are each row's own target state (a policy's goals), else the one given when built."""
        parts: list[Tensor] = []
        for c, idx, tgt in self.items:
            x = final[..., idx]
            t = tgt.to(final.dtype) if targets is None or c.target is not None else targets[..., idx]
            if c.check == "range":
                lo, hi = c.min, c.max
                width = (hi - lo) if lo is not None and hi is not None else 1.0
                inset = 0.5 * (1.0 - margin**0.5) * width if lo is not None and hi is not None else 0.0
                v = torch.zeros_like(x)
                if lo is not None:
                    v = v + torch.clamp(lo + inset - x, min=0.0)
                if hi is not None:
                    v = v + torch.clamp(x - (hi - inset), min=0.0)
                parts.append(v / max(width, 1e-9))
                continue
            b = c.bound
            if c.check == "orientation":
                q = x / torch.sqrt((x * x).sum(-1, keepdim=True) + 1e-12)
                qd = t / t.norm(dim=-1, keepdim=True)
                dot = (q * qd).sum(-1)
                r = (1.0 - dot * dot) / max(float(np.sin(b / 2)) ** 2, 1e-12)
            elif c.check == "angle":
                r = (1.0 - torch.cos(x - t)) / max(1.0 - float(np.cos(b)), 1e-12)
            elif c.check == "abs":
                r = (x - t) ** 2 / max(b * b, 1e-12)
            elif c.check == "distance":
                r = ((x - t) ** 2).sum(-1) / max(b * b, 1e-12)
            else:  # norm
                r = (x * x).sum(-1) / max(b * b, 1e-12)
            excess = torch.clamp(r - margin, min=0.0)
            parts.append(excess if excess.dim() == final.dim() else excess[..., None])
        return torch.cat(parts, dim=-1) if parts else final[..., :0]


def _tensor(values: list[float]) -> Tensor:
    return torch.tensor(values, dtype=torch.float64)


class Objective:
    """J of a validated job spec; ``objective(states (B,K+1,S), controls (B,K,U)) -> (B,)``."""

    def __init__(
        self,
        spec: JobSpec,
        layout: Sequence[LayoutGroup],
        control_scale: Sequence[float] | np.ndarray,
    ) -> None:
        size = len(spec.target_state)
        self.distance = StateDistance(layout, size)
        self.mu_u = spec.mu_u
        self.mu_s = spec.mu_s
        self.target = _tensor(spec.target_state)
        self.weights = _tensor(spec.state_weights)
        scale = np.asarray(control_scale, dtype=np.float64)
        self.inv_scale = torch.from_numpy(1.0 / np.where(scale > 0, scale, 1.0))  # (U,)
        self.terms = list(spec.terms)
        self.checks = CheckPenalty(spec.success, layout, spec.target_state)
        # each term's vectors as tensors, once, not per call: target, weights, direction, waypoints'
        self._tensors: list[dict[str, Tensor]] = []
        for t in self.terms:
            vectors: dict[str, Tensor] = {}
            if isinstance(t, FinalStateTerm):
                vectors = {"target": _tensor(t.target), "weights": _tensor(t.weights)}
            elif isinstance(t, ForwardDistanceTerm):
                vectors = {"direction": _tensor(t.direction)}
            elif isinstance(t, PathTargetTerm):
                vectors = {"weights": _tensor(t.weights)}
                vectors |= {f"waypoint{k}": _tensor(wp.target) for k, wp in enumerate(t.waypoints)}
            self._tensors.append(vectors)

    def parts(self, states: Tensor, controls: Tensor) -> dict[str, Tensor]:
        """Each weighted part of J, (B,) each: ``effort``, ``final`` and ``<i>:<term>`` per extra term."""
        dt = states.dtype
        u = controls * self.inv_scale.to(dt)
        out: dict[str, Tensor] = {}
        out["effort"] = 0.5 * self.mu_u * (u * u).sum(dim=(-1, -2))
        out["final"] = 0.5 * self.mu_s * self.distance(states[..., -1, :], self.target, self.weights)
        for i, (t, vectors) in enumerate(zip(self.terms, self._tensors, strict=True)):
            out[f"{i}:{t.term}"] = t.weight * self._term(t, vectors, states, u)
        return out

    def __call__(self, states: Tensor, controls: Tensor) -> Tensor:
        parts = self.parts(states, controls)
        return torch.stack(list(parts.values()), dim=0).sum(dim=0)

    def residuals(self, states: Tensor, controls: Tensor) -> Tensor:
        """(B, R): J's sum-of-squares parts as residuals, ``½‖r‖²`` = J minus its linear terms.

        Every part but ``forward_distance`` (linear in the final state) is a sum of squares; the
        Gauss-Newton step (``gauss_newton.py``) takes its curvature from these and its gradient
        from the whole J.
        """
        dt = states.dtype
        u = controls * self.inv_scale.to(dt)
        flat = u.flatten(-2)
        final = states[..., -1, :]
        parts = [math.sqrt(self.mu_u) * flat]
        parts.append(math.sqrt(self.mu_s) * self.distance.residuals(final, self.target, self.weights))
        for t, vectors in zip(self.terms, self._tensors, strict=True):
            root = math.sqrt(t.weight)
            if isinstance(t, FinalStateTerm):
                parts.append(root * self.distance.residuals(final, vectors["target"], vectors["weights"]))
            elif isinstance(t, ControlEffortTerm):
                parts.append(root * flat)
            elif isinstance(t, ControlSmoothnessTerm):
                parts.append(root * (u[..., 1:, :] - u[..., :-1, :]).flatten(-2))
            elif isinstance(t, FinalVelocityTerm):
                parts.append(root * final[..., t.variables])
            elif isinstance(t, SuccessMarginTerm):
                parts.append(math.sqrt(2.0) * root * self.checks.residuals(final, t.margin))
            elif isinstance(t, StayWithinBoundsTerm):
                x = states[..., 1:, t.variable]
                if t.low is not None:
                    parts.append(root * torch.clamp(t.low - x, min=0.0))
                if t.high is not None:
                    parts.append(root * torch.clamp(x - t.high, min=0.0))
            elif isinstance(t, PathTargetTerm):
                for k, wp in enumerate(t.waypoints):
                    parts.append(
                        root
                        * self.distance.residuals(
                            states[..., wp.step, :], vectors[f"waypoint{k}"], vectors["weights"]
                        )
                    )
            # ForwardDistanceTerm: linear, no residual (its gradient is in ∇J, its curvature is zero)
        return torch.cat(parts, dim=-1)

    def _term(self, t: Term, vectors: dict[str, Tensor], states: Tensor, u: Tensor) -> Tensor:
        """One unweighted term, (B,); ``u`` is already in units of each control's range."""
        dt = states.dtype
        if isinstance(t, FinalStateTerm):
            return 0.5 * self.distance(states[..., -1, :], vectors["target"], vectors["weights"])
        if isinstance(t, ControlEffortTerm):
            return 0.5 * (u * u).sum(dim=(-1, -2))
        if isinstance(t, ControlSmoothnessTerm):
            du = u[..., 1:, :] - u[..., :-1, :]
            return 0.5 * (du * du).sum(dim=(-1, -2))
        if isinstance(t, FinalVelocityTerm):
            v = states[..., -1, t.variables]
            return 0.5 * (v * v).sum(-1)
        if isinstance(t, ForwardDistanceTerm):
            moved = states[..., -1, t.variables] - states[..., 0, t.variables]
            return -(moved * vectors["direction"].to(dt)).sum(-1)
        if isinstance(t, SuccessMarginTerm):
            return self.checks(states[..., -1, :], t.margin)
        if isinstance(t, StayWithinBoundsTerm):
            x = states[..., 1:, t.variable]  # s_0 is given: only the controlled states count
            pen = torch.zeros_like(x)
            if t.low is not None:
                pen = pen + torch.clamp(t.low - x, min=0.0) ** 2
            if t.high is not None:
                pen = pen + torch.clamp(x - t.high, min=0.0) ** 2
            return 0.5 * pen.sum(-1)
        # a PathTargetTerm, the only kind left
        total = torch.zeros(states.shape[:-2], dtype=dt)
        for k, wp in enumerate(t.waypoints):
            total = total + self.distance(
                states[..., wp.step, :], vectors[f"waypoint{k}"], vectors["weights"]
            )
        return 0.5 * total


def control_scale(limits_or_range: np.ndarray) -> np.ndarray:
    """(U,) the largest magnitude of each control's (U, 2) range: the unit its effort is counted in."""
    r = np.abs(np.asarray(limits_or_range, dtype=np.float64)).max(axis=1)
    return np.where(np.isfinite(r) & (r > 0), r, 1.0)
