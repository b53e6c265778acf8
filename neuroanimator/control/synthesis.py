"""Controller synthesis by gradient descent with momentum through the emulator (thesis 5.3, 6.2).

The update is the thesis' eqs. 5.5-5.6 on the normalised control points z (see ``bptt.py``):

    δz ← −η ĝ + α δz,    z ← Π(z + δz)

with ĝ = ∇J / max|∇J| (the gradient scaled so its largest component is 1, which makes η the
largest change of any control point in one step, in units of its half-range, whatever the scale
of J) and Π the projection onto the control limits.

``line_search`` (the default) picks η and α afresh at every iteration: the candidates
η·2^-j (j = 0..11) × α·{0, ½, 1} ∪ {α + (1−α)/2, α + 3(1−α)/4} are all scored in one batched
emulator call (about the cost of one rollout for these small networks) and the best is taken.
The objectives here are badly conditioned (a lander's early attitude pulse moves its final
position a hundred times more than a late one), and a fixed (η, α) either oscillates or crawls;
choosing both coefficients per step is heavy-ball momentum with the step adapted, which on a
quadratic is what conjugate gradients does. With ``line_search`` off the update is exactly the
thesis' fixed-coefficient rule (used to reproduce Figs. 6.13-6.15).

The loop is generic over the objective (``value_and_grad``/``evaluate`` callables), so a test can
hand it one that turns NaN.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from neuroanimator.goals.spec import OptimizerSettings

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
STEP_HALVINGS = 12  # η·2^0 .. η·2^-11: from the full step down to ~1/2000 of it


@dataclass(frozen=True)
class Settings:
    """The optimiser's knobs; ``learning_rate`` is η, ``momentum`` is α."""

    learning_rate: float
    momentum: float
    max_iterations: int
    tolerance: float = 1e-6
    stop_on_success: bool = True
    line_search: bool = True
    polish_iterations: int = 3
    # False: the thesis' raw gradient (eqs. 5.5, 6.2-6.3), whose η then depends on the scale of J
    normalize_gradient: bool = True

    @classmethod
    def from_spec(cls, opt: OptimizerSettings) -> Settings:
        """The optimiser of a job's validated settings (its ``physics_rounds`` are the runner's)."""
        return cls(
            learning_rate=opt.learning_rate,
            momentum=opt.momentum,
            max_iterations=opt.max_iterations,
            tolerance=opt.tolerance,
            stop_on_success=opt.stop_on_success,
            line_search=opt.line_search,
            polish_iterations=opt.polish_iterations,
        )

    def candidates(self, first: bool) -> list[tuple[float, float]]:
        """(η, α) pairs tried in one line-search step; α is 0 on the first step (no δ yet)."""
        a = self.momentum
        alphas = (
            sorted({0.0, 0.5 * a, a, a + 0.5 * (1 - a), a + 0.75 * (1 - a)}) if not first and a > 0 else [0.0]
        )
        etas = [self.learning_rate * 2.0**-j for j in range(STEP_HALVINGS)]
        return [(e, al) for e in etas for al in alphas]


@dataclass
class Outcome:
    """What an optimisation run ended with. ``z`` is the controller returned: the first one that met
    the criterion when the run stopped on success, else the best finite one."""

    stop: str  # "success" | "converged" | "stalled" | "max_iterations" | "diverged" | "cancelled"
    reason: str | None
    z: FloatArray
    objective: float
    success: bool
    extra: Any  # what value_and_grad returned beside J and ∇J for z (the trajectory)
    iterations: int
    iterations_to_success: int | None
    history: list[float] = field(default_factory=list)
    rollouts: int = 0  # emulator trajectories evaluated, gradients and line-search candidates


ValueAndGrad = Callable[[FloatArray], tuple[float, FloatArray, Any]]
Evaluate = Callable[[FloatArray], FloatArray]  # (B, M, U) -> (B,)


def _finite(x: float | FloatArray) -> bool:
    return bool(np.all(np.isfinite(x)))


