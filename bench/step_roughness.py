"""How smooth a model's super-step is: the part of its one-step map that jumps within tiny moves.

    python bench/step_roughness.py SOURCE --substeps N [--examples 2000] [--scales 1e-4,3e-4,1e-3,3e-3]
        [--like 400000] [--json]

SOURCE is a catalog model's name or an MJCF (a file, a model folder or an archive), as ``neuro train``
takes them. The script draws held-out super-steps as ``neuro train`` draws the test set of a
training set of ``--like`` examples (whole runs of its horizon under typical controls, an independent
seed), moves each start by +r and −r of every state variable's spread along one random direction per
example, simulates the three starts under the same held controls, and reports for each scale r the second difference of the state's change over the
super-step,

    roughness(r) = Σ ‖Δ(s + δ) + Δ(s − δ) − 2 Δ(s)‖² / 4  /  Σ ‖Δ(s) − mean Δ‖²,

on the scale of the one-step relative error (each state variable's change divided by its standard
deviation). Where the map is smooth at scale r the second difference falls as r⁴ (a tenth of r, a
ten-thousandth of it); where it bends sharply, as r²; where it jumps, not at all. The slope between
scales, printed as the exponent, says which. The roughness at a scale is about the share of the
variance that an emulator smooth over moves of that size would miss; the column without the roughest
1% of the starts says whether a few jumps hold it or many.

What it is for: to see where a model's super-step is hard before training, or after a refusal. It
measures the map, not a network, and small moves only: a map smooth at these scales can still be hard
to learn at the data's spacing (dm_control's finger: smooth here, 0.03 one-step). Measured on the suite
(BENCHMARKS.md): the hopper's and the walker's super-steps jump at moves of 1e-4 of the spread, in many
starts, where the cartpole's, the reacher's and the finger's are smooth; the hopper simulated at a tenth
of its physical step over the same 0.05 s is several times smoother, so most of its jumps are a
contact that starts one physical step earlier or later. With ``--json`` the last line is one JSON
object with the same numbers.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from neuroanimator import catalog
from neuroanimator.core.state import QUATERNION_KINDS
from neuroanimator.sim import sampling
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import PhysicalModel

SCALES = (1e-4, 3e-4, 1e-3, 3e-3)
LIKE = 400_000  # about what `neuro train --mjcf` trains a model of one's own on (10 × 41,000 weights)
SEED = 7_000_003  # the held-out draw: independent of every training seed


def load(source: str) -> PhysicalModel:
    """A catalog model by name, else an MJCF file, folder or archive."""
    if source in catalog.CATALOG:
        return catalog.get(source)
    if not Path(source).exists():
        raise SystemExit(f"{source!r} is neither a catalog model ({sorted(catalog.CATALOG)}) nor a file")
    return load_mjcf(source)


def changes(model: PhysicalModel, starts: np.ndarray, ex: sampling.Examples, n: int) -> np.ndarray:
    """(B, S) change of the state over one super-step of n physical steps from each of ``starts``, under
    the examples' held controls and forces."""
    forces = ex.forces[:, None, :] if model.num_forces else None
    return model.simulate(starts, ex.controls[:, None, :], forces, nstep=n)[:, -1] - starts


def movable(model: PhysicalModel) -> np.ndarray:
    """(S,) mask of the state columns a move may touch: not a quaternion's (moved, it would leave the
    unit sphere; the attitude still moves through the angular velocity)."""
    mask = np.ones(model.state_size, dtype=bool)
    for group, sl in model.layout.group_slices():
        if group.kind in QUATERNION_KINDS:
            mask[sl] = False
    return mask


