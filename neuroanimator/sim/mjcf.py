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

from neuroanimator.core.model_spec import ModelSpec
from neuroanimator.core.operating_spec import OperatingSpec
from neuroanimator.sim import operating, sandbox
from neuroanimator.sim.bundle import Limits, SourceError
from neuroanimator.sim.model import (
    MAX_DIVERGED,
    PhysicalModel,
    SimulationDiverged,
    derive_layout,
    mujoco_warnings_as_debug,
)

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
    operating_spec: OperatingSpec | None = None,
    keyframe: str | None = None,
) -> PhysicalModel:
    """Build a model from an MJCF file, a model folder or an archive of one (``entry``: the MJCF in a
    folder or archive; see ``bundle``): name from ``name``, else the MJCF's ``model`` attribute, else
    the entry's file name; state layout from its joints, controls and their ranges from its actuators.

    Typical motion is set around the model's operating point (``operating.typical_motion``): its
    keyframes (or the one named ``keyframe``), else the controls that hold it still, else today's
    ranges: starts perturb ``qpos0`` a little (±0.3 on joint angles and slides, ±0.3 on velocities; an
    actuator's activation anywhere in its control range) and typical controls sweep each actuator's
    ctrlrange (±1 when unlimited); ``operating_spec`` (``OperatingSpec``) declares more. With ``stabilise``, the velocity perturbations are
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
    derive_layout(m)  # a model without joints is refused here, in its own words
    origin = bundle.entry if bundle.entry == p.name else f"{bundle.entry} in {p.name}"
    spec = ModelSpec(
        name=model_name,
        description=f"user model from {origin}",
        substeps=50 if substeps is None else substeps,
        episode_s=20.0,
    )
    model = PhysicalModel(bundle.xml, spec, bundle.vfs(), {a.name: a.source for a in bundle.assets}, m)
    model.spec = operating.typical_motion(model, operating_spec, keyframe)
    log.info("%s: %s", model_name, model.spec.operating.describe() if model.spec.operating else "")
    if stabilise:
        stabilise_initial_states(model)
        narrow_typical_motion(model)
    return model


PROBE_RUNS = 256
PROBE_SECONDS = 1.0
NARROWINGS = 4


def _unstable_runs(
    model: PhysicalModel, seed: int, runs: int = PROBE_RUNS, seconds: float = PROBE_SECONDS
) -> int:
    """How many of ``runs`` runs of ``seconds`` of typical motion MuJoCo could not simulate (non-finite
    values, values a thousand times the start's, or MuJoCo's own instability warning)."""
    steps = max(10, round(seconds / model.dt))
    s0, u, f = model.typical_runs(np.random.default_rng(seed), runs, steps)
    with mujoco_warnings_as_debug():  # instability is what this looks for; the caller reports it
        _, diverged = model.simulate_runs(s0, u, f, nstep=steps)
    return int(diverged.sum())


MOTION_PROBE_RUNS = 64
MOTION_PROBE_SECONDS = 5.0
MOTION_NARROWINGS = 3


def _narrowed(spec: ModelSpec, ranges: np.ndarray, scale: float) -> ModelSpec:
    """``spec`` with its typical controls' spread around the operating point's centres (the middle of
    each range where it has none) and its starts' spread, tilt included, scaled by ``scale``."""
    op = spec.operating
    init = spec.initial
    update: dict[str, object] = {
        "initial": init.model_copy(
            update={
                "low": [x * scale for x in init.low],
                "high": [x * scale for x in init.high],
                "max_tilt": init.max_tilt * scale,
            }
        )
    }
    if op is not None and ranges.size:
        centres = np.asarray(op.control_centres or [ranges.mean(axis=1).tolist()], dtype=np.float64)
        spread = np.asarray(op.control_spread or ((ranges[:, 1] - ranges[:, 0]) / 2).tolist()) * scale
        update["control_low"], update["control_high"] = operating.control_envelope(centres, spread, ranges)
        update["operating"] = op.model_copy(
            update={"control_centres": centres.tolist(), "control_spread": spread.tolist()}
        )
    return spec.model_copy(update=update)


def narrow_typical_motion(model: PhysicalModel, seed: int = 0) -> str | None:
    """Narrow the typical motion around the operating point while more than ``MAX_DIVERGED`` of
    ``MOTION_PROBE_RUNS`` runs of up to ``MOTION_PROBE_SECONDS`` diverge: controls and starts halved
    around it, up to ``MOTION_NARROWINGS`` times; what was done (also in the operating record), or None
    when nothing had to be. ``SimulationDiverged`` says what was tried when even the narrowest fails.

    Why: a drone driven by thrusts over their whole range spins up until MuJoCo gives up (Menagerie's
    X2 diverged 2.3 s into a run); sampling drops the runs that diverge, but where many do, the typical
    motion itself is out of MuJoCo's reach."""
    seconds = min(model.spec.episode_s, MOTION_PROBE_SECONDS)
    most = int(MAX_DIVERGED * MOTION_PROBE_RUNS)
    bad = _unstable_runs(model, seed, MOTION_PROBE_RUNS, seconds)
    if bad <= most:
        return None
    original, ranges = model.spec, operating.control_ranges(model)
    tried = [f"as found: {bad} of {MOTION_PROBE_RUNS}"]
    for k in range(1, MOTION_NARROWINGS + 1):
        scale = 0.5**k
        model.spec = _narrowed(original, ranges, scale)
        worse = _unstable_runs(model, seed, MOTION_PROBE_RUNS, seconds)
        tried.append(f"{scale:g}× the spread: {worse}")
        if worse <= most:
            said = (
                f"typical controls and starts narrowed to {scale:g}× their spread around the operating point: "
                f"{bad} of {MOTION_PROBE_RUNS} runs of {seconds:g} s diverged in MuJoCo at the first spread"
            )
            log.warning("%s: %s", model.name, said)
            op = model.spec.operating
            if op is not None:
                model.spec = model.spec.model_copy(
                    update={"operating": op.model_copy(update={"narrowed": said})}
                )
            return said
    model.spec = original
    raise SimulationDiverged(
        f"{_first_divergence(model, seed, seconds)}. Narrowing the typical motion around the operating point did "
        f"not help: runs of {seconds:g} s that diverged, of {MOTION_PROBE_RUNS}: {'; '.join(tried)}"
    )


def _first_divergence(model: PhysicalModel, seed: int, seconds: float) -> str:
    """What ``simulate`` says of a diverging run of typical motion: when, and at which joint."""
    steps = max(10, round(seconds / model.dt))
    s0, u, f = model.typical_runs(np.random.default_rng(seed), MOTION_PROBE_RUNS, steps)
    try:
        with mujoco_warnings_as_debug():
            model.simulate(s0, u, f, nstep=steps, check=True)
    except SimulationDiverged as exc:
        return str(exc).rstrip(".")
    return f"the simulation of model {model.name} diverges in runs of typical motion"


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
