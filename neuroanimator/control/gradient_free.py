"""Gradient-free baselines for thesis 6.3: simulated annealing, Nelder-Mead simplex and CMA-ES,
numpy only.

The thesis compares its gradient-directed synthesis with simulated annealing and the simplex
method run on the physical model (3,000 and 700 simulations against 20 iterations). These run on
the same normalised control points and the same objective as the gradient method, with every
evaluation one physical simulation; they stop when they reach a target objective value or spend
their evaluation budget. All are written from their published update rules:

- simulated annealing (Kirkpatrick, Gelatt and Vecchi 1983): Gaussian moves of every coordinate,
  accepted by the Metropolis rule at a temperature that falls geometrically from one set by the
  first moves' changes of the objective, the step scaled to keep about a third of moves accepted;
- Nelder-Mead with the dimension-adapted coefficients of Gao and Han (2012), which keep the
  simplex from collapsing in 60-80 dimensions where the classic (1, 2, ½, ½) stall;
- CMA-ES, (μ/μ_w, λ) with cumulative step-size adaptation and rank-one plus rank-μ covariance
  updates (Hansen's tutorial defaults), which scores each generation as one batch.

Bounds (the control limits) are handled by evaluating the projection of a point onto the box and,
for CMA-ES, adding a penalty on the distance to it so the search distribution does not drift out.

Shapes: ``f`` takes a batch (B, D) of flattened points and returns (B,) objective values.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BatchObjective = Callable[[FloatArray], FloatArray]


@dataclass
class Trace:
    """Progress of a search: best value after each evaluation batch, and when it hit the target."""

    method: str
    evaluations: list[int] = field(default_factory=list)
    best: list[float] = field(default_factory=list)
    wall: list[float] = field(default_factory=list)
    evaluations_to_target: int | None = None
    wall_to_target_s: float | None = None
    best_x: FloatArray | None = None
    total_evaluations: int = 0
    wall_s: float = 0.0

    def to_dict(self) -> dict[str, object]:
        return {
            "method": self.method,
            "evaluations_to_target": self.evaluations_to_target,
            "wall_to_target_s": self.wall_to_target_s,
            "total_evaluations": self.total_evaluations,
            "wall_s": self.wall_s,
            "best_objective": self.best[-1] if self.best else None,
        }


class _Counter:
    """Wraps the objective: counts evaluations, tracks the best, stops at the target or the budget."""

    def __init__(self, f: BatchObjective, trace: Trace, target: float, budget: int) -> None:
        self.f = f
        self.trace = trace
        self.target = target
        self.budget = budget
        self.count = 0
        self.best = np.inf
        self.t0 = time.perf_counter()

    @property
    def done(self) -> bool:
        return self.count >= self.budget or self.trace.evaluations_to_target is not None

    def __call__(self, xs: FloatArray) -> FloatArray:
        xs = np.atleast_2d(xs)
        xs = xs[: max(0, self.budget - self.count)]
        values = np.asarray(self.f(xs), dtype=np.float64)
        values = np.where(np.isfinite(values), values, np.inf)
        for x, v in zip(xs, values, strict=True):
            self.count += 1
            if v < self.best:
                self.best = float(v)
                self.trace.best_x = x.copy()
            if self.best <= self.target and self.trace.evaluations_to_target is None:
                self.trace.evaluations_to_target = self.count
                self.trace.wall_to_target_s = time.perf_counter() - self.t0
        self.trace.evaluations.append(self.count)
        self.trace.best.append(self.best)
        self.trace.wall.append(time.perf_counter() - self.t0)
        self.trace.total_evaluations = self.count
        self.trace.wall_s = time.perf_counter() - self.t0
        return values


def nelder_mead(
    f: BatchObjective,
    x0: FloatArray,
    *,
    low: FloatArray,
    high: FloatArray,
    step: float = 0.25,
    target: float = -np.inf,
    budget: int = 3000,
) -> Trace:
    """Minimise ``f`` from ``x0`` (D,) with the adaptive Nelder-Mead simplex inside [low, high]."""
    trace = Trace("nelder_mead")
    ev = _Counter(f, trace, target, budget)
    n = x0.size
    alpha, beta = 1.0, 1.0 + 2.0 / n  # reflection, expansion (Gao and Han 2012)
    gamma, delta = 0.75 - 1.0 / (2 * n), 1.0 - 1.0 / n  # contraction, shrink

    def proj(x: FloatArray) -> FloatArray:
        return np.clip(x, low, high)

    simplex = [proj(x0)]
    for i in range(n):
        x = x0.copy()
        # step towards the inside of the box when x0 sits on a bound
        x[i] = x[i] + step if x[i] + step <= high[i] else x[i] - step
        simplex.append(proj(x))
    pts = np.array(simplex)
    vals = ev(pts)
    if vals.size < pts.shape[0]:  # the budget ended while building the simplex
        return trace
    while not ev.done:
        order = np.argsort(vals)
        pts, vals = pts[order], vals[order]
        centroid = pts[:-1].mean(axis=0)
        xr = proj(centroid + alpha * (centroid - pts[-1]))
        (fr,) = ev(xr) if not ev.done else (np.inf,)
        if fr < vals[0]:
            xe = proj(centroid + beta * (xr - centroid))
            (fe,) = ev(xe) if not ev.done else (np.inf,)
            pts[-1], vals[-1] = (xe, fe) if fe < fr else (xr, fr)
        elif fr < vals[-2]:
            pts[-1], vals[-1] = xr, fr
        else:
            outside = fr < vals[-1]
            xc = proj(centroid + gamma * ((xr if outside else pts[-1]) - centroid))
            (fc,) = ev(xc) if not ev.done else (np.inf,)
            if fc < (fr if outside else vals[-1]):
                pts[-1], vals[-1] = xc, fc
            elif not ev.done:
                pts[1:] = proj(pts[0] + delta * (pts[1:] - pts[0]))
                new = ev(pts[1:])
                vals[1 : 1 + new.size] = new
    return trace


def cma_es(
    f: BatchObjective,
    x0: FloatArray,
    *,
    low: FloatArray,
    high: FloatArray,
    sigma: float = 0.3,
    target: float = -np.inf,
    budget: int = 3000,
    seed: int = 0,
    popsize: int | None = None,
) -> Trace:
    """Minimise ``f`` from ``x0`` (D,) with CMA-ES; each generation is one batch of ``popsize``."""
    trace = Trace("cma_es")
    rng = np.random.default_rng(seed)
    n = x0.size
    lam = popsize or 4 + int(3 * np.log(n))
    mu = lam // 2
    w = np.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    w /= w.sum()
    mu_eff = 1.0 / float((w**2).sum())
    c_c = (4 + mu_eff / n) / (n + 4 + 2 * mu_eff / n)
    c_s = (mu_eff + 2) / (n + mu_eff + 5)
    c_1 = 2 / ((n + 1.3) ** 2 + mu_eff)
    c_mu = min(1 - c_1, 2 * (mu_eff - 2 + 1 / mu_eff) / ((n + 2) ** 2 + mu_eff))
    d_s = 1 + 2 * max(0.0, np.sqrt((mu_eff - 1) / (n + 1)) - 1) + c_s
    chi_n = np.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n**2))
    mean = np.clip(x0, low, high).astype(np.float64)
    p_c = np.zeros(n)
    p_s = np.zeros(n)
    cov = np.eye(n)
    basis, scales = np.eye(n), np.ones(n)  # cov = basis · diag(scales²) · basisᵀ
    ev = _Counter(f, trace, target, budget)
    (f0,) = ev(mean[None])
    penalty = abs(float(f0)) / n + 1e-9  # per unit² of distance outside the box
    generation = 0
    while not ev.done:
        generation += 1
        zs = rng.standard_normal((lam, n))
        ys = (zs * scales) @ basis.T  # ~ N(0, C)
        xs = mean + sigma * ys
        inside = np.clip(xs, low, high)
        values = ev(inside)
        if values.size < lam:
            break
        values = values + penalty * ((xs - inside) ** 2).sum(axis=1)
        order = np.argsort(values)[:mu]
        y_w = w @ ys[order]
        mean = mean + sigma * y_w
        inv_sqrt = basis @ np.diag(1.0 / scales) @ basis.T
        p_s = (1 - c_s) * p_s + np.sqrt(c_s * (2 - c_s) * mu_eff) * (inv_sqrt @ y_w)
        h_s = np.linalg.norm(p_s) / np.sqrt(1 - (1 - c_s) ** (2 * generation)) < (1.4 + 2 / (n + 1)) * chi_n
        p_c = (1 - c_c) * p_c + h_s * np.sqrt(c_c * (2 - c_c) * mu_eff) * y_w
        rank_mu = (ys[order].T * w) @ ys[order]
        cov = (
            (1 - c_1 - c_mu) * cov
            + c_1 * (np.outer(p_c, p_c) + (1 - h_s) * c_c * (2 - c_c) * cov)
            + c_mu * rank_mu
        )
        sigma *= float(np.exp((c_s / d_s) * (np.linalg.norm(p_s) / chi_n - 1)))
        cov = 0.5 * (cov + cov.T)
        eig, basis = np.linalg.eigh(cov)
        scales = np.sqrt(np.maximum(eig, 1e-20))
    return trace


def simulated_annealing(
    f: BatchObjective,
    x0: FloatArray,
    *,
    low: FloatArray,
    high: FloatArray,
    step: float = 0.25,
    target: float = -np.inf,
    budget: int = 3000,
    seed: int = 0,
    initial_acceptance: float = 0.5,
    final_temperature: float = 1e-6,
) -> Trace:
    """Minimise ``f`` from ``x0`` (D,) by simulated annealing inside [low, high], one evaluation per move.

    The first temperature accepts an average uphill move of the first 20 with probability
    ``initial_acceptance``; it falls geometrically to ``final_temperature`` times that by the end of
    the budget. The step (in x's units) grows by 10% after an accepted move and shrinks by 5% after a
    rejected one, which holds the acceptance near a third.
    """
    trace = Trace("simulated_annealing")
    rng = np.random.default_rng(seed)
    ev = _Counter(f, trace, target, budget)
    x = np.clip(x0, low, high).astype(np.float64)
    (fx,) = ev(x[None])
    probes = min(20, max(1, budget // 10))
    ups = []
    for _ in range(probes):
        if ev.done:
            return trace
        (fy,) = ev(np.clip(x + step * rng.standard_normal(x.size), low, high)[None])
        if np.isfinite(fy) and fy > fx:
            ups.append(fy - fx)
    t0 = (float(np.mean(ups)) if ups else abs(float(fx)) * 0.01 + 1e-9) / -np.log(initial_acceptance)
    cooling = final_temperature ** (1.0 / max(1, budget - ev.count))
    temperature = t0
    while not ev.done:
        y = np.clip(x + step * rng.standard_normal(x.size), low, high)
        (fy,) = ev(y[None])
        if fy <= fx or rng.random() < np.exp(-(fy - fx) / temperature):
            x, fx = y, fy
            step *= 1.1
        else:
            step *= 0.95
        temperature *= cooling
    return trace
