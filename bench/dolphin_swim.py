"""The dolphin's hand-written travelling wave on MuJoCo: swimming speed, shape and physics speed.

    python bench/dolphin_swim.py [--seconds 60] [--json]

Rows: the stroke as a smooth function of time, and the same stroke held constant over each super-step
of 50 physical steps (what an emulator of N^50 sees), both from rest. Speed is the forward motion of
the nodes' centre of mass after the first 10 s (the start-up), in m/s and body lengths per second;
E_d is the deformation energy of thesis 6.1.3 over the whole run (mean, min, max; E_d of the rest
shape is 0). Physics speed: one trajectory on one thread, and a batch of 16 on the model's threads.
With ``--json`` the last line is one JSON object with the same numbers.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from neuroanimator import catalog
from neuroanimator.catalog import dolphin

SETTLE_S = 10.0


def _swim(model: catalog.PhysicalModel, controls: np.ndarray) -> dict[str, float]:
    traj = model.simulate(model.rest_state()[None], controls[None])[0]
    com = dolphin.centre_of_mass(traj)
    settle = int(SETTLE_S / model.dt)
    span = (len(traj) - settle) * model.dt
    speed = float((com[-1, 0] - com[settle, 0]) / span)
    energy = dolphin.deformation_energy(dolphin.node_positions(traj))
    return {
        "speed_m_s": speed,
        "speed_body_lengths_s": speed / dolphin.BODY_LENGTH,
        "distance_m": float(com[-1, 0] - com[0, 0]),
        "sideways_m": float(np.abs(com[:, 1] - com[0, 1]).max()),
        "vertical_m": float(np.abs(com[:, 2] - com[0, 2]).max()),
        "ed_mean": float(energy.mean()),
        "ed_min": float(energy.min()),
        "ed_max": float(energy.max()),
    }


def _steps_per_second(model: catalog.PhysicalModel, batch: int, threads: int, steps: int) -> float:
    u = dolphin.travelling_wave(np.arange(steps) * model.dt)[None].repeat(batch, axis=0)
    s0 = np.repeat(model.rest_state()[None], batch, axis=0)
    model.simulate(s0[:1], u[:1, :10], threads=1)  # warm the per-thread MjData
    start = time.perf_counter()
    model.simulate(s0, u, threads=threads)
    return batch * steps / (time.perf_counter() - start)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    model = catalog.get("dolphin")
    steps = round(args.seconds / model.dt)
    times = np.arange(steps) * model.dt
    smooth = dolphin.travelling_wave(times)
    held = dolphin.travelling_wave(times - times % (model.spec.substeps * model.dt))
    rows = {"travelling wave": _swim(model, smooth), "held per super-step": _swim(model, held)}
    speed = {
        "one trajectory, 1 thread": _steps_per_second(model, 1, 1, 2000),
        "batch of 16, 2 threads": _steps_per_second(model, 16, 2, 1000),
    }
    print(
        f"dolphin: state {model.state_size}, controls {model.num_controls}, δt {model.dt} s, "
        f"body length {dolphin.BODY_LENGTH} m, {args.seconds:.0f} s from rest"
    )
    print(
        "| stroke | speed (m/s) | body lengths/s | distance (m) | max drift y, z (m) | E_d mean | E_d min | E_d max |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(
            f"| {name} | {r['speed_m_s']:.3f} | {r['speed_body_lengths_s']:.3f} | {r['distance_m']:.2f} | "
            f"{r['sideways_m']:.2f}, {r['vertical_m']:.2f} | {r['ed_mean']:.3f} | {r['ed_min']:.1e} | "
            f"{r['ed_max']:.3f} |"
        )
    print()
    print("| physics | steps/s |")
    print("|---|---|")
    for name, value in speed.items():
        print(f"| {name} | {value:,.0f} |")
    if args.json:
        print(
            json.dumps(
                {
                    "model": "dolphin",
                    "state_size": model.state_size,
                    "dt": model.dt,
                    "seconds": args.seconds,
                    "body_length_m": dolphin.BODY_LENGTH,
                    "strokes": rows,
                    "steps_per_second": speed,
                }
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