def _not_finite(j: float, g: FloatArray) -> str | None:
    """Which of J and ∇J is not finite ("objective" first), or None when both are."""
    if not _finite(j):
        return "objective"
    return None if _finite(g) else "gradient"


@dataclass
class _Progress:
    """A run so far: the best controllers, the first update that met the criterion, J's history
    and the emulator rollouts spent."""

    best: Outcome  # lowest J so far
    best_ok: Outcome | None  # lowest J among controllers that meet the criterion
    to_success: int | None  # updates made when the criterion was first met
    history: list[float]
    rollouts: int

    @classmethod
    def start(cls, z: FloatArray, j: float, ok: bool, extra: Any) -> _Progress:
        """The run at the initial controller z (M, U), one rollout spent on it."""
        first = Outcome("", None, z, j, ok, extra, 0, None)
        return cls(first, first if ok else None, 0 if ok else None, [j], 1)

    def record(self, z: FloatArray, j: float, ok: bool, extra: Any, done: int) -> None:
        """The controller z (M, U) after ``done`` updates, with its J and verdict."""
        self.history.append(j)
        if ok and self.to_success is None:
            self.to_success = done
        current = Outcome("", None, z, j, ok, extra, done, None)
        if j < self.best.objective:
            self.best = current
        if ok and (self.best_ok is None or j < self.best_ok.objective):
            self.best_ok = current

    def polished(self, done: int, settings: Settings) -> bool:
        """Whether the run met the criterion and has made its polishing updates since."""
        return (
            self.to_success is not None
            and settings.stop_on_success
            and done >= self.to_success + settings.polish_iterations
        )

    def outcome(self, stop: str, reason: str | None, done: int, settings: Settings) -> Outcome:
        """The controller returned: the best one that meets the criterion, else the lowest J."""
        if stop == "max_iterations" and self.to_success is not None and settings.stop_on_success:
            stop = "success"  # the cap fell inside the polishing iterations
        chosen = self.best_ok if self.best_ok is not None else self.best
        chosen.stop, chosen.reason = stop, reason
        chosen.iterations = done
        chosen.iterations_to_success = self.to_success
        chosen.history = self.history
        chosen.rollouts = self.rollouts
        return chosen


def _halt(
    progress: _Progress,
    done: int,
    g: FloatArray,
    settings: Settings,
    should_stop: Callable[[], bool] | None,
) -> tuple[str, str | None] | None:
    """Why the run ends before its next update (the stop and the reason), or None to go on."""
    if progress.polished(done, settings):
        return "success", None
    if done >= settings.max_iterations:
        return "max_iterations", None
    if should_stop is not None and should_stop():
        return "cancelled", f"cancelled after {done} iterations"
    if float(np.abs(g).max()) == 0.0:
        return "converged", "the gradient is zero"
    return None


def _line_search(
    z: FloatArray,
    g_hat: FloatArray,
    delta: FloatArray,
    j: float,
    first: bool,
    settings: Settings,
    project: Callable[[FloatArray], FloatArray],
    evaluate: Evaluate,
) -> tuple[FloatArray | None, int]:
    """The best of the candidates Π(z − η ĝ + α δ) over ``settings.candidates`` (each (M, U)),
    scored in one batch, or None when none lowers J below ``j``; and how many were scored."""
    cands = settings.candidates(first=first)
    zs = np.stack([project(z - eta * g_hat + alpha * delta) for eta, alpha in cands])
    values = np.asarray(evaluate(zs), dtype=np.float64)
    values = np.where(np.isfinite(values), values, np.inf)  # a candidate that diverged is never taken
    b = int(np.argmin(values))
    return (zs[b] if values[b] < j else None), len(cands)


