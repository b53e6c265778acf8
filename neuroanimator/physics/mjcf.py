"""A user's own model -> ``PhysicalModel``, through the same contract as the catalog.

The model comes as users ship it: an MJCF file with includes and assets, a folder, or a .zip / .tar.gz
of a folder (``bundle.load_source``); the model is built from its self-contained bundle, so what is
trained and stored never needs the source again.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path, PurePosixPath

import mujoco
import numpy as np

from neuroanimator.model_spec import InitialStates, ModelSpec
from neuroanimator.physics.bundle import Limits, SourceError, load_source
from neuroanimator.physics.model import ModelError, PhysicalModel, derive_layout, read_model_name

log = logging.getLogger(__name__)


def folder_name(text: str) -> str:
    """A model name made usable as a folder name: other characters become '-' ("planar walker" ->
    "planar-walker")."""
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-._")


def load_mjcf(
    path: str | Path,
    *,
    substeps: int | None = None,
    entry: str | None = None,
    name: str | None = None,
    limits: Limits | None = None,
) -> PhysicalModel:
    """Build a model from an MJCF file, a model folder or an archive of one (``entry``: the MJCF in a
    folder or archive; see ``bundle``): name from ``name``, else the MJCF's ``model`` attribute, else
    the entry's file name; state layout from its joints, controls and their ranges from its actuators.

    Typical initial states perturb ``qpos0`` a little (±0.3 on joint angles and slides, ±0.3 on
    velocities), and typical controls sweep each actuator's ctrlrange (±1 when unlimited).
    """
    p = Path(path)
    bundle = load_source(p, entry, limits)
    entry_stem = PurePosixPath(bundle.entry).stem
    model_name = folder_name(name or read_model_name(bundle.xml, entry_stem)) or folder_name(entry_stem)
    if not model_name:
        raise SourceError("entry", f"no usable model name in {p.name!r}: give one (--name)")
    try:
        m = mujoco.MjModel.from_xml_string(bundle.xml, bundle.vfs() or None)
    except Exception as exc:  # compiled once already by load_source: not expected
        raise ModelError(f"malformed MJCF {str(p)!r}: {exc}") from exc
    layout = derive_layout(m)
    unlimited = [
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"actuator{i}"
        for i in range(m.nu)
        if not m.actuator_ctrllimited[i]
    ]
    if unlimited:
        log.warning(
            "%s: actuators without ctrlrange: %s; their typical controls are drawn from [-1, 1] and the "
            "emulator is trained there only (give each a ctrlrange in the MJCF to choose the range)",
            bundle.entry,
            ", ".join(unlimited),
        )
    low, high = np.zeros(layout.size), np.zeros(layout.size)
    for g, sl in layout.group_slices():
        if g.kind in ("angle", "scalar", "local_vector", "world_vector"):
            low[sl], high[sl] = -0.3, 0.3
    origin = bundle.entry if bundle.entry == p.name else f"{bundle.entry} in {p.name}"
    spec = ModelSpec(
        name=model_name,
        description=f"user model from {origin}",
        substeps=50 if substeps is None else substeps,
        initial=InitialStates(low=low.tolist(), high=high.tolist(), random_yaw=True, max_tilt=0.3),
        episode_s=20.0,
    )
    return PhysicalModel(bundle.xml, spec, bundle.vfs(), {a.name: a.source for a in bundle.assets})
