"""A user's own MJCF file -> ``PhysicalModel``, through the same contract as the catalog."""

from __future__ import annotations

import logging
from pathlib import Path

import mujoco
import numpy as np

from neuroanimator.model_spec import InitialStates, ModelSpec
from neuroanimator.physics.model import ModelError, PhysicalModel, derive_layout, read_model_name

log = logging.getLogger(__name__)


def load_mjcf(path: str | Path, *, substeps: int | None = None) -> PhysicalModel:
    """Build a model from an MJCF file: name from its ``model`` attribute (else the file name),
    state layout from its joints, controls and their ranges from its actuators.

    Typical initial states perturb ``qpos0`` a little (±0.3 on joint angles and slides, ±0.3 on
    velocities), and typical controls sweep each actuator's ctrlrange (±1 when unlimited).
    """
    p = Path(path)
    if not p.is_file():
        raise ModelError(f"MJCF file {str(p)!r} does not exist")
    xml = p.read_text()
    if "file=" in xml:
        # an artifact carries one self-contained MJCF; meshes and includes would not travel with it
        raise ModelError(
            f"MJCF {p.name!r} refers to other files (meshes, includes); give a self-contained MJCF"
        )
    name = read_model_name(xml, p.stem)
    try:
        m = mujoco.MjModel.from_xml_string(xml)
    except Exception as exc:
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
            p.name,
            ", ".join(unlimited),
        )
    low, high = np.zeros(layout.size), np.zeros(layout.size)
    for g, sl in layout.group_slices():
        if g.kind in ("angle", "scalar", "local_vector", "world_vector"):
            low[sl], high[sl] = -0.3, 0.3
    spec = ModelSpec(
        name=name,
        description=f"user model from {p.name}",
        substeps=50 if substeps is None else substeps,
        initial=InitialStates(low=low.tolist(), high=high.tolist(), random_yaw=True, max_tilt=0.3),
        episode_s=20.0,
    )
    return PhysicalModel(xml, spec)
