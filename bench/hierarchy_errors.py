"""Where a hierarchical emulator's error sits: each network's held-out error, the groups that hold it,
and how predictable the data are at all.

    python bench/hierarchy_errors.py [--model dolphin] [--examples 5000] [--test 2000]
        [--hidden 32] [--seconds 20] [--networks global,segment2] [--top 5] [--data FILE.npz] [--json]

It simulates ``examples + test`` super-steps at the model's default n (or reads them from ``--data``,
and writes them there when the file does not exist yet), trains each network of the hierarchy on its
own targets for ``--seconds`` (as ``neuro train`` does), and prints, per network, the held-out
one-step relative error (1 − R²) of the network and of its linear baseline, with the ``--top`` output
groups that hold most of the network's error (their share of the network's total).

Then a **full-state linear** row per kind of state group: a least-squares map from the whole state
and the controls to the change of the state, fitted on the training rows, its held-out relative
error, and the share of that error held by the worst 1% and 5% of the held-out examples. A heavy tail
(a few examples holding most of the error) points at the data, not the networks: rare transients that
typical use never meets. With ``--json`` the last line is one JSON object with the same numbers.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator import catalog
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim import sampling
from neuroanimator.training.hierarchy import _normalised, build_hierarchy, fit_network, network_data
from neuroanimator.training.train import apply_linear, relative_error, to_tensors

log = logging.getLogger("hierarchy_errors")


def _examples(model: catalog.PhysicalModel, count: int, seed: int, path: Path | None) -> sampling.Examples:
    if path is not None and path.exists():
        z = np.load(path)
        return sampling.Examples(z["s"], z["u"], z["f"], z["n"])
    t0 = time.perf_counter()
    ex = sampling.generate(model, model.spec.substeps, count, seed)
    log.info("simulated %d examples in %.0f s", count, time.perf_counter() - t0)
    if path is not None:
        np.savez(path, s=ex.states, u=ex.controls, f=ex.forces, n=ex.next_states)
    return ex


def _group_shares(
    net: StructuredEmulator, pred: torch.Tensor, y: torch.Tensor, top: int
) -> list[dict[str, Any]]:
    """The output groups holding most of the network's squared error, as shares of its total."""
    total = float(((y - y.mean(dim=0)) ** 2).sum())
    rows: list[dict[str, Any]] = []
    at = 0
    for g in net.layout:
        sl = slice(at, at + g.size)
        rows.append({"group": g.name, "share": float(((pred[:, sl] - y[:, sl]) ** 2).sum()) / total})
        at += g.size
    if at != y.shape[1]:  # a layout whose outputs this count does not follow: no breakdown
        return []
    return sorted(rows, key=lambda r: -float(r["share"]))[:top]


def full_state_linear(model: catalog.PhysicalModel, ex: sampling.Examples, n_test: int) -> dict[str, Any]:
    """Per kind of state group: the held-out error of a least-squares map (state, controls) -> change,
    and the share of it in the worst 1% and 5% of examples."""
    s, u, nx = ex.states, ex.controls, ex.next_states
    x = np.hstack([s, u, np.ones((len(s), 1))])
    y = nx - s
    test, train = slice(0, n_test), slice(n_test, None)
    w = np.linalg.lstsq(x[train], y[train], rcond=1e-8)[0]
    sd = y[train].std(axis=0) + 1e-12
    res = (y[test] - x[test] @ w) / sd
    kinds: dict[str, list[int]] = {}
    for g, sl in model.layout.group_slices():
        kind = f"{g.kind}:{g.name.rsplit('.', 1)[-1]}" if "." in g.name else g.kind
        kinds.setdefault(kind, []).extend(range(sl.start, sl.stop))
    out = {}
    for kind, cols in kinds.items():
        per_example = (res[:, cols] ** 2).sum(axis=1)
        worst = np.sort(per_example)[::-1]
        spread = (((y[test][:, cols] - y[test][:, cols].mean(axis=0)) / sd[cols]) ** 2).sum()
        k1, k5 = max(1, n_test // 100), max(1, n_test // 20)
        out[kind] = {
            "rel_error": float(worst.sum() / spread),
            "worst_1pct_share": float(worst[:k1].sum() / worst.sum()),
            "worst_5pct_share": float(worst[:k5].sum() / worst.sum()),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="dolphin")
    ap.add_argument("--examples", type=int, default=5000)
    ap.add_argument("--test", type=int, default=2000)
    ap.add_argument("--hidden", default="32")
    ap.add_argument("--seconds", type=float, default=20.0, help="training seconds per network")
    ap.add_argument("--networks", default="", help="comma-separated names (default: all)")
    ap.add_argument("--top", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--data", type=Path, default=None, help=".npz to read the examples from, or write them to"
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    model = catalog.get(args.model)
    ex = _examples(model, args.examples + args.test, args.seed, args.data)
    cfg = TrainConfig(
        substeps=model.spec.substeps,
        hidden=tuple(int(h) for h in args.hidden.split(",")),
        max_seconds=args.seconds,
        rollout_steps=0,
        progress=False,
        examples=args.examples,
        seed=args.seed,
    ).resolved()
    torch.manual_seed(args.seed)
    emu = build_hierarchy(model, cfg)
    s, u, _, nxt = to_tensors(ex)
    assert u is not None, "a hierarchy's model has controls"
    test, train = slice(0, args.test), slice(args.test, None)
    wanted = set(args.networks.split(",")) - {""}
    rows: list[dict[str, Any]] = []
    for (name, net), d_train, d_test in zip(
        emu.networks,
        network_data(emu, s[train], u[train], nxt[train]),
        network_data(emu, s[test], u[test], nxt[test]),
        strict=True,
    ):
        if wanted and name not in wanted:
            continue
        linear, _ = fit_network(net, d_train, cfg)
        x, y = _normalised(net, d_test)
        with torch.no_grad():
            pred = net.network(x)
            row = {
                "network": name,
                "one_step_rel_error": relative_error(pred, y),
                "linear_baseline_rel_error": relative_error(apply_linear(linear, x), y),
                "worst_groups": _group_shares(net, pred, y, args.top),
            }
        rows.append(row)
        log.info("%s: %.4f (linear %.4f)", name, row["one_step_rel_error"], row["linear_baseline_rel_error"])
    lin = full_state_linear(model, ex, args.test)

    print(f"\n{model.name}: {args.examples} examples, {args.test} held out, n = {model.spec.substeps}")
    print("| network | one-step | linear | worst groups (share of the network's error) |")
    print("|---|---|---|---|")
    for r in rows:
        groups = ", ".join(f"{g['group']} {g['share']:.4f}" for g in r["worst_groups"])
        print(
            f"| {r['network']} | {r['one_step_rel_error']:.4f} | {r['linear_baseline_rel_error']:.4f} | {groups} |"
        )
    print("\n| state groups | full-state linear | worst 1% of examples | worst 5% |")
    print("|---|---|---|---|")
    for kind, v in lin.items():
        print(
            f"| {kind} | {v['rel_error']:.4f} | {v['worst_1pct_share']:.2f} | {v['worst_5pct_share']:.2f} |"
        )
    if args.json:
        print(
            json.dumps(
                {
                    "model": model.name,
                    "examples": args.examples,
                    "test": args.test,
                    "substeps": model.spec.substeps,
                    "networks": rows,
                    "full_state_linear": lin,
                }
            )
        )


if __name__ == "__main__":
    main()
