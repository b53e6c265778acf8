"""MuJoCo Menagerie's Skydio X2 as shipped (tests/data/skydio_x2: x2.xml and scene.xml, the OBJ mesh and
its texture in assets/ through ``<compiler assetdir>``): a model nobody here wrote loads through
``load_mjcf``, and where it operates is found both from its own ``hover`` keyframe and, with the
keyframe removed, from the physics (the four thrusts that carry its weight)."""

from __future__ import annotations

import re
from pathlib import Path

import mujoco
import numpy as np
import pytest

from neuroanimator.sim import operating
from neuroanimator.sim.mjcf import load_mjcf

X2 = Path(__file__).resolve().parents[1] / "data" / "skydio_x2"
MASS = 1.325  # kg: four rotors of 0.25 and a body of 0.325 (the visual mesh has none)
HOVER_THRUST = 3.2495625  # N per rotor, the keyframe's ctrl: a quarter of 1.325 kg × 9.81 m/s²


def _without_keyframes() -> mujoco.MjModel:
    """x2.xml as shipped less its <keyframe> element, compiled from its text and its assets' bytes."""
    text = (X2 / "x2.xml").read_text()
    stripped = re.sub(r"\s*<keyframe>.*?</keyframe>", "", text, flags=re.DOTALL)
    assert stripped != text and "<key " not in stripped
    assets = {p.name: p.read_bytes() for p in (X2 / "assets").iterdir()}
    return mujoco.MjModel.from_xml_string(stripped, assets)


def test_the_menagerie_x2_loads_as_shipped() -> None:
    model = load_mjcf(X2, entry="x2.xml", stabilise=False)
    m = model.mj_model
    assert model.name == "Skydio-X2"
    assert model.num_controls == 4 and model.state_size == 13  # a free body: 7 positions, 6 velocities
    assert sorted(model.asset_sources.values()) == [
        "assets/X2_lowpoly.obj",
        "assets/X2_lowpoly_texture_SpinningProps_1024.png",
    ]
    assert m.nmesh == 1 and m.mesh_vertnum[0] == 4303 and m.mesh_facenum[0] == 2554
    assert float(m.body_subtreemass[1]) == pytest.approx(MASS)
    assert float(MASS * -m.opt.gravity[2]) == pytest.approx(HOVER_THRUST * 4)


def test_its_scene_compiles_with_the_floor() -> None:
    m = mujoco.MjModel.from_xml_path(str(X2 / "scene.xml"))
    assert (m.nbody, m.nu, m.nkey) == (2, 4, 1)
    assert mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor") >= 0


def test_its_hover_keyframe_is_its_operating_point() -> None:
    found = operating.find(load_mjcf(X2, entry="x2.xml", stabilise=False).mj_model)
    assert found.source == "keyframe" and [k.name for k in found.points] == ["hover"]
    assert found.points[0].qpos[2] == pytest.approx(0.3)
    # the bundle's MJCF (MjSpec.to_xml) writes numbers to six significant digits: 3.24956
    np.testing.assert_allclose(found.points[0].ctrl, HOVER_THRUST, rtol=1e-5)


def test_without_its_keyframe_the_physics_finds_the_same_hover() -> None:
    m = _without_keyframes()
    assert m.nkey == 0
    u, need, left = operating.hold_controls(m)
    np.testing.assert_allclose(u, HOVER_THRUST, atol=1e-3)
    assert left <= operating.HOLD_RTOL * need + operating.HOLD_ATOL
    found = operating.find(m)
    assert found.source == "hold", found.reason
    np.testing.assert_allclose(found.points[0].ctrl, HOVER_THRUST, atol=1e-3)
