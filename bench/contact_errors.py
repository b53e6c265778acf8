"""Where a trained emulator's one-step error sits with respect to contact.

    python bench/contact_errors.py MODEL [--artifacts artifacts] [--substeps N] [--examples 4000] [--json]

It draws ``--examples`` fresh held-out super-steps of the emulator's model (the seed its training held
out), simulates each one's physical steps again to see its contacts, and sorts the examples into three
kinds: **none** (no contact at any physical step of the super-step), **always** (in contact at every
one) and **switch** (a contact starts or ends inside it). Per kind it prints the share of the examples,
the share of the emulator's squared error they hold, and the relative one-step error (1 − R²) within
them, on the normalised targets as ``neuro train`` reports it; then the share of the error held by each
output, named by the state's column it predicts (the change of that column, in the emulator's frame:
a free body's velocities in its body frame).

What it is for: a contact model's error may sit in a few examples (dm_control's finger: 8% of the
examples touch the spinner and hold 85% of the error), which says what to build next (features of the
distance between the geoms that touch), where an error spread evenly would say the network is short
of data or width. With ``--json`` the last line is one JSON object with the same numbers.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.train import held_out_examples, held_out_seed, to_tensors

log = logging.getLogger("contact_errors")
KINDS = ("none", "always", "switch")


def contact_kinds(
    model: PhysicalModel, states: np.ndarray, controls: np.ndarray, forces: np.ndarray, n: int
) -> np.ndarray:
    """(B,) kind of each super-step from (B, S) states under held (B, U) controls and (B, F) forces:
    0 none, 1 always, 2 switch (indices into ``KINDS``), from MuJoCo's contacts at each physical step."""
    traj = model.simulate(
        states, controls[:, None, :], forces[:, None, :] if model.num_forces else None, nstep=n
    )  # (B, n, S)
    m = model.mj_model
    d = mujoco.MjData(m)
    every = np.concatenate([states[:, None, :], traj], axis=1).reshape(-1, model.state_size)
    flat = np.empty(every.shape[0], dtype=bool)
    for i, row in enumerate(model.to_physics(every)):
        mujoco.mj_setState(m, d, row, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_forward(m, d)
        flat[i] = d.ncon > 0
    touching = flat.reshape(states.shape[0], n + 1)
    return np.where(~touching.any(axis=1), 0, np.where(touching.all(axis=1), 1, 2))


def measure(path: Path, examples: int) -> dict[str, Any]:
    manifest = registry.read_manifest(path)
    if manifest.emulator.parts:
        raise SystemExit(f"{path}: a hierarchy; bench/hierarchy_errors.py splits its error by network")
    model = registry.load_physical_model(path, manifest)
    n, cfg = manifest.substeps, manifest.train_config
    like = manifest.metrics.examples  # held out as the training runs were drawn
    test = held_out_examples(model, n, examples, held_out_seed(cfg.seed), False, cfg.sampler, like=like)
    emu = artifacts.load_torch(path)
    s, u, f, nxt = to_tensors(test)
    with torch.no_grad():
        y = emu.network_targets(s, nxt)
        sq = (emu.network(emu.network_inputs(s, u, f)) - y) ** 2  # (B, Y)
        spread = float(((y - y.mean(dim=0)) ** 2).sum())
    per_example = sq.sum(dim=1).numpy()
    total = float(per_example.sum())
    kinds = contact_kinds(model, test.states, test.controls, test.forces, n)
    rows = []
    for k, name in enumerate(KINDS):
        sel = kinds == k
        share = float(sel.mean())
        held = float(per_example[sel].sum())
        rows.append(
            {
                "kind": name,
                "examples_share": share,
                "error_share": held / total if total else 0.0,
                # the error of these examples against the spread of all: what the whole error would be
                # if every example were of this kind
                "rel_error_within": held / spread / share if share else None,
            }
        )
    per_output = sq.sum(dim=0).numpy()
    labels = manifest.state_labels if per_output.size == manifest.state_size else None
    outputs = {
        (labels[i] if labels else f"output{i}"): float(per_output[i] / per_output.sum())
        for i in range(per_output.size)
    }
    return {
        "model": manifest.model,
        "version": manifest.version,
        "substeps": n,
        "examples": examples,
        "one_step_rel_error": total / spread,
        "kinds": rows,
        "outputs": outputs,
    }


def print_report(r: dict[str, Any]) -> None:
    print(
        f"{r['model']} {r['version']} n={r['substeps']}: one-step relative error {r['one_step_rel_error']:.4g} "
        f"over {r['examples']:,} held-out examples"
    )
    print("| contact in the super-step | examples | error held | relative error within |")
    print("|---|---|---|---|")
    for row in r["kinds"]:
        within = "–" if row["rel_error_within"] is None else f"{row['rel_error_within']:.4g}"
        print(f"| {row['kind']} | {row['examples_share']:.1%} | {row['error_share']:.1%} | {within} |")
    top = sorted(r["outputs"].items(), key=lambda kv: -kv[1])
    print("error by output: " + ", ".join(f"{k} {v:.0%}" for k, v in top))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="the emulator's model name in the registry")
    p.add_argument("--artifacts", default="artifacts", help="the registry (default: artifacts/)")
    p.add_argument("--substeps", type=int, help="the version at this super-step (default: the latest)")
    p.add_argument("--examples", type=int, default=4000, help="held-out super-steps to draw (default 4000)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.examples < 1:
        p.error(f"--examples must be positive, got {args.examples}")
    path = registry.resolve(Path(args.artifacts), args.model, substeps=args.substeps)
    report = measure(path, args.examples)
    print_report(report)
    if args.json:
        print(json.dumps(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