def _next_point(
    z: FloatArray,
    g: FloatArray,
    delta: FloatArray,
    j: float,
    first: bool,
    settings: Settings,
    project: Callable[[FloatArray], FloatArray],
    evaluate: Evaluate | None,
) -> tuple[FloatArray | None, int]:
    """The next controller (M, U) from z, its gradient g and the last step δ (both (M, U)): the
    line search's choice, or the fixed-coefficient update; None when no candidate lowers J. Also
    how many rollouts choosing it took."""
    scale = float(np.abs(g).max())
    g_hat = g / scale if settings.normalize_gradient else g
    if settings.line_search:
        assert evaluate is not None
        return _line_search(z, g_hat, delta, j, first, settings, project, evaluate)
    return project(z - settings.learning_rate * g_hat + settings.momentum * delta), 0


def optimize(
    value_and_grad: ValueAndGrad,
    z0: FloatArray,
    settings: Settings,
    *,
    project: Callable[[FloatArray], FloatArray] = lambda z: z,
    evaluate: Evaluate | None = None,
    is_success: Callable[[Any], bool] = lambda extra: False,
    on_iteration: Callable[[int, float, float, bool], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> Outcome:
    """Minimise J from ``z0`` (M, U) by momentum gradient descent; see the module docstring.

    ``on_iteration(l, J, best J, success)`` is called for the initial controller (l = 0) and after
    every update. A NaN or Inf objective or gradient ends the run as ``diverged`` and returns the
    best finite controller so far; ``should_stop()`` returning True ends it as ``cancelled``.

    With ``stop_on_success`` the run goes on for ``polish_iterations`` more updates once the
    criterion is first met, so the controller handed to the real physics meets it with some margin
    rather than on the edge; the controller returned is then the best one that meets it.
    """
    if settings.line_search and evaluate is None:
        raise ValueError("line_search needs an evaluate function that scores a batch of controllers")
    z = project(np.asarray(z0, dtype=np.float64))
    j, g, extra = value_and_grad(z)
    what = _not_finite(j, g)
    if what is not None:
        why = f"diverged at iteration 0: the {what} of the initial controller is not finite"
        return Outcome("diverged", why, z, j, False, extra, 0, None, [], 1)
    ok = is_success(extra)
    progress = _Progress.start(z, j, ok, extra)
    if on_iteration is not None:
        on_iteration(0, j, j, ok)
    stop: str
    reason: str | None
    delta = np.zeros_like(z)
    done = 0  # updates made
    while True:
        halt = _halt(progress, done, g, settings, should_stop)
        if halt is not None:
            stop, reason = halt
            break
        z_new, scored = _next_point(z, g, delta, j, done == 0, settings, project, evaluate)
        progress.rollouts += scored
        if z_new is None:
            stop, reason = "stalled", "no step along the gradient and the momentum lowers the objective"
            break
        delta = z_new - z  # the step actually taken (after projection) is the next momentum
        z = z_new
        done += 1
        j_new, g, extra = value_and_grad(z)
        progress.rollouts += 1
        what = _not_finite(j_new, g)
        if what is not None:
            stop, reason = "diverged", f"diverged at iteration {done}: the {what} is not finite ({j_new})"
            log.warning(
                "control synthesis %s; keeping the best finite controller (J=%g)",
                reason,
                progress.best.objective,
            )
            break
        ok = is_success(extra)
        progress.record(z, j_new, ok, extra, done)
        if on_iteration is not None:
            on_iteration(done, j_new, progress.best.objective, ok)
        if abs(j_new - j) <= settings.tolerance * max(abs(j), 1e-12):
            stop, reason = "converged", f"relative change of the objective below {settings.tolerance:g}"
            break
        j = j_new
    return progress.outcome(stop, reason, done, settings)


def elapsed(t0: float) -> float:
    return round(time.perf_counter() - t0, 4)


def clean(x: Any) -> Any:
    """JSON-able copy: arrays to lists, non-finite floats to None (JSON has no NaN)."""
    if isinstance(x, dict):
        return {k: clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return clean(x.tolist())
    if isinstance(x, np.floating | float):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x
