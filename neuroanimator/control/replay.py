"""Replay a controller on the real physics: MuJoCo from the same initial state, same held controls.

The emulator was trained with every control held for the n physical steps of a super-step, so the
replay holds each super-step's value for its n steps too (``np.repeat``); the physical model is the
artifact's own copy of the MJCF (``registry.load_physical_model``), so a later change to the
catalog cannot make the replay disagree with what the emulator learned.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.state import QUATERNION_KINDS, LayoutGroup
from neuroanimator.goals import criteria
from neuroanimator.goals.spec import JobSpec
from neuroanimator.sim.model import PhysicalModel

FloatArray = NDArray[np.float64]


def simulate_held(
    model: PhysicalModel, initial: FloatArray, held: FloatArray, substeps: int, threads: int = 1
) -> FloatArray:
    """MuJoCo states at every super-step boundary, (B, K+1, S), from initial states (B, S) under held
    controls (B, K, U), each held for ``substeps`` physical steps."""
    s0 = np.asarray(initial, dtype=np.float64)
    u = np.asarray(held, dtype=np.float64)
    b, k = u.shape[0], u.shape[1]
    s0 = np.broadcast_to(s0, (b, s0.shape[-1])).copy()
    fine = model.simulate(s0, np.repeat(u, substeps, axis=1), threads=threads)  # (B, K·n, S)
    return np.concatenate([s0[:, None], fine[:, substeps - 1 :: substeps]], axis=1)[:, : k + 1]


def final_error(
    final: FloatArray, target: Sequence[float], weights: Sequence[float], layout: Sequence[LayoutGroup]
) -> tuple[float, dict[str, float]]:
    """The distance of a final state (S,) from the goal: ‖W e‖ with e per variable (angles wrapped,
    a quaternion's error the rotation angle to its target), and every weighted variable's |e|.

    This is the square root of the final-state term of J, in readable units.
    """
    s = np.asarray(final, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    total = 0.0
    per: dict[str, float] = {}
    for g in layout:
        a, n = g.offset, g.size
        labels = [f"{g.name}.{lab}" for lab in g.labels] or (
            [g.name] if n == 1 else [f"{g.name}[{i}]" for i in range(n)]
        )
        if g.kind in QUATERNION_KINDS:
            q = s[a : a + 4] / np.linalg.norm(s[a : a + 4])
            qd = tgt[a : a + 4] / np.linalg.norm(tgt[a : a + 4])
            angle = float(2.0 * np.arccos(min(1.0, abs(float(q @ qd)))))
            wq = float(np.sqrt(np.mean(w[a : a + 4] ** 2)))
            total += (wq * angle) ** 2
            if wq > 0:
                per[f"{g.name}.angle"] = angle
            continue
        e = s[a : a + n] - tgt[a : a + n]
        if g.kind in ("angle", "heading"):
            e = (e + np.pi) % (2 * np.pi) - np.pi
        total += float(np.sum((w[a : a + n] * e) ** 2))
        for i in range(n):
            if w[a + i] > 0:
                per[labels[i]] = float(abs(e[i]))
    return float(np.sqrt(total)), per


@dataclass
class Replay:
    """A controller's outcome on one simulator: states (K+1, S), the final error, success."""

    states: FloatArray
    final_error: float
    final_errors: dict[str, float]
    success: bool
    checks: list[criteria.CheckResult]

    @classmethod
    def of(
        cls, states: FloatArray, spec: JobSpec, layout: Sequence[LayoutGroup], labels: Sequence[str]
    ) -> Replay:
        err, per = final_error(states[-1], spec.target_state, spec.state_weights, layout)
        ok, checks = criteria.evaluate(spec.success, states[-1], np.asarray(spec.target_state), labels)
        return cls(states, err, per, ok, checks)
