"""The runner's controller on MuJoCo: speed over 30 s at two target speeds, pushes, throughput.

    python bench/runner_run.py [--speeds 2.0,2.6] [--seconds 30] [--push-n 250]
                               [--control-every 3] [--kinematic] [--starts K] [--gait JSON]
                               [--json]

Each run starts from ``runner_control.running_start`` at the target speed. The speed is the mean
forward speed of the pelvis over the whole run and over its last 25 s; a run has fallen once its
pelvis drops below 0.55 m. Pushes: a force of ``--push-n`` newtons on the torso for 0.2 s at 10 s,
leftwards, rightwards, forwards and backwards, while running at the first target speed. Throughput:
simulated seconds per wall-clock second of the closed loop (MuJoCo's sensors) (Python controller every few physical
steps, ``mujoco.rollout`` in between, 2 threads), for one run and for a batch of 64.

One run from one start says little about a chaotic loop: with ``--starts K`` each case (every target
speed, and each push at the first one, here at 5 s) runs again from K starts whose velocities are
perturbed by N(0, 0.01) (m/s, rad/s), and a table says how many stay up for the whole run, the
median time up, and the mean speed and sideways drift of those that stayed up.
With ``--json`` the last line is one JSON object with every number.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from neuroanimator import catalog
from neuroanimator.catalog.runner import gait as rc


def _speeds(result: rc.RunResult, seconds: float) -> tuple[float, float]:
    x = result.states[0, :, 1]  # full-physics state: time, then qpos (pelvis x first)
    x_end = float(result.final_qpos[0, 0])
    k5 = round(5.0 / result.dt)
    return x_end / seconds, (x_end - float(x[k5])) / (seconds - 5.0)


def _reliability(
    m: Any, speeds: list[float], pushes: dict[str, tuple[float, float, float]], args: argparse.Namespace
) -> list[dict[str, Any]]:
    """Each case from ``args.starts`` perturbed starts: how many stay up, for how long, how fast."""
    rng = np.random.default_rng(0)
    cases: list[tuple[str, float, rc.Push | None]] = [(f"{v:.1f} m/s", v, None) for v in speeds]
    cases += [
        (
            f"pushed {name} at {speeds[0]:.1f} m/s",
            speeds[0],
            rc.Push(force=force, start_s=5.0, duration_s=0.2),
        )
        for name, force in pushes.items()
    ]
    print()
    print(
        f"| case ({args.starts} perturbed starts) | up for {args.seconds:.0f} s | median s up | mean speed (m/s) | mean sideways drift (m) |"
    )
    print("|---|---|---|---|---|")
    rows = []
    for name, v, push in cases:
        start = rc.perturbed_starts(m, v, args.starts, rng)
        res = rc.run(
            m, start, v, args.seconds, push=push, control_every=args.control_every,
            kinematic=args.kinematic, record=False, gait=args.gait,
        )  # fmt: skip
        up = ~np.isfinite(res.fell_at)
        speed = float(np.mean(res.final_qpos[up, 0])) / args.seconds if up.any() else None
        drift = float(np.mean(np.abs(res.final_qpos[up, 1]))) if up.any() else None
        median = float(np.median(np.minimum(res.fell_at, args.seconds)))
        rows.append(
            {"case": name, "target": v, "starts": args.starts, "up": int(up.sum()), "median_s": median,
             "speed": speed, "drift": drift}
        )  # fmt: skip
        speed_text = "–" if speed is None else f"{speed:.2f}"
        drift_text = "–" if drift is None else f"{drift:.2f}"
        print(f"| {name} | {int(up.sum())} of {args.starts} | {median:.1f} | {speed_text} | {drift_text} |")
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--speeds", default="2.0,2.6")
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--push-n", type=float, default=250.0)
    p.add_argument("--control-every", type=int, default=3, help="physical steps per control period")
    p.add_argument("--kinematic", action="store_true", help="the controller reads KinematicSensors")
    p.add_argument(
        "--starts", type=int, default=0, help="perturbed starts per case for the reliability table"
    )
    p.add_argument(
        "--gait", type=Path, help="a gait as JSON (as runner_tune.py prints it) instead of the default"
    )
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    args.gait = rc.Gait(**json.loads(args.gait.read_text())) if args.gait else None
    m = catalog.get("runner").mj_model
    speeds = [float(s) for s in args.speeds.split(",")]
    every = args.control_every
    out: dict[str, Any] = {
        "dt": m.opt.timestep,
        "seconds": args.seconds,
        "control_every": args.control_every,
        "kinematic": args.kinematic,
        "runs": [],
        "pushes": [],
    }

    print("| target speed (m/s) | mean speed (m/s) | after 5 s (m/s) | sideways drift (m) | fell |")
    print("|---|---|---|---|---|")
    for v in speeds:
        res = rc.run(
            m, rc.running_start(m, v), v, args.seconds, control_every=every, kinematic=args.kinematic,
            gait=args.gait,
        )  # fmt: skip
        mean, settled = _speeds(res, args.seconds)
        fell = float(res.fell_at[0])
        drift = float(res.final_qpos[0, 1])
        out["runs"].append(
            {
                "target": v,
                "mean": mean,
                "after_5s": settled,
                "drift": drift,
                "fell_at": None if np.isinf(fell) else fell,
            }
        )
        print(
            f"| {v:.1f} | {mean:.2f} | {settled:.2f} | {drift:+.2f} | {'no' if np.isinf(fell) else f'at {fell:.1f} s'} |"
        )

    v = speeds[0]
    f = args.push_n
    pushes = {
        "left": (0.0, f, 0.0),
        "right": (0.0, -f, 0.0),
        "forward": (f, 0.0, 0.0),
        "backward": (-f, 0.0, 0.0),
    }
    print()
    print(
        f"| push on the torso at {v:.1f} m/s | force (N) | for (s) | impulse (N·s) | fell | speed after 5 s more (m/s) |"
    )
    print("|---|---|---|---|---|---|")
    for name, force in pushes.items():
        push = rc.Push(force=force, start_s=10.0, duration_s=0.2)
        res = rc.run(
            m, rc.running_start(m, v), v, 15.0, push=push, control_every=every, kinematic=args.kinematic,
            gait=args.gait,
        )  # fmt: skip
        fell = float(res.fell_at[0])
        k10 = round(10.0 / res.dt)
        after = (float(res.final_qpos[0, 0]) - float(res.states[0, k10, 1])) / 5.0
        out["pushes"].append(
            {
                "direction": name,
                "force": list(force),
                "duration_s": 0.2,
                "fell_at": None if np.isinf(fell) else fell,
                "speed_after": after,
            }
        )
        print(
            f"| {name} | {f:.0f} | 0.2 | {0.2 * f:.0f} | {'no' if np.isinf(fell) else f'at {fell:.1f} s'} | {after:.2f} |"
        )

    if args.starts > 0:
        out["reliability"] = _reliability(m, speeds, pushes, args)

    print()
    print("| runs at once | control every (steps) | simulated s per wall s (all runs) | per run |")
    print("|---|---|---|---|")
    out["throughput"] = []
    for batch in (1, 64):
        for every in (3, 6):
            start = np.repeat(rc.running_start(m, v)[None], batch, axis=0)
            res = rc.run(m, start, v, 5.0, control_every=every, record=False, gait=args.gait)
            rate = batch * 5.0 / res.wall_s
            out["throughput"].append({"batch": batch, "control_every": every, "sim_s_per_wall_s": rate})
            print(f"| {batch} | {every} | {rate:.1f} | {rate / batch:.2f} |")
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
