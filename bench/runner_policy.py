"""The runner's learned running policy (task ``runner-run``): learned through the committed emulator
from the running controller (``control.runner_policy``), judged on MuJoCo beside the controller.

    python bench/runner_policy.py [--speeds 1.8,2.0,2.2] [--runs 16] [--seconds 30]
                                  [--rounds 6] [--data-runs 64] [--data-seconds 10]
                                  [--mujoco-every K] [--members M] [--seed 0] [--save-to DATA_DIR]
                                  [--quick] [--json]

For each command: ``--runs`` runs of ``--seconds`` on MuJoCo from perturbed running starts, pushed
with 250 N for 0.2 s at 5 s (forward, backward, left, right in turn), the policy every super-step
(16.2 ms) on the state, the controller the same on ``KinematicSensors``: how many stayed up, how many
also ran within 10 % of the command over the last two thirds of the run, and their mean speed.
``success_physics``: the share of all the policy's runs that met their command (the target: 16 of 16
at each of 1.8, 2.0 and 2.2 m/s). ``root_drift_1s_m``: the pelvis's mean distance between the emulator
and MuJoCo 1 s after 10 running starts at 2.0 m/s, each under the policy (the target: 0.2 m).
``--quick``: seconds of everything (a smoke test).
With ``--json`` the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

from neuroanimator.artifacts import registry
from neuroanimator.control.policy_store import save_commanded_policy
from neuroanimator.control.runner_policy import (
    RUNNER_RUN,
    DistillSettings,
    distill,
    emulator_step,
    judge,
    root_drift,
    session_starts,
)
from neuroanimator.control.threads import torch_threads
from neuroanimator.core.policy_manifest import PolicyMetrics
from neuroanimator.export.runtime import OnnxEmulator

REPO = Path(__file__).resolve().parents[1]
log = logging.getLogger("bench")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--speeds", default="1.8,2.0,2.2", help="commands judged, m/s")
    p.add_argument("--runs", type=int, default=16, help="pushed runs on MuJoCo per command")
    p.add_argument("--seconds", type=float, default=30.0, help="each judged run's length")
    p.add_argument(
        "--rounds", type=int, default=DistillSettings().rounds, help="rounds of the policy's own runs"
    )
    p.add_argument("--data-runs", type=int, default=DistillSettings().runs, help="emulated runs per round")
    p.add_argument(
        "--data-seconds", type=float, default=DistillSettings().seconds, help="each emulated run's length"
    )
    p.add_argument(
        "--mujoco-every",
        type=int,
        default=DistillSettings().mujoco_every,
        help="every how many rounds the policy's own runs are gathered on MuJoCo (0: never)",
    )
    p.add_argument(
        "--members", type=int, default=DistillSettings().members, help="networks averaged in the policy"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--save-to", type=Path, help="also store the policy under this data directory (to serve it)"
    )
    p.add_argument("--quick", action="store_true", help="seconds of everything: a smoke test")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    logging.getLogger("bench").setLevel(logging.INFO)
    logging.getLogger("neuroanimator.control.runner_policy").setLevel(logging.INFO)
    speeds = [float(v) for v in args.speeds.split(",")]
    settings = DistillSettings(
        runs=args.data_runs,
        seconds=args.data_seconds,
        rounds=args.rounds,
        seed=args.seed,
        mujoco_every=args.mujoco_every,
        members=args.members,
    )
    runs, seconds = args.runs, args.seconds
    if args.quick:
        settings = DistillSettings(
            runs=4, seconds=1.0, rounds=1, epochs=1, hidden=(32,), members=args.members, seed=args.seed
        )
        runs, seconds = 4, 1.0
    path = registry.resolve(REPO / "artifacts", "runner")
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    with torch_threads(1):
        result = distill(path, settings)
        log.info(
            "runner-run: learned in %.0f s from %d emulated super-steps", result.wall_s, result.emulated_steps
        )
        t0 = time.perf_counter()
        ours = [judge(model, manifest.substeps, result.policy, v, runs, seconds, args.seed) for v in speeds]
        step = emulator_step(OnnxEmulator(path / registry.ONNX_FILE, threads=1))
        drift = root_drift(model, step, manifest.substeps, result.policy, seed=args.seed)
    theirs = [judge(model, manifest.substeps, None, v, runs, seconds, args.seed) for v in speeds]
    judged_s = time.perf_counter() - t0
    print(
        f"runner {path.name}: policy learned in {result.wall_s:.0f} s ({result.emulated_steps:,} emulated super-steps)"
    )
    print("| command m/s | policy: up | met | mean speed | controller: up | met | mean speed |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for a, b in zip(ours, theirs, strict=True):
        print(
            f"| {a['speed']} | {a['up']}/{a['runs']} | {a['met']}/{a['runs']} | {a['mean_speed']} | "
            f"{b['up']}/{b['runs']} | {b['met']}/{b['runs']} | {b['mean_speed']} |"
        )
    row: dict[str, Any] = {
        "task": "runner-run",
        "emulator": path.name,
        "success_physics": round(sum(r["met"] for r in ours) / sum(r["runs"] for r in ours), 4),
        "up_physics": round(sum(r["up"] for r in ours) / sum(r["runs"] for r in ours), 4),
        "commands": ours,
        "controller": {
            "success_physics": round(sum(r["met"] for r in theirs) / sum(r["runs"] for r in theirs), 4),
            "commands": theirs,
        },
        # the pelvis's distance between the emulator and MuJoCo 1 s after 10 starts under the policy
        "root_drift_1s_m": round(drift, 3),
        "rounds": result.rounds,
        "kept_round": result.kept_round,  # the round whose runs the kept policy drove (0: the last fit)
        "emulated_steps": result.emulated_steps,
        "mujoco_steps": result.mujoco_steps,  # the policy's own MuJoCo runs (the judging's not counted)
        "wall_s": round(result.wall_s, 1),
        "judged_s": round(judged_s, 1),
        "settings": {
            "rounds": settings.rounds,
            "runs": settings.runs,
            "seconds": settings.seconds,
            "seed": settings.seed,
            "mujoco_every": settings.mujoco_every,
            "members": settings.members,
        },
    }
    if args.save_to is not None:
        metrics = PolicyMetrics(
            success_physics=row["success_physics"],
            evaluate_runs=sum(r["runs"] for r in ours),
            mujoco_steps=result.mujoco_steps,
            iterations=len(result.rounds),
            wall_s=round(result.wall_s, 2),
        )
        roots = registry.Roots(args.save_to, REPO / "artifacts")
        starts = session_starts(model)
        stored = save_commanded_policy(roots, RUNNER_RUN, result.policy, manifest, metrics, starts=starts)
        row["stored"] = str(stored)
        log.info("runner-run: stored in %s", row["stored"])
    print(
        f"\nsuccess on MuJoCo: policy {row['success_physics']:.2f}, controller {row['controller']['success_physics']:.2f}"
    )
    if args.json:
        print(json.dumps({"tasks": [row]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
