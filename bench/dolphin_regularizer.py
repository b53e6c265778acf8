"""The dolphin's spring regulariser (thesis 6.1.3): deformation over a long swim (Fig. 6.7) and its cost
in speed (Table 6.2's last column).

    python bench/dolphin_regularizer.py [--artifacts DIR] [--version V] [--steps 5] [--seconds 60]
        [--periods 4,3] [--png bench/results/dolphin_regularizer.png] [--no-speed] [--json]

For each stroke period, the hand-written travelling wave (held over each super-step) drives the body
from rest for ``--seconds`` on MuJoCo and on the stored N^50 emulator twice: with the model's
regulariser of ``--steps`` Euler steps after each super-step (default: the manifest's when it has
one, else 5; stiffness and damping: the catalog's) and without. It prints the deformation
energy E_d (½ Σ ((l − l_r)/l_r)² over the springs) after the first 10 s (the start-up, when the
simulation's E_d rises from 0): the simulation's mean, and for each emulator its mean, its range as a
share of the simulation's mean, and the ratio of its last 10 s to its first 10 s after the start-up
(above 1: it grows). Beside it, in metres, how far each emulator's centre of mass is from MuJoCo's at
the end, and how far each swam. The PNG is Fig. 6.7: E_d over time, all three, for the first period.

Speed: MuJoCo for 20,000 physical steps on one thread against the emulator's ONNX graph with and
without the regulariser covering the same simulated time (one client), and both batched at B = 1,024
on two threads (``neuroanimator.evaluation.speed``). With ``--json`` the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.catalog import dolphin
from neuroanimator.emulator.regularizer import SpringRegularization, deformation_energy
from neuroanimator.evaluation import speed
from neuroanimator.export.onnx import to_onnx
from neuroanimator.sim.model import PhysicalModel

log = logging.getLogger("dolphin_regularizer")
SETTLE_S = 10.0


def _energy(model: PhysicalModel, states: np.ndarray) -> np.ndarray:
    spec = model.spec.regularizer
    assert spec is not None
    return deformation_energy(spec, dolphin.node_positions(states))


def _emulate(emu: torch.nn.Module, s0: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(S,) start, (M, U) controls -> (M + 1, S) emulated states."""
    out = [s0.astype(np.float32)]
    with torch.no_grad():
        s = torch.from_numpy(out[0][None])
        for u in held.astype(np.float32):
            s = emu(s, torch.from_numpy(u[None]))
            out.append(s[0].numpy())
    return np.asarray(out, dtype=np.float64)


def _summary(energy: np.ndarray, reference_mean: float, window: int, settle: int) -> dict[str, float]:
    after = energy[settle:]
    return {
        "ed_mean": float(after.mean()),
        "ed_min_share": float(after.min() / reference_mean),
        "ed_max_share": float(after.max() / reference_mean),
        "ed_growth": float(after[-window:].mean() / after[:window].mean()),
    }


def _stroke(model: PhysicalModel, emu: torch.nn.Module, period: float, seconds: float) -> dict[str, Any]:
    n = model.spec.substeps
    m = round(seconds / (n * model.dt))
    held = dolphin.travelling_wave(np.arange(m) * n * model.dt, period=period)  # (M, 6)
    s0 = model.rest_state()
    traj = model.simulate(s0[None], np.repeat(held, n, axis=0)[None])[0]  # (M·n, S) after each step
    physical = np.concatenate([s0[None], traj[n - 1 :: n]])  # (M + 1, S) at the super-steps
    regularizer = getattr(emu, "regularizer", None)
    with_reg = _emulate(emu, s0, held)
    emu.regularizer = None  # type: ignore[assignment]
    without = _emulate(emu, s0, held)
    emu.regularizer = regularizer  # type: ignore[assignment]
    settle = round(SETTLE_S / (n * model.dt))
    window = settle
    e_sim = _energy(model, physical)
    reference = float(e_sim[settle:].mean())
    com = {
        k: dolphin.centre_of_mass(v)
        for k, v in (("mujoco", physical), ("with", with_reg), ("without", without))
    }
    rows: dict[str, Any] = {"period_s": period, "mujoco": _summary(e_sim, reference, window, settle)}
    rows["mujoco"]["distance_m"] = float(com["mujoco"][-1, 0] - com["mujoco"][0, 0])
    for key, states in (("with", with_reg), ("without", without)):
        r = _summary(_energy(model, states), reference, window, settle)
        r["finite"] = bool(np.isfinite(states).all())
        r["distance_m"] = float(com[key][-1, 0] - com[key][0, 0])
        r["com_error_m"] = float(np.linalg.norm(com[key][-1] - com["mujoco"][-1]))
        r["com_error_10s_m"] = float(np.linalg.norm(com[key][settle] - com["mujoco"][settle]))
        rows[key] = r
    rows["series"] = {
        "t": (np.arange(m + 1) * n * model.dt).tolist(),
        "mujoco": e_sim.tolist(),
        "with": _energy(model, with_reg).tolist(),
        "without": _energy(model, without).tolist(),
    }
    return rows


