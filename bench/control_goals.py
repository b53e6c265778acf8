"""Controllers for goals drawn at random, not only the built-in tasks' own.

    python bench/control_goals.py [--seed 0] [--goals 20] [--tasks a,b] [--starts 4]
                                  [--global-generations 3] [--gauss-newton 20]
                                  [--success-margin W] [--quick]
                                  [--artifacts artifacts] [--json]

Per task, ``--goals`` goals are drawn with ``--seed`` (numpy's default generator, one stream per
task) in these ranges, each run as the task with only its target moved (same start, horizon,
weights and success checks, which follow the target):

- truck-parking: a target position uniform in ±15 m in x and y, any heading (uniform in ±π), at rest;
- lander-landing: a pad uniform in ±10 m in x and y on the ground (z = 0), upright, with the task's
  small downward speed;
- pendulum-swing: every joint angle uniform in ±π, at rest.

Each job runs through ``run_job`` (one torch thread) and reports: success on the emulator, on
MuJoCo for the controller found on the emulator alone (``emulator_phase``) and for the controller
returned after physics refinement; whether the job called the goal reachable; iterations,
emulator rollouts (every trajectory the emulator scored: global search, every start, line-search
candidates, gradients), wall time and the final errors on both, with their median and worst.
``--starts 1 --global-generations 0`` runs the single-start descent alone, for comparison, and
``--gauss-newton 0`` leaves out the Levenberg-Marquardt updates after a descent that misses.

Prints a table; with ``--json`` the last line is one JSON object
``{"seed", "goals", "settings", "tasks": [{"task", "success_emulator", "success_physics_emulator_only",
"success_physics", "reachable", "iterations", "emulator_rollouts", "wall_s", "final_error_emulator",
"final_error_physics", "jobs": [...]}]}``, each statistic ``{"median", "worst"}`` or a count.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator.catalog.tasks import TASKS
from neuroanimator.control.job import run_job

log = logging.getLogger("bench.control_goals")
GOAL_TASKS = ("pendulum-swing", "lander-landing", "truck-parking")  # the tasks with a goal range
TRUCK_RANGE_M = 15.0
LANDER_RANGE_M = 10.0


def draw_target(task: str, rng: np.random.Generator) -> list[float]:
    """One random goal state for a built-in task (ranges in the module docstring)."""
    target = list(TASKS[task].target_state)
    if task == "truck-parking":
        x, y = rng.uniform(-TRUCK_RANGE_M, TRUCK_RANGE_M, 2)
        return [float(x), float(y), float(rng.uniform(-math.pi, math.pi)), 0.0, 0.0, 0.0]
    if task == "lander-landing":
        x, y = rng.uniform(-LANDER_RANGE_M, LANDER_RANGE_M, 2)
        target[0:3] = [float(x), float(y), 0.0]
        return target
    if task == "pendulum-swing":
        return [float(a) for a in rng.uniform(-math.pi, math.pi, 3)] + [0.0, 0.0, 0.0]
    raise ValueError(f"no goal range for task {task!r}")


def stats(values: list[Any], worst: str = "max") -> dict[str, float | None]:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return {"median": None, "worst": None}
    return {
        "median": round(statistics.median(finite), 4),
        "worst": round(max(finite) if worst == "max" else min(finite), 4),
    }


def bench_task(task: str, args: argparse.Namespace) -> dict[str, Any]:
    rng = np.random.default_rng([args.seed, list(TASKS).index(task)])
    optimizer: dict[str, int] = {
        "starts": args.starts,
        "global_generations": args.global_generations,
        "gauss_newton_iterations": args.gauss_newton,
    }
    if args.quick:
        optimizer |= {"max_iterations": 5, "global_generations": min(1, args.global_generations)}
        optimizer |= {"gauss_newton_iterations": min(2, args.gauss_newton)}
        optimizer |= {"physics_rounds": 1}
    extra: dict[str, Any] = {}
    if args.success_margin > 0:
        extra["terms"] = [
            *map(dict, TASKS[task].terms),
            {"term": "success_margin", "weight": args.success_margin},
        ]
    jobs = []
    for i in range(args.goals):
        target = draw_target(task, rng)
        r = run_job(
            {"task": task, "target_state": target, "optimizer": optimizer, **extra}, Path(args.artifacts)
        )
        assert r.emulator_phase is not None and r.refinement is not None
        jobs.append(
            {
                "goal": i,
                "target_state": [round(v, 4) for v in target],
                "stop": r.stop,
                "success_emulator": bool(r.success_emulator),
                "success_physics_emulator_only": bool(r.emulator_phase.success_physics),
                "success_physics": bool(r.success_physics),
                "reachable": r.reachable,
                "reachability": r.reachability,
                "iterations": r.iterations,
                "refinement_iterations": r.refinement.iterations,
                "emulator_rollouts": r.emulator_rollouts,
                "wall_s": r.wall_s,
                "final_error_emulator": r.final_error_emulator,
                "final_error_physics": r.final_error_physics,
                "final_error_physics_emulator_only": r.emulator_phase.final_error_physics,
                "chosen_start": r.search.chosen if r.search else None,
                "gauss_newton_iterations": r.gauss_newton.iterations if r.gauss_newton else 0,
            }
        )
        log.info("%s goal %d: %s", task, i, jobs[-1])

    def count(key: str) -> int:
        return sum(1 for j in jobs if j[key])

    return {
        "task": task,
        "goals": len(jobs),
        "success_emulator": count("success_emulator"),
        "success_physics_emulator_only": count("success_physics_emulator_only"),
        "success_physics": count("success_physics"),
        "reachable": count("reachable"),
        "iterations": stats([j["iterations"] for j in jobs]),
        "emulator_rollouts": stats([j["emulator_rollouts"] for j in jobs]),
        "wall_s": stats([j["wall_s"] for j in jobs]),
        "final_error_emulator": stats([j["final_error_emulator"] for j in jobs]),
        "final_error_physics": stats([j["final_error_physics"] for j in jobs]),
        "final_error_physics_emulator_only": stats([j["final_error_physics_emulator_only"] for j in jobs]),
        "jobs": jobs,
    }


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| task | goals | success emulator | MuJoCo, emulator-only controller | MuJoCo, refined | "
        "iterations median / worst | emulator rollouts median / worst | wall s median / worst | "
        "final error MuJoCo median / worst |"
    )
    lines = [head, "|" + "---|" * 9]
    for r in rows:

        def mw(key: str, r: dict[str, Any] = r) -> str:
            return f"{r[key]['median']} / {r[key]['worst']}"

        lines.append(
            f"| {r['task']} | {r['goals']} | {r['success_emulator']} | {r['success_physics_emulator_only']} | "
            f"{r['success_physics']} | {mw('iterations')} | {mw('emulator_rollouts')} | {mw('wall_s')} | "
            f"{mw('final_error_physics')} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--goals", type=int, default=20, help="goals per task")
    p.add_argument("--tasks", default=",".join(GOAL_TASKS))
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--starts", type=int, default=4, help="the jobs' optimizer.starts")
    p.add_argument("--global-generations", type=int, default=3, help="the jobs' optimizer.global_generations")
    p.add_argument(
        "--gauss-newton",
        type=int,
        default=20,
        help="the jobs' optimizer.gauss_newton_iterations (0: descent alone)",
    )
    p.add_argument(
        "--success-margin",
        type=float,
        default=0.0,
        help="add a success_margin term of this weight to every job (0: the task's own terms)",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="5 iterations, 1 generation, 2 Levenberg-Marquardt updates: a smoke test",
    )
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    rows = []
    for name in args.tasks.split(","):
        if name not in GOAL_TASKS:
            p.error(f"no goal range for task {name!r}; tasks are {list(GOAL_TASKS)}")
        rows.append(bench_task(name, args))
        print(f"{name}: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    print(table(rows))
    if args.json:
        settings = {
            "starts": args.starts,
            "global_generations": args.global_generations,
            "gauss_newton_iterations": args.gauss_newton,
            "success_margin": args.success_margin,
            "quick": args.quick,
        }
        print(json.dumps({"seed": args.seed, "goals": args.goals, "settings": settings, "tasks": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
