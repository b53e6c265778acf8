"""Run ``neuro eval`` and ``neuro bench`` for every catalog model and print the BENCHMARKS.md tables.

    python bench/core_tables.py [--artifacts DIR] [--models a,b] [--no-save] [--json]

Each version's results are also saved in its folder, ``<artifacts>/<model>/<version>/eval.json`` and
``bench.json`` (``neuro eval --save``, ``neuro bench --save``; the dashboard's error plot and speed
table read them). With ``--json`` the last line is one JSON object: {"eval": {model: ...}, "bench":
{model: ...}}, each model's as ``neuro eval --json`` and ``neuro bench --json`` print it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

from neuroanimator import catalog
from neuroanimator.core.results import ModelBench, ModelEval


def _neuro(*args: str) -> str:
    """The last line of a ``neuro ... --json`` run: its JSON result."""
    out = subprocess.run(
        [sys.executable, "-m", "neuroanimator.cli", *args, "--json"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return out.strip().splitlines()[-1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--models", default=",".join(catalog.CATALOG))
    p.add_argument("--no-save", action="store_true", help="do not write the versions' eval.json / bench.json")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    models = args.models.split(",")
    save = [] if args.no_save else ["--save"]
    evals = {
        m: ModelEval.model_validate_json(_neuro("eval", m, "--artifacts", args.artifacts, *save))
        for m in models
    }
    benches = {
        m: ModelBench.model_validate_json(_neuro("bench", m, "--artifacts", args.artifacts, *save))
        for m in models
    }

    print("| model | n | one-step rel. error | linear baseline | ratio | rollout error @20 s |")
    print("|---|---|---|---|---|---|")
    for m, e in evals.items():
        for r in e.by_substeps:
            print(
                f"| {m} | {r.substeps} | {r.one_step_rel_error:.5f} | {r.linear_baseline_rel_error:.4f}"
                f" | {r.baseline_ratio:.0f}× | {r.rollout_error_at_20s:.3f} |"
            )
    print()
    print("| model | n | MuJoCo 20,000 steps (s) | emulator (s) | speed-up |")
    print("|---|---|---|---|---|")
    for m, b in benches.items():
        for s in b.single:
            print(f"| {m} | {s.substeps} | {s.physics_s:.4f} | {s.emulator_s:.4f} | {s.ratio:.1f}× |")
    print()
    print("| model | B | mujoco.rollout steps/s | emulator steps/s | speed-up |")
    print("|---|---|---|---|---|")
    for m, b in benches.items():
        for row in b.batched:
            print(
                f"| {m} | {row.batch} | {row.physics_steps_per_s:.3g} | {row.emulator_steps_per_s:.3g} | {row.ratio:.0f}× |"
            )
    if args.json:
        out = {
            "eval": {m: e.model_dump(mode="json") for m, e in evals.items()},
            "bench": {m: b.model_dump(mode="json") for m, b in benches.items()},
        }
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
