"""How well an emulator holds its model's operating point: emulator and MuJoCo side by side from it.

    python bench/operating_point.py ARTIFACT_DIR [--seconds 10] [--push 0] [--json]

ARTIFACT_DIR is one version's folder (``neuro train ... --json`` prints it as ``artifact``). From the
model's first operating state (its keyframe, or ``qpos0`` where the controls that hold it still were
found), with a velocity push of ``--push`` (m/s or rad/s on every velocity) and that point's controls held,
the served emulator (ONNX Runtime) and MuJoCo each step for ``--seconds``; the table gives the gap
between their root positions (m; the first three state values of a free root) and their largest state
gap, by time, and how far MuJoCo itself moved. What it is for: a drone hovering in the Playground, an arm
holding a pose. With ``--json`` the last line is one JSON object with the same numbers.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from neuroanimator.artifacts.registry import load_physical_model, read_manifest
from neuroanimator.export.runtime import OnnxEmulator

log = logging.getLogger("bench.operating_point")


def side_by_side(folder: Path, seconds: float, push: float) -> dict[str, object]:
    """The gaps between the emulator and MuJoCo from the operating point (see the module doc)."""
    manifest = read_manifest(folder)
    model = load_physical_model(folder, manifest)
    op = manifest.spec.operating
    if op is None or not op.control_centres or not model.spec.initial.centres:
        raise SystemExit(
            f"{manifest.model}: trained without an operating point (a catalog model, or none found)"
        )
    start = np.asarray(model.spec.initial.centres[0], dtype=np.float64)[None]
    for g, sl in model.layout.group_slices():
        if g.source == "qvel":
            start[0, sl] += push
    controls = np.asarray(op.control_centres[0], dtype=np.float64)[None]
    forces = np.zeros((1, model.num_forces), dtype=np.float32)
    emulator = OnnxEmulator(folder / "emulator.onnx")
    n = manifest.substeps
    steps = max(1, round(seconds / (n * model.dt)))
    emulated, simulated = start.astype(np.float32), start.copy()
    rows = []
    for k in range(1, steps + 1):
        emulated = emulator.step(emulated, controls.astype(np.float32), forces)
        simulated = model.step_held(simulated, controls, None, n)
        gap = np.abs(emulated[0].astype(np.float64) - simulated[0])
        rows.append(
            {
                "t_s": round(k * n * model.dt, 4),
                "root_gap_m": float(np.linalg.norm(gap[:3])),
                "largest_state_gap": float(gap.max()),
                "mujoco_moved_m": float(np.linalg.norm(simulated[0, :3] - start[0, :3])),
            }
        )
    return {
        "model": manifest.model,
        "version": manifest.version,
        "substeps": n,
        "operating": op.describe(),
        "push": push,
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("artifact", type=Path, help="a version's folder")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--push", type=float, default=0.0, help="added to every velocity at the start")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    out = side_by_side(args.artifact, args.seconds, args.push)
    rows = out["rows"]
    assert isinstance(rows, list)
    every = max(1, len(rows) // 10)
    print(f"{out['model']} {out['version']} n={out['substeps']}: {out['operating']}")
    print(f"{'t (s)':>8} {'root gap (m)':>14} {'largest gap':>12} {'MuJoCo moved (m)':>17}")
    for r in rows[every - 1 :: every]:
        print(
            f"{r['t_s']:8.2f} {r['root_gap_m']:14.4g} {r['largest_state_gap']:12.4g} {r['mujoco_moved_m']:17.4g}"
        )
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