def measure(
    model: PhysicalModel, n: int, examples: int, scales: tuple[float, ...], like: int = LIKE
) -> dict[str, Any]:
    """The roughness of ``model``'s super-step of n physical steps at each scale, from ``examples``
    held-out starts drawn as a training set of ``like`` examples is (its runs' horizon: a small set's
    runs are short, all within the first seconds after a start): {"scales": [{"r", "roughness",
    "without_top_1pct", "median"}], "exponents": [...]}. ``without_top_1pct``: the same with the 1%
    roughest examples left out (a few jumps or many)."""
    ex = sampling.generate_held_out(model, n, examples, SEED, like=like, progress=False)
    s = ex.states
    base = ex.next_states - s  # the draw simulated them already (MuJoCo again gives the same to 1e-15)
    spread_dim = base.std(axis=0)
    scale_dim = np.where(spread_dim > 0, spread_dim, 1.0)
    y0 = base / scale_dim
    spread = float(((y0 - y0.mean(axis=0)) ** 2).sum())
    direction = np.random.default_rng(SEED).normal(size=s.shape) * s.std(axis=0) * movable(model)
    rows = []
    for r in scales:
        plus = changes(model, s + r * direction, ex, n) / scale_dim
        minus = changes(model, s - r * direction, ex, n) / scale_dim
        per_example = ((plus + minus - 2 * y0) ** 2).sum(axis=1) / 4  # (B,)
        ordered = np.sort(per_example)[::-1]
        rows.append(
            {
                "r": r,
                "roughness": float(per_example.sum() / spread),
                "without_top_1pct": float(ordered[len(ordered) // 100 :].sum() / spread),
                "median": float(np.median(per_example) * len(per_example) / spread),
            }
        )
    exponents = [
        math.log(b["roughness"] / a["roughness"]) / math.log(b["r"] / a["r"])
        if a["roughness"] > 0 and b["roughness"] > 0
        else None
        for a, b in itertools.pairwise(rows)
    ]
    return {
        "model": model.name,
        "substeps": n,
        "dt": model.dt,
        "super_step_s": n * model.dt,
        "examples": examples,
        "like": like,
        "scales": rows,
        "exponents": exponents,
    }


def print_report(r: dict[str, Any]) -> None:
    print(
        f"{r['model']} n={r['substeps']} (δt {r['dt']:g} s, super-step {r['super_step_s']:g} s), "
        f"{r['examples']:,} held-out starts"
    )
    print("| r | roughness | without the roughest 1% | median example | exponent to the next r |")
    print("|---|---|---|---|---|")
    for i, row in enumerate(r["scales"]):
        exp = r["exponents"][i] if i < len(r["exponents"]) else None
        print(
            f"| {row['r']:g} | {row['roughness']:.2e} | {row['without_top_1pct']:.2e} | {row['median']:.2e} | "
            f"{'–' if exp is None else f'{exp:.2f}'} |"
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", help="a catalog model's name, or an MJCF file, folder or archive")
    p.add_argument("--substeps", type=int, required=True, help="physical steps in the super-step")
    p.add_argument("--examples", type=int, default=2000, help="held-out starts (default 2000)")
    p.add_argument(
        "--scales",
        default=",".join(f"{s:g}" for s in SCALES),
        help="moves r, as fractions of each state variable's spread (default 1e-4,3e-4,1e-3,3e-3)",
    )
    p.add_argument(
        "--like",
        type=int,
        default=LIKE,
        help=f"draw the starts as a training set of this many examples is (default {LIKE:,})",
    )
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.substeps < 1:
        p.error(f"--substeps must be positive, got {args.substeps}")
    if args.examples < 100:
        p.error(f"--examples must be at least 100 (its 1% is left out), got {args.examples}")
    try:
        scales = tuple(sorted(float(x) for x in args.scales.split(",")))
    except ValueError:
        p.error(f"--scales must be comma-separated numbers, got {args.scales!r}")
    if not scales or scales[0] <= 0:
        p.error(f"--scales must be positive, got {args.scales!r}")
    report = measure(load(args.source), args.substeps, args.examples, scales, args.like)
    print_report(report)
    if args.json:
        print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
