"""Before gradient descent: a global pass and several starts, all batched on the emulator.

Gradient descent from one start settles in the nearest basin, and some goals have none near the
start: a truck asked to park straight sideways sits on a flat spot (at rest, steering has no
gradient), a pendulum asked to stand inverted has a zero gradient by symmetry, and a truck that
must reverse stalls metres short when it starts by rolling forward. The emulator scores a batch of
hundreds of controllers in about the time of one (bench: 256 trajectories of 40 steps in 20-40 ms
on one thread), so the search spends that batch width where one start would spend iterations:

1. ``starting_points``: the job's constant initial controller and, for each control, the same
   with that control shifted up and down by half its useful range (gas forward/back, steer
   left/right, torque left/right, tilt jets each way): P = 1 + 2U constant controllers.
2. ``cross_entropy``: a short cross-entropy search (Rubinstein 1999; CEM in trajectory optimisation)
   seeded by those starts: generation 0 scores the starts and random controllers around them, each
   later generation samples around the mean and spread of the best tenth so far. Gradient-free and
   global: it finds the basin (which way to drive, which way to swing), not the precise controller.
3. ``descend_starts``: gradient descent with the per-iteration (η, α) search (``synthesis.py``) from
   several starts at once: the global search's best and the best of the structured starts, each
   iteration one batched rollout and backward pass for all of them and one batched evaluation of
   every start's step candidates. The start that meets the criterion, else the lowest objective,
   is refined further by ``synthesis.optimize``.

Why these, measured (``bench/control_goals.py --seed 0 --goals 20``, success on MuJoCo of the
controller returned, single start → this search): truck-parking 13 → 18 of 20 (the goals that
stalled 2-8 m short from the zero-control start are reached from a global-search or steer start),
pendulum-swing 15 → 16, lander-landing 13 → 14. The built-in tasks keep within 20 iterations and
2 s: 7 / 17 / 17 iterations (pendulum / lander / truck), at about 1,400-2,400 emulator rollouts
instead of 560-1,200. What the search leaves (descents that settle on a compromise short of the
criterion, like a lander on the pad but tilted 11-16°) the Levenberg-Marquardt updates after the
descent finish (``gauss_newton.py``): 18 / 20 / 18 of 20 on MuJoCo.
Encoding the success checks into the objective as a penalty (the ``success_margin`` term) was
measured too and is not a default: with weight 10 on every job it lowered MuJoCo success to 13
(pendulum), 2 (lander) and 18 (truck) of 20; a job can still ask for it.

Shapes: P starts, B controllers in a batch, M control points per control, U controls; points are
normalised (``bptt.ControlProblem``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from neuroanimator.control.synthesis import Settings

FloatArray = NDArray[np.float64]
BatchEvaluate = Callable[[FloatArray], FloatArray]  # (B, M, U) -> (B,)
# (B, M, U) -> J (B,), ∇J (B, M, U), and per controller what is_success needs
BatchValueAndGrad = Callable[[FloatArray], tuple[FloatArray, FloatArray, list[Any]]]

START_SHIFT = 0.5  # of a control's half range: the structured starts' offset
ELITE_FRACTION = 0.1
MIN_SPREAD = 0.05  # the cross-entropy spread never collapses below this (normalised units)


def starting_points(z0: FloatArray, project: Callable[[FloatArray], FloatArray]) -> FloatArray:
    """(P, M, U): ``z0`` (M, U) and, per control, ``z0`` with that control shifted by ±START_SHIFT
    (projected onto the limits; a shift the limits undo is left out)."""
    starts = [project(z0)]
    for u in range(z0.shape[1]):
        for sign in (1.0, -1.0):
            z = z0.copy()
            z[:, u] += sign * START_SHIFT
            z = project(z)
            if not any(np.allclose(z, s) for s in starts):
                starts.append(z)
    return np.stack(starts)


@dataclass
class GlobalSearch:
    """What the cross-entropy pass found: every scored controller's best few, in order."""

    best: FloatArray  # (B, M, U) the lowest objectives first
    values: FloatArray  # (B,)
    start_values: FloatArray  # (P,) each structured start's objective
    rollouts: int
    generations: int


