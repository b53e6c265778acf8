"""Simulated training data kept on disk, so that trying training settings does not simulate again.

Simulating is most of a large training's time (the runner's 800,000 transitions: about 15 minutes on
two cores). With ``neuro train --data-cache DIR`` (or ``NEURO_DATA_CACHE``) the examples a training
simulates are written to DIR, and a later training that asks for the same ones reads them back.

The same ones means: the same model (its MJCF's sha256 and data source), super-step, count, seed and
sampler, simulated by the same code. The key holds the sha256 of every source file that simulates
(``neuroanimator.sim.sampling`` and the ``neuroanimator.catalog`` package: samplers, controllers, the
models' MJCF builders), so changing any of them misses the cache rather than reading stale data.

Shapes: N examples, S state, U controls, F forces.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from neuroanimator.sim import sampling
from neuroanimator.sim.model import PhysicalModel

log = logging.getLogger(__name__)

ENV = "NEURO_DATA_CACHE"

Data = TypeVar("Data", sampling.Examples, sampling.Sequences)


@functools.cache
def code_fingerprint() -> str:
    """sha256 over the source files that simulate training data, by path relative to the package."""
    package = Path(__file__).resolve().parents[1]
    files = [package / "sim" / "sampling.py", *sorted((package / "catalog").rglob("*.py"))]
    files += [package / "sim" / name for name in ("model.py", "controls.py", "waves.py", "separation.py")]
    h = hashlib.sha256()
    for f in files:
        h.update(f.relative_to(package).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def cache_key(
    model: PhysicalModel, substeps: int, count: int, seed: int, sampler: str, kind: str = "examples"
) -> str:
    """The sha256 that names one set of examples (or runs, ``kind``): everything that decides them."""
    what = {
        "kind": kind,
        "model": model.name,
        "mjcf": model.mjcf_sha256(),
        "data_source": model.spec.data_source,
        "substeps": substeps,
        "count": count,
        "seed": seed,
        "sampler": sampler,
        "code": code_fingerprint(),
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()


def directory(given: str | Path | None = None) -> Path | None:
    """The cache directory: ``given``, else ``$NEURO_DATA_CACHE``, else None (no cache)."""
    chosen = given if given is not None else os.environ.get(ENV) or None
    return None if chosen is None else Path(chosen)


def cached(
    cache: Path | None,
    model: PhysicalModel,
    substeps: int,
    count: int,
    seed: int,
    sampler: str,
    simulate: Callable[[], Data],
    kind: type[Data],
) -> Data:
    """What ``simulate`` makes (``kind``: examples, or the runs of the ``"runs"`` sampler), read from
    ``cache`` when an earlier call kept the same (see the module docstring), else simulated and kept
    there. ``cache`` None: simulate, keep nothing."""
    if cache is None:
        return simulate()
    what = kind.__name__.lower()
    key = cache_key(model, substeps, count, seed, sampler, what)
    path = cache / f"{model.name}-{what}-n{substeps}-{count}-seed{seed}-{key[:16]}.npz"
    arrays = [f.name for f in dataclasses.fields(kind)]
    if path.is_file():
        with np.load(path) as z:
            if str(z["key"]) == key:
                data = kind(*(z[a] for a in arrays))
                log.info("%s: %d %s read from %s", model.name, len(data), what, path)
                return data
        log.warning("%s holds other data than its name says: simulating again", path)
    data = simulate()
    cache.mkdir(parents=True, exist_ok=True)
    part = path.with_name(path.name + f".{os.getpid()}.part")
    with part.open("wb") as f:  # a file object: np.savez would add .npz to a path
        np.savez(f, key=np.asarray(key), **{a: getattr(data, a) for a in arrays})
    os.replace(part, path)  # whole or not at all: a second training may be reading the directory
    log.info("%s: %d %s kept in %s", model.name, len(data), what, path)
    return data
