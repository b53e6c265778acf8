"""How long the runner's emulated running loop stays up, over many starts, against MuJoCo's.

    python bench/runner_falls.py [--artifacts artifacts] [--runs 16] [--seconds 30] [--json]

One emulated run says little: the closed loop (the running controller reading the emulated state every
super-step, ``runner_control.run_emulated``) is chaotic, and outputs that differ by 1e-6 fall seconds
apart. So each case starts ``--runs`` runs from the same running stride (``runner_control.running_start``)
with every velocity perturbed by N(0, 0.01) (m/s, rad/s), and reports the median, least and most time
each stays up (a run that never falls counts as ``--seconds``) and how many stay up the whole time, for
the emulator (the latest ``runner`` artifact) and for MuJoCo (``runner_control.run``, the controller
every super-step on kinematic sensors, as on the emulator). Cases: a target speed in the training
data, one that is not (``runner_data.UNSEEN_SPEED``), and the first pushed sideways at 5 s (not a push
of the training runs, whose pushes come at random times, directions and sizes up to 300 N). With
``--json`` the last line is one JSON object with every number.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from neuroanimator.artifacts import registry
from neuroanimator.catalog.runner import data as runner_data
from neuroanimator.catalog.runner import gait as rc
from neuroanimator.export.runtime import OnnxEmulator

log = logging.getLogger("runner_falls")
TRAINED_SPEED = 2.2
PUSH = rc.Push(force=(0.0, 250.0, 0.0), start_s=5.0, duration_s=0.2)  # 50 N·s; data: random pushes ≤ 300 N
VELOCITY_NOISE = 0.01


def _summary(times: np.ndarray, seconds: float) -> dict[str, Any]:
    up = np.minimum(times, seconds)
    return {
        "median_s": float(np.median(up)),
        "min_s": float(up.min()),
        "max_s": float(up.max()),
        "up_whole_run": int(np.sum(up >= seconds)),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--artifacts", type=Path, default=Path("artifacts"))
    p.add_argument("--runs", type=int, default=16)
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    path = registry.resolve(args.artifacts, "runner")
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    m = model.mj_model
    onnx = OnnxEmulator(path / registry.ONNX_FILE, threads=2)

    def step(s: np.ndarray, u: np.ndarray, f: np.ndarray) -> np.ndarray:
        out = onnx.step(s.astype(np.float32), u.astype(np.float32), f.astype(np.float32), validate=False)
        return np.asarray(out, dtype=np.float64)

    rng = np.random.default_rng(args.seed)
    cases = [
        ("a speed in the data", TRAINED_SPEED, None),
        ("a speed not in the data", runner_data.UNSEEN_SPEED, None),
        ("a push not in the data", TRAINED_SPEED, PUSH),
    ]
    rows = []
    for name, speed, push in cases:
        start = rc.perturbed_starts(m, speed, args.runs, rng, VELOCITY_NOISE)
        emu = rc.run_emulated(model, step, manifest.substeps, start, speed, args.seconds, push=push)
        ref = rc.run(
            m,
            start,
            speed,
            args.seconds,
            control_every=manifest.substeps,
            kinematic=True,
            push=push,
            record=False,
        )
        e, mj = _summary(emu.fell_at, args.seconds), _summary(ref.fell_at, args.seconds)
        push_info = None if push is None else {"force": list(push.force), "start_s": push.start_s}
        rows.append({"case": name, "target_speed": speed, "push": push_info, "emulator": e, "mujoco": mj})
        log.info(
            "%s (%.1f m/s): emulator up %.1f s median (%.1f-%.1f), %d of %d for %g s; MuJoCo %d of %d",
            name, speed, e["median_s"], e["min_s"], e["max_s"], e["up_whole_run"], args.runs, args.seconds,
            mj["up_whole_run"], args.runs,
        )  # fmt: skip
    if args.json:
        print(
            json.dumps(
                {"version": manifest.version, "runs": args.runs, "seconds": args.seconds, "cases": rows}
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
