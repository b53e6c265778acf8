"""A user's own model -> ``PhysicalModel``, through the same contract as the catalog.

The model comes as users ship it: an MJCF file with includes and assets, a folder, or a .zip / .tar.gz
of a folder (``sandbox.load_bundle``); the model is built from its self-contained bundle, so what is
trained and stored never needs the source again.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path, PurePosixPath

import mujoco
import numpy as np

from neuroanimator.core.model_spec import InitialStates, ModelSpec
from neuroanimator.sim import sandbox
from neuroanimator.sim.bundle import Limits, SourceError
from neuroanimator.sim.model import PhysicalModel, SimulationDiverged, derive_layout, mujoco_warnings_as_debug

log = logging.getLogger(__name__)
MAX_NAME = 64  # characters of a model's name (a folder's)


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
    stabilise: bool = True,
    require_landlock: bool | None = None,
) -> PhysicalModel:
    """Build a model from an MJCF file, a model folder or an archive of one (``entry``: the MJCF in a
    folder or archive; see ``bundle``): name from ``name``, else the MJCF's ``model`` attribute, else
    the entry's file name; state layout from its joints, controls and their ranges from its actuators.

    Typical initial states perturb ``qpos0`` a little (±0.3 on joint angles and slides, ±0.3 on
    velocities; an actuator's activation anywhere in its control range), and typical controls sweep
    each actuator's ctrlrange (±1 when unlimited). With ``stabilise``, the velocity perturbations are
    narrowed where MuJoCo cannot simulate them (``stabilise_initial_states``); a quick check of an
    upload may skip that.
    """
    p = Path(path)
    bundle, m = sandbox.load_source(p, entry, limits or Limits(), require_landlock)
    entry_stem = PurePosixPath(bundle.entry).stem
    model_name = folder_name(name or bundle.name or entry_stem) or folder_name(entry_stem)
    if not model_name:
        raise SourceError("entry", f"no usable model name in {p.name!r}: give one (--name)")
    if len(model_name) > MAX_NAME:
        raise SourceError(
            "entry",
            f"the model's name ({model_name[:40]}...) has {len(model_name)} characters; a name may have "
            f"{MAX_NAME}: give a shorter one (--name, or the form field name)",
        )
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
        if g.source == "act":  # an activation: anywhere its control can drive it
            a = _actuator_of_activation(m, g.address)
            if m.actuator_ctrllimited[a]:
                low[sl], high[sl] = m.actuator_ctrlrange[a]
            else:
                low[sl], high[sl] = -1.0, 1.0
        elif g.kind in ("angle", "scalar", "local_vector", "world_vector"):
            low[sl], high[sl] = -0.3, 0.3
    origin = bundle.entry if bundle.entry == p.name else f"{bundle.entry} in {p.name}"
    spec = ModelSpec(
        name=model_name,
        description=f"user model from {origin}",
        substeps=50 if substeps is None else substeps,
        initial=InitialStates(low=low.tolist(), high=high.tolist(), random_yaw=True, max_tilt=0.3),
        episode_s=20.0,
    )
    model = PhysicalModel(bundle.xml, spec, bundle.vfs(), {a.name: a.source for a in bundle.assets}, m)
    if stabilise:
        stabilise_initial_states(model)
    return model


def _actuator_of_activation(m: mujoco.MjModel, address: int) -> int:
    """The actuator whose activation sits at ``act[address]``."""
    return int(np.flatnonzero(m.actuator_actadr == address)[0])


PROBE_RUNS = 256
PROBE_SECONDS = 1.0
NARROWINGS = 4


def _unstable_runs(model: PhysicalModel, seed: int) -> int:
    """How many of ``PROBE_RUNS`` runs of typical motion MuJoCo could not simulate (non-finite values,
    values a thousand times the start's, or MuJoCo's own instability warning)."""
    rng = np.random.default_rng(seed)
    steps = max(10, round(PROBE_SECONDS / model.dt))
    times = np.arange(steps, dtype=np.float64) * model.dt
    s0 = model.initial_states(rng, PROBE_RUNS)
    u = model.typical_controls(rng, PROBE_RUNS, times)
    f = model.typical_forces(rng, PROBE_RUNS, times) if model.num_forces else None
    try:
        with mujoco_warnings_as_debug():  # instability is what this looks for; the caller reports it
            traj = model.simulate(s0, u, f, nstep=steps, check=True)
    except SimulationDiverged:
        return PROBE_RUNS
    huge = ~np.isfinite(traj) | (np.abs(traj) > 1e3 * (1.0 + np.abs(s0[:, None, :])))
    return int(huge.any(axis=(1, 2)).sum())


def stabilise_initial_states(model: PhysicalModel, seed: int = 0) -> str | None:
    """Narrow the velocity perturbations of the typical initial states until MuJoCo simulates a probe of
    typical motion (``PROBE_RUNS`` runs of ``PROBE_SECONDS``) without instability; the reason, or None
    when the first spread was stable.

    Why: a fixed ±0.3 on every velocity is mild for a walker and violent for a 10 cm fish in dense water
    (dm_control's fish diverges within 0.03 s in about 1 run of 64). The spread is halved up to
    ``NARROWINGS`` times, then velocities start at zero; the first stable spread is halved once more, as a
    margin for the many more runs of sampling. A model that is unstable even from rest keeps
    its spread, and sampling then names the time and the joint (``SimulationDiverged``).
    """
    init = model.spec.initial
    if not init.low:
        return None
    vel = np.zeros(model.state_size, dtype=bool)
    for g, sl in model.layout.group_slices():
        vel[sl] = g.source == "qvel"
    low, high = np.asarray(init.low, dtype=np.float64), np.asarray(init.high, dtype=np.float64)
    original, first_bad = model.spec, 0

    def scaled(scale: float) -> ModelSpec:
        lo, hi = low.copy(), high.copy()
        lo[vel], hi[vel] = low[vel] * scale, high[vel] * scale
        return original.model_copy(
            update={"initial": init.model_copy(update={"low": lo.tolist(), "high": hi.tolist()})}
        )

    for k in range(NARROWINGS + 2):
        scale = 0.0 if k == NARROWINGS + 1 else 0.5**k
        model.spec = scaled(scale)
        bad = _unstable_runs(model, seed)
        if bad == 0:
            if k == 0:
                return None
            model.spec = scaled(scale / 2.0)
            reason = (
                f"typical initial velocities narrowed to {scale / 2.0:g} of ±{np.max(np.abs(high[vel])):g}: "
                f"from the wider spread MuJoCo could not simulate {first_bad} of {PROBE_RUNS} runs of typical motion"
            )
            log.warning("%s: %s", model.name, reason)
            return reason
        first_bad = first_bad or bad
    model.spec = original
    return None