def _plot(row: dict[str, Any], steps: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = row["series"]
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=120)
    ax.plot(s["t"], s["mujoco"], color="black", lw=1.4, label="MuJoCo (physics)")
    ax.plot(s["t"], s["with"], color="tab:blue", lw=1.4, label=f"emulator, {steps} regularisation steps")
    ax.plot(s["t"], s["without"], color="tab:red", lw=1.2, ls="--", label="emulator, no regularisation")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("deformation energy $E_d$")
    ax.set_title(f"Dolphin, travelling wave of period {row['period_s']:g} s (thesis Fig. 6.7)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def _speeds(model: PhysicalModel, emu: torch.nn.Module) -> dict[str, Any]:
    regularizer = getattr(emu, "regularizer", None)
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths = {"with": Path(tmp) / "with", "without": Path(tmp) / "without"}
        for key, path in paths.items():
            path.mkdir()
            emu.regularizer = regularizer if key == "with" else None  # type: ignore[assignment]
            (path / registry.ONNX_FILE).write_bytes(to_onnx(emu))  # type: ignore[arg-type]
        emu.regularizer = regularizer  # type: ignore[assignment]
        n = model.spec.substeps
        for key, path in paths.items():
            single = speed.single(path, model, n, repeats=2)
            batched = speed.batched(path, model, n, 1024, repeats=1)
            out[key] = {
                "single_physics_s": single.physics_s,
                "single_emulator_s": single.emulator_s,
                "single_ratio": single.ratio,
                "batched_physics_steps_per_s": batched.physics_steps_per_s,
                "batched_emulator_steps_per_s": batched.emulator_steps_per_s,
                "batched_ratio": batched.ratio,
            }
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--artifacts", type=Path, default=Path("artifacts"))
    p.add_argument("--version", help="an artifact version (default: the latest)")
    p.add_argument(
        "--steps", type=int, help="Euler steps of the regulariser (default: the manifest's, else 5)"
    )
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--periods", default="4,3", help="stroke periods in seconds, comma-separated")
    p.add_argument("--png", type=Path, default=Path("bench/results/dolphin_regularizer.png"))
    p.add_argument("--no-speed", action="store_true", help="leave out the speed table")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)

    version = registry.resolve(args.artifacts, "dolphin", args.version)
    manifest = registry.read_manifest(version)
    model = registry.load_physical_model(version, manifest)
    emu = artifacts.load_emulator(version)
    # the catalog's regulariser (its stiffness and damping as the code sets them now)
    spec = catalog.get("dolphin").spec.regularizer
    assert spec is not None
    stored = manifest.emulator.regularizer
    steps = args.steps if args.steps is not None else (stored.steps if stored else 5)
    emu.regularizer = SpringRegularization(
        model.layout, spec.model_copy(update={"steps": steps}), model.num_controls
    )
    rows = [_stroke(model, emu, float(t), args.seconds) for t in args.periods.split(",")]
    _plot(rows[0], steps, args.png)

    print(
        f"dolphin {version.name}: {args.seconds:.0f} s from rest, {steps} regularisation steps; E_d after {SETTLE_S:.0f} s"
    )
    print(
        "| stroke period | run | E_d mean | E_d range / MuJoCo's mean | growth (last 10 s / first 10 s) | swam (m) | centre of mass vs MuJoCo at 10 s, end (m) |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        for key, name in (
            ("mujoco", "MuJoCo"),
            ("with", "emulator, regularised"),
            ("without", "emulator, none"),
        ):
            x = r[key]
            err = f"{x['com_error_10s_m']:.3f}, {x['com_error_m']:.3f}" if key != "mujoco" else "–"
            print(
                f"| {r['period_s']:g} s | {name} | {x['ed_mean']:.4f} | {x['ed_min_share']:.0%} – {x['ed_max_share']:.0%} "
                f"| {x['ed_growth']:.2f} | {x['distance_m']:.2f} | {err} |"
            )
    print(f"plot: {args.png}")
    speeds = None if args.no_speed else _speeds(model, emu)
    if speeds:
        print()
        print(
            "| emulator | one client: MuJoCo 20,000 steps (s) | emulator (s) | ratio | B = 1,024: MuJoCo steps/s | emulator steps/s | ratio |"
        )
        print("|---|---|---|---|---|---|---|")
        for key, name in (("without", "N^50"), ("with", f"N^50 with {steps} regularisation steps")):
            x = speeds[key]
            print(
                f"| {name} | {x['single_physics_s']:.2f} | {x['single_emulator_s']:.3f} | {x['single_ratio']:.0f}× "
                f"| {x['batched_physics_steps_per_s']:,.0f} | {x['batched_emulator_steps_per_s']:,.0f} | {x['batched_ratio']:.0f}× |"
            )
    if args.json:
        for r in rows:
            r.pop("series")
        print(
            json.dumps(
                {
                    "model": "dolphin",
                    "version": version.name,
                    "regularizer_steps": steps,
                    "strokes": rows,
                    "speed": speeds,
                }
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
