"""Speed of an emulator against MuJoCo, side by side in one run (thesis Table 6.2, and batched).

- single client: MuJoCo (``mujoco.rollout``, one thread, C loop) for 20,000 physical steps vs the
  ONNX emulator covering the same simulated time (20,000 / n calls), for each trained n;
- batched: ``mujoco.rollout`` with 2 threads vs one emulator call per super-step stepping B clients,
  20 s of simulated time each.

Ratios compare physical steps covered per second on the same cores in the same process.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from neuroanimator.artifacts import registry
from neuroanimator.core.results import BatchedSpeed, ModelBench, SingleClientSpeed
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim.model import PhysicalModel

SINGLE_STEPS = 20_000
BATCH_SECONDS = 20.0
BATCHES = (1, 64, 1024, 4096)


def _best_time(fn: Callable[[], object], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _inputs(
    model: PhysicalModel, batch: int, steps: int, substeps: int, seed: int = 7
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    s0 = model.initial_states(rng, batch)
    times = np.arange(0, steps, substeps, dtype=np.float64) * model.dt
    u = model.typical_controls(rng, batch, times)  # held per super-step
    f = model.typical_forces(rng, batch, times)
    return s0, u, f


def single(path: Path, model: PhysicalModel, substeps: int, repeats: int = 3) -> SingleClientSpeed:
    s0, u, f = _inputs(model, 1, SINGLE_STEPS, substeps)
    u_phys = np.repeat(u, substeps, axis=1)
    f_phys = np.repeat(f, substeps, axis=1) if model.num_forces else None
    physics = _best_time(lambda: model.simulate(s0, u_phys, f_phys, threads=1), repeats)
    emu = OnnxEmulator(path / registry.ONNX_FILE, threads=1)
    s32 = s0.astype(np.float32)
    u32 = np.ascontiguousarray(u.astype(np.float32))
    f32 = np.ascontiguousarray(f.astype(np.float32))
    m = SINGLE_STEPS // substeps

    def run() -> None:
        s = s32
        for k in range(m):
            s = emu.step(
                s,
                u32[:, k] if emu.num_controls else None,
                f32[:, k] if emu.num_forces else None,
                validate=False,
            )

    run()  # warm-up
    emulator = _best_time(run, repeats)
    return SingleClientSpeed(
        substeps=substeps, version=path.name, physics_s=physics, emulator_s=emulator, ratio=physics / emulator
    )


CHUNK_VALUES = 200_000_000  # state values one MuJoCo batch returns (1.6 GB of float64)


def batched(path: Path, model: PhysicalModel, substeps: int, batch: int, repeats: int = 2) -> BatchedSpeed:
    steps = round(BATCH_SECONDS / model.dt)
    s0, u, f = _inputs(model, batch, steps, substeps)
    u_phys = np.repeat(u, substeps, axis=1)
    f_phys = np.repeat(f, substeps, axis=1) if model.num_forces else None
    # MuJoCo returns every physical step's state: in chunks of at most CHUNK_VALUES values, so a large
    # model at B = 4,096 (the dolphin: 18 GB at once) fits in memory; its throughput on two threads
    # does not depend on the chunk once each thread has a few clients
    chunk = max(8, CHUNK_VALUES // (steps * model.state_size))

    def simulate() -> None:
        for a in range(0, batch, chunk):
            model.simulate(
                s0[a : a + chunk],
                u_phys[a : a + chunk],
                None if f_phys is None else f_phys[a : a + chunk],
                threads=2,
            )

    physics = _best_time(simulate, 1 if batch >= 1024 else repeats)
    emu = OnnxEmulator(path / registry.ONNX_FILE, threads=2)
    s32 = s0.astype(np.float32)
    u32 = np.ascontiguousarray(u.astype(np.float32).transpose(1, 0, 2))  # (M, B, U): one slab per call
    f32 = np.ascontiguousarray(f.astype(np.float32).transpose(1, 0, 2))
    m = steps // substeps

    def run() -> None:
        s = s32
        for k in range(m):
            s = emu.step(
                s, u32[k] if emu.num_controls else None, f32[k] if emu.num_forces else None, validate=False
            )

    run()
    emulator = _best_time(run, repeats + 1)
    covered = batch * steps
    return BatchedSpeed(
        batch=batch,
        physics_steps_per_s=covered / physics,
        emulator_steps_per_s=covered / emulator,
        ratio=physics / emulator,
    )


def run(root: registry.Root, name: str, batches: tuple[int, ...] = BATCHES, repeats: int = 3) -> ModelBench:
    """The whole benchmark for one model: single client for every trained n, batched for n = 50
    (else the latest's n)."""
    latest = registry.resolve(root, name)
    manifest = registry.read_manifest(latest)
    model = registry.load_physical_model(latest, manifest)
    ns = registry.available_substeps(root, name)
    single_rows = [single(registry.resolve(root, name, substeps=n), model, n, repeats) for n in ns]
    n_batched = 50 if 50 in ns else manifest.substeps
    path = registry.resolve(root, name, substeps=n_batched)
    return ModelBench(
        model=name,
        single=single_rows,
        batched=[batched(path, model, n_batched, b, repeats=min(repeats, 2)) for b in batches],
        batched_substeps=n_batched,
        batched_version=path.name,
    )
