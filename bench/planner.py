"""The sampling planner through the emulator (``control/planner.py``) on one of dm_control's suite
tasks, and the policy copied from it (``control/planner_copy.py``), on the held-out episodes of
``bench/policies.py``.

    python bench/planner.py [--task acrobot-swingup] [--artifacts DIR] [--episodes 10]
                            [--horizon 3.0] [--samples 256] [--iterations 3] [--shaping 0.3]
                            [--copy-seconds 0] [--copy-rounds R] [--quick] [--json]

1. the task's emulator at its control period (found in ``--artifacts`` or trained, as
   ``bench/policies.py`` trains it);
2. ``planner``: the planner drives the held-out episodes on MuJoCo (``HELD_OUT_SEED``), planning
   through the emulator at every super-step: the suite's return (a ceiling for a policy copied from
   it) and the wall time;
3. with ``--copy-seconds S``: a reward policy trained for S seconds with the planner as its teacher
   (``RewardSettings(teacher="planner")``; ``--copy-rounds R``: R rounds of copying, then the
   actor-critic from the copy), judged on the same episodes: ``copy``.

Prints a table; with ``--json`` the last line is one JSON object ``{"task", "emulator", "planner":
{"settings", "return_physics", "returns", "wall_s"}, "copy": {"return_physics", "returns",
"history", "mujoco_steps", "wall_s"} | null}``. ``--quick``: two short episodes, a small search.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _suite import HELD_OUT_SEED, emulator_for

from neuroanimator.artifacts import registry
from neuroanimator.control.planner import PlannerSettings
from neuroanimator.control.planner_copy import CopySettings, PlannerCopy
from neuroanimator.control.reward_policy import (
    RewardSettings,
    RewardTrainer,
    draw_starts,
    run_on_mujoco,
)
from neuroanimator.control.suite_tasks import SUITE_TASKS

log = logging.getLogger("bench.planner")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="acrobot-swingup", choices=sorted(SUITE_TASKS))
    p.add_argument("--artifacts", default=None, help="where the task's emulator is found or trained")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--horizon", type=float, default=PlannerSettings.horizon_s, help="seconds searched ahead")
    p.add_argument("--samples", type=int, default=PlannerSettings.samples)
    p.add_argument("--iterations", type=int, default=PlannerSettings.iterations)
    p.add_argument("--shaping", type=float, default=PlannerSettings.shaping)
    p.add_argument("--copy-seconds", type=float, default=0.0, help="train a policy copying the planner")
    p.add_argument("--copy-rounds", type=int, default=None, help="rounds of copying, then the actor-critic")
    p.add_argument("--quick", action="store_true", help="two short episodes, a small search: a smoke test")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", stream=sys.stderr)
    torch.set_num_threads(1)

    task = SUITE_TASKS[args.task]
    episodes = args.episodes
    settings = PlannerSettings(
        horizon_s=args.horizon, samples=args.samples, iterations=args.iterations, shaping=args.shaping
    )
    if args.quick:
        task = dataclasses.replace(task, episode_steps=min(task.episode_steps, 60))
        episodes = 2
        settings = dataclasses.replace(settings, horizon_s=min(args.horizon, 0.4), samples=16, iterations=2)
    root = Path(args.artifacts) if args.artifacts else registry.writable(registry.Roots.default())
    path, _, _, _ = emulator_for(task, root, 60.0 if args.quick else task.emulator_seconds)

    copying = CopySettings(planner=settings, rounds=args.copy_rounds, episodes=2 if args.quick else 8)
    trainer = RewardTrainer(task, path, RewardSettings(seconds=max(args.copy_seconds, 1.0), teacher="planner",
                                                       copying=copying))  # fmt: skip
    planner = PlannerCopy(trainer).planner
    starts, params = draw_starts(task, trainer.physical, np.random.default_rng(HELD_OUT_SEED), episodes)
    t0 = time.perf_counter()
    planned = run_on_mujoco(task, trainer.physical, trainer.ctx, planner.act, starts, params)
    planner_wall = time.perf_counter() - t0
    row: dict[str, Any] = {
        "task": task.name,
        "emulator": str(path),
        "planner": {
            "settings": dataclasses.asdict(settings),
            "return_physics": planned.mean,
            "returns": [round(float(r), 1) for r in planned.returns],
            "wall_s": round(planner_wall, 1),
        },
        "copy": None,
    }
    log.info(
        "%s: the planner on MuJoCo %.1f over %d episodes (%.0f s)",
        task.name,
        planned.mean,
        episodes,
        planner_wall,
    )
    if args.copy_seconds > 0:
        t0 = time.perf_counter()
        trainer.t0 = t0  # the copy's budget starts now, not when the planner above began
        result = trainer.train()
        copied = run_on_mujoco(task, trainer.physical, trainer.ctx, result.policy.act, starts, params)
        row["copy"] = {
            "return_physics": copied.mean,
            "returns": [round(float(r), 1) for r in copied.returns],
            "history": [list(h) for h in result.return_history],
            "mujoco_steps": result.mujoco_steps,
            "wall_s": round(time.perf_counter() - t0, 1),
        }
        log.info(
            "%s: the policy copied from it on MuJoCo %.1f (%.0f s)", task.name, copied.mean, result.wall_s
        )
    print(f"{'':18} {'return on MuJoCo':>17} {'wall s':>7}  episodes")
    print(f"{'planner':18} {planned.mean:17.1f} {planner_wall:7.0f}  {row['planner']['returns']}")
    if row["copy"] is not None:
        c = row["copy"]
        print(f"{'policy (copied)':18} {c['return_physics']:17.1f} {c['wall_s']:7.0f}  {c['returns']}")
    if args.json:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
