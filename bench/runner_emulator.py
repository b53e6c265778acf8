"""The runner's emulator (thesis 4.4, 6.1, Fig. 6.5): its networks' errors, the emulated running loop
against MuJoCo's, and its speed.

    python bench/runner_emulator.py [--artifacts artifacts] [--seconds 30] [--no-speed] [--json]

The emulator is the latest ``runner`` artifact (``neuro train runner``). Three tables:

- each network's held-out one-step relative error and the error of a linear map of the same inputs
  (from the artifact's manifest: measured at training on transitions of an independent seed);
- the running controller (``runner_control``, reading ``KinematicSensors``) closing its loop through
  the emulator (``run_emulated``) and through MuJoCo (``run`` with the controller every super-step),
  from the same start: at a target speed in the training data, at ``runner_data.UNSEEN_SPEED`` (not in
  it), and pushed sideways at 5 s (a push none of the training runs had: their pushes come at random
  times, directions and sizes up to the push inputs' range). Root (pelvis) position error at 1, 5,
  10 s and the end; mean forward speed of each; the largest relative difference of their forward speeds over
  5-second windows; whether and when each fell. Errors and speeds are compared while both are up
  ("–" after a fall);
- speed against MuJoCo for 20,000 physical steps, one client and batched (``neuroanimator.evaluation.speed``:
  the same open-loop controls for both, on the same cores in the same run).

With ``--json`` the last line is one JSON object with every number.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from neuroanimator.artifacts import registry
from neuroanimator.catalog.runner import data as runner_data
from neuroanimator.catalog.runner import gait as rc
from neuroanimator.evaluation import speed
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel

TRAINED_SPEED = 2.2
PUSH = rc.Push(force=(0.0, 250.0, 0.0), start_s=5.0, duration_s=0.2)  # 50 N·s; data: random pushes ≤ 300 N


def _windows(x: np.ndarray, dt: float, seconds: float, width: float = 5.0) -> np.ndarray:
    """(T,) forward positions every dt -> mean speed over each ``width``-second window."""
    k = round(width / dt)
    ends = np.arange(k, min(len(x), round(seconds / dt) + 1), k)
    return (x[ends] - x[ends - k]) / width


def closed_loop(
    model: PhysicalModel,
    onnx: OnnxEmulator,
    substeps: int,
    speed_target: float,
    seconds: float,
    push: rc.Push | None,
) -> dict[str, Any]:
    """The emulated loop and MuJoCo's from the same start: errors and speeds (see the module docstring)."""
    m = model.mj_model

    def step(s: np.ndarray, u: np.ndarray, f: np.ndarray) -> np.ndarray:
        out = onnx.step(s.astype(np.float32), u.astype(np.float32), f.astype(np.float32), validate=False)
        return np.asarray(out, dtype=np.float64)

    start = rc.running_start(m, speed_target)
    emu = rc.run_emulated(model, step, substeps, start, speed_target, seconds, push=push)
    ref = rc.run(m, start, speed_target, seconds, control_every=substeps, kinematic=True, push=push)
    sim = model.from_physics(ref.states[0])  # (T, S): the state each control period starts from
    em = emu.states[0]
    pos = model.layout.slice_of("root.pos")
    # compare while both are up: after a fall an emulator leaves everything it was trained on
    up_s = min(float(emu.fell_at[0]), float(ref.fell_at[0]), seconds)
    n = min(len(em), len(sim), round(up_s / emu.dt) + 1)
    err = np.linalg.norm(em[:n, pos] - sim[:n, pos], axis=1)
    at = {
        f"{t:g}": float(err[round(t / emu.dt)]) if round(t / emu.dt) < n else None
        for t in (1.0, 5.0, 10.0, seconds)
    }
    v_emu = _windows(em[:n, pos.start], emu.dt, up_s)
    v_sim = _windows(sim[:n, pos.start], emu.dt, up_s)
    span = max(1, n - 1) * emu.dt
    return {
        "target_speed": speed_target,
        "push": None
        if push is None
        else {
            "force": np.asarray(push.force).tolist(),
            "start_s": push.start_s,
            "duration_s": push.duration_s,
        },
        "root_error_m": at,
        "compared_s": (n - 1) * emu.dt,
        "mean_speed_emulator": float((em[n - 1, pos.start] - em[0, pos.start]) / span),
        "mean_speed_mujoco": float((sim[n - 1, pos.start] - sim[0, pos.start]) / span),
        "worst_window_speed_difference": float(np.max(np.abs(v_emu - v_sim) / np.abs(v_sim)))
        if len(v_sim)
        else None,
        "fell_emulator_s": None if np.isinf(emu.fell_at[0]) else float(emu.fell_at[0]),
        "fell_mujoco_s": None if np.isinf(ref.fell_at[0]) else float(ref.fell_at[0]),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--artifacts", type=Path, default=Path("artifacts"))
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--no-speed", action="store_true")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    path = registry.resolve(args.artifacts, "runner")
    manifest = registry.read_manifest(path)
    model = registry.load_physical_model(path, manifest)
    n = manifest.substeps
    out: dict[str, Any] = {"version": path.name, "substeps": n, "super_timestep": manifest.super_timestep}

    nets = manifest.metrics.model_dump().get("networks", {})
    print(f"runner {path.name}: n = {n} (Δt = {manifest.super_timestep * 1000:.1f} ms)\n")
    print("| network | inputs | outputs | one-step error | linear | ratio |")
    print("|---|---|---|---|---|---|")
    for name, m in nets.items():
        ratio = m["linear_baseline_rel_error"] / m["one_step_rel_error"]
        print(
            f"| {name} | {m['inputs']} | {m['outputs']} | {m['one_step_rel_error']:.4f} | "
            f"{m['linear_baseline_rel_error']:.4f} | {ratio:.1f}× |"
        )
    out["networks"] = nets

    onnx = OnnxEmulator(path / registry.ONNX_FILE, threads=1)
    runs = [
        ("in the training speeds", TRAINED_SPEED, None),
        ("a speed not in the data", runner_data.UNSEEN_SPEED, None),
        ("a push not in the data", TRAINED_SPEED, PUSH),
    ]
    print(
        "\n| run | target (m/s) | root error 1 / 5 / 10 / end (m) | speed emulator / MuJoCo (m/s) | worst 5-s speed difference | fell (emulator / MuJoCo) |"
    )
    print("|---|---|---|---|---|---|")
    out["runs"] = []
    for label, v, push in runs:
        r = closed_loop(model, onnx, n, v, args.seconds, push)
        e = r["root_error_m"]
        fell = " / ".join(
            "no" if t is None else f"at {t:.1f} s" for t in (r["fell_emulator_s"], r["fell_mujoco_s"])
        )
        worst = r["worst_window_speed_difference"]
        print(
            f"| {label} | {v:.1f} | {' / '.join('–' if x is None else f'{x:.2f}' for x in e.values())} | "
            f"{r['mean_speed_emulator']:.2f} / {r['mean_speed_mujoco']:.2f} | "
            f"{'–' if worst is None else f'{100 * worst:.0f} %'} | {fell} |"
        )
        out["runs"].append({"label": label, **r})

    if not args.no_speed:
        single = speed.single(path, model, n)
        print(
            f"\nsingle client, 20,000 physical steps: MuJoCo {single.physics_s:.2f} s, emulator {single.emulator_s:.2f} s: {single.ratio:.1f}×"
        )
        batched = speed.batched(path, model, n, 1024)
        print(
            f"batched, B = 1,024: MuJoCo {batched.physics_steps_per_s:,.0f} steps/s, emulator {batched.emulator_steps_per_s:,.0f}: {batched.ratio:.0f}×"
        )
        out["speed"] = {"single": single.model_dump(), "batched_1024": batched.model_dump()}
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
