"""Search the running controller's gait parameters: many candidate gaits run at once, the best kept.

    python bench/runner_tune.py [--init gait.json] [--batch 64] [--rounds 10] [--speeds 2.0,3.0]
                                [--seconds 4,8,15] [--push-n 250] [--budget-s 600]
                                [--control-every 3] [--kinematic] [--starts 1] [--noise 0.01]

Each candidate gait runs at every target speed, and (from the last horizon on) four times more
with a push of the torso (sideways both ways, forwards, backwards); all runs of all candidates are one
batch of the closed loop. With ``--starts 1`` a candidate scores its worst condition: the seconds it
stayed up, less the error of its mean speed. The running loop is chaotic, so a gait that survives one
start may fall from a start 0.01 m/s away: with ``--starts K`` every condition runs from K starts
whose velocities are perturbed by N(0, ``--noise``), drawn afresh each round, and a candidate scores
the mean over all of them (a smoother measure of how reliably it stays up). The next round samples
around the best quarter (a shrinking Gaussian step); the best ones are scored again each round, so
a lucky draw does not keep a gait. After each round a line gives the best gait so far as JSON, the form
``runner_control.Gait`` takes; the controller's defaults come from such a search.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from neuroanimator import catalog
from neuroanimator.catalog.runner import gait as rc

RANGES: dict[str, tuple[float, float]] = {
    "stance_s": (0.15, 0.45),
    "flight_max_s": (0.02, 0.25),
    "lean": (-0.1, 0.3),
    "lean_per_speed": (0.0, 0.2),
    "pitch_kp": (300.0, 2500.0),
    "pitch_kd": (20.0, 250.0),
    "roll_kp": (200.0, 2000.0),
    "roll_kd": (20.0, 200.0),
    "yaw_kp": (50.0, 1500.0),
    "yaw_kd": (5.0, 200.0),
    "step_gain": (0.1, 1.0),
    "speed_gain": (0.0, 0.3),
    "side_gain": (0.0, 0.4),
    "width": (0.0, 0.12),
    "swing_knee": (0.8, 2.1),
    "fold_fraction": (0.2, 0.9),
    "touchdown_knee": (0.05, 0.6),
    "stance_knee": (0.1, 0.8),
    "pushoff_knee": (0.0, 0.5),
    "pushoff_ankle": (-0.8, 0.2),
    "pushoff_from": (0.2, 0.9),
    "liftoff_hip": (-0.3, 1.0),
    "arm_swing": (0.0, 1.5),
    "waist_lean": (-0.1, 0.3),
}


def score(
    pop: np.ndarray,
    names: list[str],
    speeds: list[float],
    seconds: float,
    push_n: float | None,
    control_every: int = 3,
    kinematic: bool = False,
    starts: int = 1,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
    speed_weight: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(C, P) candidates -> (C,) scores, (C,) worst seconds up, (C,) mean speed at the first target.

    With ``starts`` > 1 each condition runs ``starts`` times per candidate from perturbed starts and
    the score and the seconds up are means over them."""
    m = catalog.get("runner").mj_model
    rng = rng or np.random.default_rng(0)
    conditions: list[tuple[float, rc.Push | None]] = [(v, None) for v in speeds]
    if push_n:  # sideways both ways, and forwards and backwards at 0.8 of the force
        for force in (
            (0.0, push_n, 0.0),
            (0.0, -push_n, 0.0),
            (0.8 * push_n, 0.0, 0.0),
            (-0.8 * push_n, 0.0, 0.0),
        ):
            conditions.append((speeds[0], rc.Push(force=force, start_s=seconds / 2, duration_s=0.2)))
    c = pop.shape[0]
    scores, alive_all, speed0 = [], [], np.zeros(c)
    reps = np.repeat(pop, starts, axis=0)  # (C·K, P): each candidate K times in a row
    for k, (v, push) in enumerate(conditions):
        gait = rc.Gait(**{n: reps[:, i] for i, n in enumerate(names)})  # type: ignore[arg-type]
        # one start per condition as it is, or K perturbed ones
        start = rc.perturbed_starts(m, v, reps.shape[0], rng, noise if starts > 1 else 0.0)
        res = rc.run(
            m,
            start,
            v,
            seconds,
            gait=gait,
            push=push,
            record=False,
            control_every=control_every,
            kinematic=kinematic,
        )
        alive = np.minimum(res.fell_at, seconds)
        mean = res.final_qpos[:, 0] / np.maximum(alive, 1e-3)
        each = alive - speed_weight * np.abs(mean - v) - np.abs(res.final_qpos[:, 1]) / seconds
        scores.append(each.reshape(c, starts).mean(axis=1))
        alive_all.append(alive.reshape(c, starts).mean(axis=1))
        if k == 0:
            speed0 = mean.reshape(c, starts).mean(axis=1)
    if starts > 1:  # many starts per condition: the mean over everything, not the worst condition
        return np.mean(scores, axis=0), np.mean(alive_all, axis=0), speed0
    return np.min(scores, axis=0), np.min(alive_all, axis=0), speed0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--init", type=Path, help="a gait as JSON to start from (else the defaults)")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--speeds", default="2.0,3.0")
    p.add_argument("--seconds", default="4,8,15", help="horizons, each for an equal share of the rounds")
    p.add_argument("--push-n", type=float, default=250.0)
    p.add_argument("--sigma", type=float, default=0.08, help="first step, as a fraction of each range")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--budget-s", type=float, default=600.0)
    p.add_argument("--control-every", type=int, default=3, help="physical steps per control period")
    p.add_argument(
        "--kinematic", action="store_true", help="the controller reads runner_control.KinematicSensors"
    )
    p.add_argument("--starts", type=int, default=1, help="perturbed starts per condition and candidate")
    p.add_argument("--noise", type=float, default=0.01, help="velocity perturbation of those starts")
    p.add_argument("--speed-weight", type=float, default=2.0, help="score lost per m/s off the target")
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    names = list(RANGES)
    lo = np.array([RANGES[n][0] for n in names])
    hi = np.array([RANGES[n][1] for n in names])
    init = dataclasses.asdict(rc.Gait())
    if args.init:
        init.update(json.loads(args.init.read_text()))
    centre = np.array([init[n] for n in names])
    sigma = args.sigma * (hi - lo)
    pop = np.clip(centre + sigma * rng.standard_normal((args.batch, len(names))), lo, hi)
    pop[0] = centre
    speeds = [float(s) for s in args.speeds.split(",")]
    horizons = [float(s) for s in args.seconds.split(",")]
    t0 = time.time()
    best = centre
    for r in range(args.rounds):
        stage = min(len(horizons) - 1, r * len(horizons) // args.rounds)
        seconds = horizons[stage]
        push = args.push_n if stage == len(horizons) - 1 else None
        s, alive, v = score(
            pop,
            names,
            speeds,
            seconds,
            push,
            args.control_every,
            args.kinematic,
            args.starts,
            args.noise,
            rng,
            args.speed_weight,
        )
        order = np.argsort(-s)
        best = pop[order[0]].copy()
        print(
            f"round {r}: {seconds:.0f} s, best score {s[order[0]]:.2f} (up {alive[order[0]]:.1f} s, "
            f"{v[order[0]]:.2f} m/s), mean up {alive.mean():.1f} s, {(alive >= seconds).sum()} of {len(s)} "
            f"stay up, {time.time() - t0:.0f} s",
            flush=True,
        )
        print(json.dumps({n: round(float(best[i]), 4) for i, n in enumerate(names)}), flush=True)
        if time.time() - t0 > args.budget_s:
            break
        elite = pop[order[: max(2, args.batch // 4)]]
        parents = elite[rng.integers(0, len(elite), args.batch)]
        pop = np.clip(parents + sigma * (0.8 ** (r + 1)) * rng.standard_normal(parents.shape), lo, hi)
        pop[: len(elite)] = elite
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
