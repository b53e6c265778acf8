"""Each network of the runner's emulator on held-out runs: its one-step error, its linear baseline, and
where its error sits.

    python bench/runner_networks.py [--artifacts artifacts] [--version V] [--seeds 1,2,3]
        [--test 20000] [--fit 40000] [--json]

The training reports one held-out set (``training.held_out_seed``), and a held-out set is cut from a
few batches of 32 closed-loop runs: one set says how the emulator does on those runs. This measures
the latest ``runner`` artifact (or ``--version``) on ``--test`` transitions from the runs of each of
``--seeds`` (``runner_data.examples``, never the training's seed), and for each network prints the
held-out one-step relative error, that of a ridge map of the same inputs fitted on ``--fit``
transitions of the training's own seed (``training.network_errors``), their ratio, and the share of
the network's squared error held by the worst 1% and 10% of the examples (a heavy tail: a few
transitions, such as a foot landing inside the super-step, hold most of it). With ``--json`` the last
line is one JSON object with every number.

Shapes: N transitions, D network inputs, S state (network outputs).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator.artifacts import registry
from neuroanimator.artifacts.store import load_torch
from neuroanimator.catalog.runner import data as runner_data
from neuroanimator.emulator.articulated import ArticulatedCore, articulated_core
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.train import network_errors, to_tensors

log = logging.getLogger("runner_networks")


def _normalised(
    emu: StructuredEmulator, model: PhysicalModel, substeps: int, count: int, seed: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Network inputs (N, D) and targets (N, S), normalised, of ``count`` transitions from ``seed``'s runs."""
    s, u, f, nxt = to_tensors(runner_data.examples(model, substeps, count, seed, progress=False))
    with torch.no_grad():
        return emu.network_inputs(s, u, f), emu.network_targets(s, nxt)


def _tail_shares(core: ArticulatedCore, x: torch.Tensor, y: torch.Tensor) -> dict[str, tuple[float, float]]:
    """Per network, the shares of its squared error held by the worst 1% and 10% of the examples."""
    with torch.no_grad():
        err = (core(x) - y) ** 2
    out = {}
    for name, cols in core.output_columns().items():
        per_example = np.sort(err[:, cols].sum(dim=1).numpy())[::-1]
        share = np.cumsum(per_example) / per_example.sum()  # of the worst k + 1 examples
        n = len(per_example)
        out[name] = (float(share[max(1, n // 100) - 1]), float(share[max(1, n // 10) - 1]))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--artifacts", type=Path, default=Path("artifacts"))
    p.add_argument("--version", help="an artifact version (default: the latest)")
    p.add_argument("--seeds", default="1,2,3", help="comma-separated seeds of the held-out runs")
    p.add_argument("--test", type=int, default=20_000, help="held-out transitions per seed")
    p.add_argument("--fit", type=int, default=40_000, help="training-seed transitions for the linear maps")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    path = registry.resolve(args.artifacts, "runner", args.version)
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    emu = load_torch(path).eval()
    core = articulated_core(emu)
    if core is None:
        raise SystemExit(f"{path} is not an articulated hierarchy")
    train_seed = manifest.train_config.seed
    seeds = [int(s) for s in args.seeds.split(",")]
    if train_seed in seeds:
        raise SystemExit(f"seed {train_seed} is the training's own: choose held-out seeds")
    x_fit, y_fit = _normalised(emu, model, manifest.substeps, args.fit, train_seed)
    sets: list[dict[str, Any]] = []
    for seed in seeds:
        x, y = _normalised(emu, model, manifest.substeps, args.test, seed)
        with torch.no_grad():
            errors = network_errors(core, x_fit, y_fit, x, y)
        tails = _tail_shares(core, x, y)
        for name, e in errors.items():
            e["worst_1pct_share"], e["worst_10pct_share"] = tails[name]
        sets.append({"seed": seed, "networks": errors})
        log.info(
            "seed %d: %s", seed,
            ", ".join(f"{n} {e['one_step_rel_error']:.4f} (linear {e['linear_baseline_rel_error']:.3f})"
                      for n, e in errors.items()),
        )  # fmt: skip
    names = list(sets[0]["networks"])
    print(
        f"{'network':<10} {'error per set':<28} {'linear':<14} {'ratio':>6} {'worst 1%':>9} {'worst 10%':>10}"
    )
    summary = {}
    for name in names:
        errs = [s["networks"][name]["one_step_rel_error"] for s in sets]
        lins = [s["networks"][name]["linear_baseline_rel_error"] for s in sets]
        w1 = float(np.mean([s["networks"][name]["worst_1pct_share"] for s in sets]))
        w10 = float(np.mean([s["networks"][name]["worst_10pct_share"] for s in sets]))
        ratio = float(np.mean(lins) / np.mean(errs))
        summary[name] = {"max_error": max(errs), "mean_error": float(np.mean(errs)), "ratio": ratio}
        print(
            f"{name:<10} {', '.join(f'{e:.4f}' for e in errs):<28} {min(lins):.3f}-{max(lins):.3f}  "
            f"{ratio:>5.1f}x {w1:>8.0%} {w10:>10.0%}"
        )
    if args.json:
        print(json.dumps({"version": manifest.version, "test": args.test, "sets": sets, "summary": summary}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
