"""Where in a run a trained emulator's one-step error sits: by the time since the run's typical start.

    python bench/errors_by_time.py MODEL [--artifacts artifacts] [--substeps N] [--runs 256]
        [--seconds S] [--seed 11] [--json]

It simulates ``--runs`` fresh runs of the emulator's model as its training data were made (a typical
start, a random lead of up to 5 super-steps, then consecutive super-steps with the typical controls
held over each), ``--seconds`` long (default: the model's episode), and scores the emulator's one-step
prediction of every super-step on the normalised targets as ``neuro train`` does (1 − R², each bin's
squared error against the spread of all the runs' targets). It prints the whole runs' error and the
error of the super-steps in bins of time since the start: 0-4, 4-8, 8-16, 16-32, ... super-steps.

What it is for: a start perturbed from ``qpos0`` can ring for a second (dm_control's ball_in_cup starts
with its string past its length, the hopper falls from standing), and an error measured over the first
seconds of runs measures that transient. With ``--json`` the last line is one JSON object with the same
numbers. A hierarchy (several networks) is not scored here: ``bench/hierarchy_errors.py`` splits it.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.sim import sampling

log = logging.getLogger("errors_by_time")


def bins(horizon: int) -> list[tuple[int, int]]:
    """Super-step bins [a, b) over a run of ``horizon``: 0-4, 4-8, then doubling, the last cut at the end."""
    edges = [0, 4]
    while edges[-1] < horizon:
        edges.append(edges[-1] * 2)
    return [(a, min(b, horizon)) for a, b in itertools.pairwise(edges) if a < horizon]


def measure(path: Path, runs: int, seconds: float | None, seed: int) -> dict[str, Any]:
    manifest = registry.read_manifest(path)
    if manifest.emulator.parts:
        raise SystemExit(f"{path}: a hierarchy; bench/hierarchy_errors.py splits its error by network")
    model = registry.load_physical_model(path, manifest)
    n = manifest.substeps
    span = model.spec.episode_s if seconds is None else seconds
    horizon = max(1, round(span / (model.dt * n)))
    seq = sampling.generate_sequences(model, n, runs, horizon, seed, progress=False)
    emu = artifacts.load_torch(path)

    def rows(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(a.reshape(-1, a.shape[-1])).float()

    u = rows(seq.controls) if model.num_controls else None
    f = rows(seq.forces) if model.num_forces else None
    s, nxt = rows(seq.states[:, :-1]), rows(seq.states[:, 1:])
    with torch.no_grad():
        y = emu.network_targets(s, nxt)
        sq = ((emu.network(emu.network_inputs(s, u, f)) - y) ** 2).sum(dim=1).numpy().reshape(runs, horizon)
        spread = float(((y - y.mean(dim=0)) ** 2).sum(dim=1).mean())  # per example
    super_step_s = model.dt * n
    return {
        "model": manifest.model,
        "version": manifest.version,
        "substeps": n,
        "runs": runs,
        "super_steps": horizon,
        "one_step_rel_error": float(sq.mean() / spread),
        "bins": [
            {
                "from_s": a * super_step_s,
                "to_s": b * super_step_s,
                "one_step_rel_error": float(sq[:, a:b].mean() / spread),
            }
            for a, b in bins(horizon)
        ],
    }


def print_report(r: dict[str, Any]) -> None:
    print(
        f"{r['model']} {r['version']} n={r['substeps']}: one-step relative error {r['one_step_rel_error']:.4g} over "
        f"{r['runs']} runs of {r['super_steps']} super-steps"
    )
    print("| time since the start (s) | one-step relative error |")
    print("|---|---|")
    for b in r["bins"]:
        print(f"| {b['from_s']:.2f}-{b['to_s']:.2f} | {b['one_step_rel_error']:.4g} |")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="the emulator's model name in the registry")
    p.add_argument("--artifacts", default="artifacts", help="the registry (default: artifacts/)")
    p.add_argument("--substeps", type=int, help="the version at this super-step (default: the latest)")
    p.add_argument("--runs", type=int, default=256, help="fresh runs to simulate (default 256)")
    p.add_argument("--seconds", type=float, help="length of each run (default: the model's episode)")
    p.add_argument("--seed", type=int, default=11, help="the runs' seed (default 11)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.runs < 1:
        p.error(f"--runs must be positive, got {args.runs}")
    if args.seconds is not None and not args.seconds > 0:
        p.error(f"--seconds must be positive, got {args.seconds}")
    path = registry.resolve(Path(args.artifacts), args.model, substeps=args.substeps)
    report = measure(path, args.runs, args.seconds, args.seed)
    print_report(report)
    if args.json:
        print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
