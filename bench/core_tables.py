"""Run ``neuro eval`` and ``neuro bench`` for every catalog model and print the BENCHMARKS.md tables.

    python bench/core_tables.py [--artifacts DIR] [--models a,b] [--no-save] [--json]

Each model's results are also saved as ``<artifacts>/<model>/eval.json`` and ``bench.json`` (the
dashboard's error plot and speed table read them). With ``--json`` the last line is one JSON object:
{"eval": {model: ...}, "bench": {model: ...}}.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from neuroanimator import physics


def _neuro(*args: str) -> dict[str, Any]:
    out = subprocess.run(
        [sys.executable, "-m", "neuroanimator.cli", *args, "--json"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    result: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    return result


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--models", default=",".join(physics.CATALOG))
    p.add_argument("--no-save", action="store_true", help="do not write eval.json / bench.json")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    models = args.models.split(",")
    evals = {m: _neuro("eval", m, "--artifacts", args.artifacts) for m in models}
    benches = {m: _neuro("bench", m, "--artifacts", args.artifacts) for m in models}
    if not args.no_save:
        for m in models:
            folder = Path(args.artifacts) / m
            (folder / "eval.json").write_text(json.dumps(evals[m], indent=1) + "\n")
            (folder / "bench.json").write_text(json.dumps(benches[m], indent=1) + "\n")

    print("| model | n | one-step rel. error | linear baseline | ratio | rollout error @20 s |")
    print("|---|---|---|---|---|---|")
    for m, e in evals.items():
        for r in e["by_substeps"]:
            print(
                f"| {m} | {r['substeps']} | {r['one_step_rel_error']:.5f} | {r['linear_baseline_rel_error']:.4f}"
                f" | {r['baseline_ratio']:.0f}× | {r['rollout_error_at_20s']:.3f} |"
            )
    print()
    print("| model | n | MuJoCo 20,000 steps (s) | emulator (s) | speed-up |")
    print("|---|---|---|---|---|")
    for m, b in benches.items():
        for r in b["single"]:
            print(
                f"| {m} | {r['substeps']} | {r['physics_s']:.4f} | {r['emulator_s']:.4f} | {r['ratio']:.1f}× |"
            )
    print()
    print("| model | B | mujoco.rollout steps/s | emulator steps/s | speed-up |")
    print("|---|---|---|---|---|")
    for m, b in benches.items():
        for r in b["batched"]:
            print(
                f"| {m} | {r['batch']} | {r['physics_steps_per_s']:.3g} | {r['emulator_steps_per_s']:.3g}"
                f" | {r['ratio']:.0f}× |"
            )
    if args.json:
        print(json.dumps({"eval": evals, "bench": benches}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
