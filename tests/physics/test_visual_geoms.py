"""Visual-only geoms (group 2, no contacts, no mass) give catalog models their look in the dashboard
(the lander's legs and nozzle, the truck's wheels and cab, the pendulum's stand) and change nothing
physical: the model with them and the same model with them deleted have the same masses, inertias
and contacts, and simulate to the same numbers."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.sim.model import PhysicalModel

ROOT = Path(__file__).resolve().parents[2]
VISUAL_GROUP = 2
DRESSED = ["lander", "truck", "pendulum-passive", "pendulum-active", "pendulum-force"]


def _without_visuals(xml: str) -> tuple[str, int]:
    spec = mujoco.MjSpec.from_string(xml)
    visuals = [g for g in spec.geoms if g.group == VISUAL_GROUP]
    for g in visuals:
        spec.delete(g)
    spec.compile()
    return spec.to_xml(), len(visuals)


@pytest.mark.parametrize("name", DRESSED)
def test_visual_geoms_are_visual_only(name: str) -> None:
    model = catalog.get(name)
    m = model.mj_model
    visual = [g for g in range(m.ngeom) if m.geom_group[g] == VISUAL_GROUP]
    assert len(visual) >= 3, f"{name} has {len(visual)} visual geoms"
    for g in visual:
        label = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g)
        assert label, "every visual geom is named"
        assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0, label


@pytest.mark.parametrize("name", DRESSED)
def test_visual_geoms_change_no_physics(name: str) -> None:
    dressed = catalog.get(name)
    bare_xml, removed = _without_visuals(dressed.xml)
    assert removed > 0
    bare = PhysicalModel(bare_xml, dressed.spec)
    a, b = dressed.mj_model, bare.mj_model
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "dof_damping", "actuator_gear"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert dressed.frame == bare.frame
    rng = np.random.default_rng(3)
    times = np.arange(300.0) * dressed.dt
    s0 = dressed.initial_states(rng, 3)
    u = dressed.typical_controls(rng, 3, times)
    f = dressed.typical_forces(rng, 3, times) if dressed.num_forces else None
    np.testing.assert_array_equal(dressed.simulate(s0, u, f), bare.simulate(s0, u, f))


@pytest.mark.parametrize(
    ("name", "wanted"),
    [
        ("lander", {"leg0", "nozzle", "foot3", "pad"}),
        ("truck", {"cab", "wheel_rear_left"}),
        ("pendulum-force", {"axle", "post"}),
    ],
)
def test_committed_emulators_draw_their_visuals(name: str, wanted: set[str]) -> None:
    """The dashboard draws a model from its artifact's own MJCF (``GET /models/{model}/geometry``), so
    the committed default emulators carry the visual geoms too."""
    from services.emulator.scene import Kinematics, geometry

    path = registry.resolve(ROOT / "artifacts", name)
    g = geometry(name, path.name, Kinematics(registry.load_physical_model(path)))
    names = {geom.name for geom in g.world} | {geom.name for b in g.bodies for geom in b.geoms}
    assert wanted <= names, f"{name}: {sorted(wanted - names)} missing from {sorted(names)}"