def cross_entropy(
    evaluate: BatchEvaluate,
    starts: FloatArray,
    project: Callable[[FloatArray], FloatArray],
    *,
    generations: int,
    population: int,
    sigma: float = 0.5,
    keep: int = 8,
    seed: int = 0,
) -> GlobalSearch:
    """Cross-entropy search from ``starts`` (P, M, U): ``generations`` batches of ``population``
    controllers after generation 0 (the starts and ``population − P`` samples around them)."""
    rng = np.random.default_rng(seed)
    p = starts.shape[0]
    extra = max(0, population - p)
    around = starts[np.arange(extra) % p]
    batch = np.concatenate([starts, project(around + sigma * rng.standard_normal(around.shape))])
    values = _finite(evaluate(batch))
    rollouts = batch.shape[0]
    start_values = values[:p].copy()
    pool_z, pool_j = batch, values
    n_elite = max(2, round(ELITE_FRACTION * batch.shape[0]))
    for _ in range(generations):
        order = np.argsort(pool_j)[:n_elite]
        elite = pool_z[order]
        mean = elite.mean(axis=0)
        spread = np.maximum(elite.std(axis=0), MIN_SPREAD)
        batch = project(mean + spread * rng.standard_normal((population, *mean.shape)))
        values = _finite(evaluate(batch))
        rollouts += population
        pool_z = np.concatenate([pool_z[order], batch])
        pool_j = np.concatenate([pool_j[order], values])
    order = np.argsort(pool_j)[:keep]
    return GlobalSearch(pool_z[order], pool_j[order], start_values, rollouts, generations)


@dataclass
class StartsOutcome:
    """The best of several starts after ``iterations`` batched descent steps."""

    z: FloatArray  # (M, U) the chosen start's controller
    objective: float
    success: bool
    index: int  # which start
    iterations: int
    rollouts: int
    history: list[float] = field(default_factory=list)  # the lowest J over the starts per iteration
    objectives: list[float] = field(default_factory=list)  # every start's final J


def descend_starts(
    values_and_grads: BatchValueAndGrad,
    evaluate: BatchEvaluate,
    zs: FloatArray,
    settings: Settings,
    iterations: int,
    *,
    project: Callable[[FloatArray], FloatArray],
    is_success: Callable[[Any], bool],
    on_iteration: Callable[[int, float, float, bool], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> StartsOutcome:
    """Momentum descent with the (η, α) search from B starts (B, M, U) at once, for at most
    ``iterations`` updates; ends early when a start meets the criterion or every start stalls.
    The chosen start is the one that meets the criterion with the lowest J, else the lowest J."""
    b = zs.shape[0]
    z = zs.copy()
    delta = np.zeros_like(z)
    active = np.ones(b, dtype=bool)
    history: list[list[float]] = []
    rollouts = 0
    done = 0
    j, g, extras = values_and_grads(z)
    rollouts += b
    j = _finite(j)
    ok = np.array([is_success(e) for e in extras])
    history.append(j.tolist())
    while done < iterations and not ok.any() and active.any():
        if should_stop is not None and should_stop():
            break
        cands = settings.candidates(first=done == 0)
        idx = np.flatnonzero(active)
        steps = []
        for i in idx:
            scale = float(np.abs(g[i]).max())
            g_hat = g[i] / scale if scale > 0 else g[i]
            steps.append(np.stack([project(z[i] - eta * g_hat + alpha * delta[i]) for eta, alpha in cands]))
        trial = np.stack(steps)  # (A, C, M, U)
        values = _finite(evaluate(trial.reshape(-1, *z.shape[1:]))).reshape(len(idx), len(cands))
        rollouts += values.size
        for a, i in enumerate(idx):
            c = int(np.argmin(values[a]))
            if values[a, c] < j[i]:
                delta[i] = trial[a, c] - z[i]
                z[i] = trial[a, c]
            else:
                active[i] = False  # stalled: no candidate lowers its objective
        done += 1
        j, g, extras = values_and_grads(z)
        rollouts += b
        j = _finite(j)
        ok = np.array([is_success(e) for e in extras])
        history.append(j.tolist())
        if on_iteration is not None:
            best = int(np.argmin(j))
            on_iteration(done, float(j[best]), float(j.min()), bool(ok.any()))
    chosen = int(np.argmin(np.where(ok, j, np.inf))) if ok.any() else int(np.argmin(j))
    return StartsOutcome(
        z=z[chosen],
        objective=float(j[chosen]),
        success=bool(ok[chosen]),
        index=chosen,
        iterations=done,
        rollouts=rollouts,
        history=[min(h) for h in history[1:]],
        objectives=j.tolist(),
    )


def _finite(values: FloatArray) -> FloatArray:
    v = np.asarray(values, dtype=np.float64)
    return np.where(np.isfinite(v), v, np.inf)
