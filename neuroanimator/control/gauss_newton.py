"""Levenberg-Marquardt through the emulator: when gradient descent stalls short of the goal.

The objective is almost entirely a sum of squares, J = ½‖r(z)‖² (+ linear terms, see
``Objective.residuals``), over the control points z. Gradient descent with momentum sees only
∇J = Jᵣᵀ r, and on these badly conditioned problems it settles on compromises: a lander that
arrives on the pad still tilted 11-16°, because the late attitude pulses that would right it move
J a hundred times less than the early ones that steer it. The Gauss-Newton model Jᵣᵀ Jᵣ knows how
each control point moves each residual, so its step rights the lander and keeps the position:

    δ(λ) = −(Jᵣᵀ Jᵣ + λ (diag(Jᵣᵀ Jᵣ) + ε))⁻¹ ∇J,     z ← Π(z + δ(λ))

(Marquardt's scaling; Π the projection onto the control limits). The residual Jacobian Jᵣ (R, V)
costs one batched rollout and one backward pass: R + 1 copies of the controller go through the
emulator as a batch and the backward pass of Σᵢ rᵢ(copy i) + J(copy R) gives every row at once
(``ControlProblem.residual_jacobian``; counted as R + 1 emulator rollouts, 174 for the lander's
40 steps). A whole range
of λ is then scored in one batched emulator call, the way the line search scores its (η, α)
candidates, and the best step is taken: no λ schedule to tune.

Measured (``bench/control_goals.py --seed 0 --goals 20``): the six lander goals that the descent
left tilted 0.185-0.273 rad (the check is 0.175) were all reached in 3-4 updates, about 0.6 s each
job, ending 0.006-0.16 rad from upright; on MuJoCo, with the controller found on the emulator alone,
the lander goes from 14 to 20 of 20 and the pendulum (after refinement) from 16 to 18. It runs only
after a descent that misses, so jobs the descent solves (the built-in tasks) cost what they did.

Shapes: V = M·U control points, R residuals.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
# z (M, U) -> J, ∇J (M, U), r (R,), Jᵣ (R, V), what is_success needs
ResidualJacobian = Callable[[FloatArray], tuple[float, FloatArray, FloatArray, FloatArray, Any]]
Evaluate = Callable[[FloatArray], FloatArray]  # (B, M, U) -> (B,)

DAMPINGS = 10.0 ** np.arange(-6.0, 3.5, 0.5)  # λ tried per iteration, relative to mean(diag Jᵣᵀ Jᵣ)
RIDGE = 1e-9  # ε: keeps the system solvable where a control point moves no residual


@dataclass
class LMOutcome:
    """Where Levenberg-Marquardt ended: the best controller (the lowest J that meets the criterion,
    else the lowest J), its J, whether it meets the criterion, and what it cost."""

    z: FloatArray
    objective: float
    success: bool
    extra: Any
    iterations: int
    rollouts: int
    stop: str  # "success" | "stalled" | "max_iterations" | "cancelled"
    iterations_to_success: int | None = None
    history: list[float] = field(default_factory=list)


def steps(jr: FloatArray, grad: FloatArray, dampings: FloatArray = DAMPINGS) -> FloatArray:
    """(L, V): the damped Gauss-Newton step for each λ, from Jᵣ (R, V) and ∇J (V,)."""
    a = jr.T @ jr
    d = np.diag(a).copy()
    scale = float(d.mean()) if d.size and d.mean() > 0 else 1.0
    out = []
    for lam in dampings:
        m = a + lam * np.diag(d + RIDGE * scale)
        try:
            out.append(-np.linalg.solve(m, grad))
        except np.linalg.LinAlgError:
            out.append(-np.linalg.lstsq(m, grad, rcond=None)[0])
    return np.stack(out)


def levenberg_marquardt(
    residual_jacobian: ResidualJacobian,
    evaluate: Evaluate,
    z0: FloatArray,
    *,
    max_iterations: int,
    project: Callable[[FloatArray], FloatArray],
    is_success: Callable[[Any], bool],
    polish_iterations: int = 0,
    on_iteration: Callable[[int, float, float, bool], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> LMOutcome:
    """Minimise J from ``z0`` (M, U) by Levenberg-Marquardt (module docstring); stops
    ``polish_iterations`` updates after the criterion is first met, when no λ lowers J, or after
    ``max_iterations`` updates. ``on_iteration(l, J, best J, success)`` follows every update."""
    z = project(np.asarray(z0, dtype=np.float64))
    shape = z.shape
    j, g, _, jr, extra = residual_jacobian(z)
    rollouts = jr.shape[0] + 1  # the Jacobian's batch: one copy per residual and one for J
    ok = is_success(extra)
    best: tuple[bool, float, FloatArray, Any] = (ok, j, z, extra)
    history = [j]
    stop = "max_iterations"
    met_at: int | None = 0 if ok else None
    done = 0
    while done < max_iterations:
        if met_at is not None and done >= met_at + polish_iterations:
            stop = "success"
            break
        if should_stop is not None and should_stop():
            stop = "cancelled"
            break
        cands = np.stack([project(z + s.reshape(shape)) for s in steps(jr, g.ravel())])
        values = np.asarray(evaluate(cands), dtype=np.float64)
        rollouts += len(cands)
        values = np.where(np.isfinite(values), values, np.inf)
        c = int(np.argmin(values))
        if not values[c] < j:
            stop = "stalled"
            break
        z = cands[c]
        done += 1
        j, g, _, jr, extra = residual_jacobian(z)
        rollouts += jr.shape[0] + 1
        ok = is_success(extra)
        if ok and met_at is None:
            met_at = done
        history.append(j)
        if (ok, -j) > (best[0], -best[1]):
            best = (ok, j, z, extra)
        if on_iteration is not None:
            on_iteration(done, j, best[1], ok)
    if stop == "max_iterations" and met_at is not None:
        stop = "success"
    ok, j, z, extra = best
    return LMOutcome(z, j, ok, extra, done, rollouts, stop, met_at, history)
