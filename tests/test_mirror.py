"""The mirror map: MuJoCo's step commutes with it for a symmetric figure, and an asymmetric one is
refused with the joint or body named."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.catalog.runner import data as runner_data
from neuroanimator.catalog.runner.body import runner
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.sim.mirror import MirrorError, check_mirror, mirror_map, partner_name, with_mirror_images
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import ModelError, PhysicalModel, derive_layout
from neuroanimator.sim.sampling import Examples
from neuroanimator.training.train import train


@pytest.fixture(scope="module")
def figure() -> PhysicalModel:
    return runner()


def test_partner_names() -> None:
    assert partner_name("left_hip_x") == "right_hip_x"
    assert partner_name("right_toe") == "left_toe"
    assert partner_name("waist_x") == "waist_x"


def test_the_runners_step_commutes_with_the_mirror(figure: PhysicalModel) -> None:
    mir = mirror_map(figure.mj_model, figure.layout, figure.spec.forces)
    ex = runner_data.examples(figure, figure.spec.substeps, 200, seed=4, progress=False)
    s, u, f = ex.states, ex.controls, ex.forces
    reflected = figure.step_held(mir.state(s), mir.controls(u), mir.forces(f), figure.spec.substeps)
    change = np.abs(ex.next_states - s).max()
    assert np.abs(reflected - mir.state(ex.next_states)).max() < 1e-8 * change
    # the left leg's angles become the right leg's, the sideways push changes sign, a roll joint flips
    labels = figure.layout.labels()
    assert np.array_equal(
        mir.state(s)[:, labels.index("right_knee.angle")], s[:, labels.index("left_knee.angle")]
    )
    assert np.array_equal(
        mir.state(s)[:, labels.index("waist_x.angle")], -s[:, labels.index("waist_x.angle")]
    )
    assert np.array_equal(mir.forces(f)[:, 1], -f[:, 1])
    # reflecting twice is the identity
    assert np.array_equal(mir.state(mir.state(s)), s)
    assert np.array_equal(mir.controls(mir.controls(u)), u)


_ARMS = """
<mujoco>
  <worldbody>
    <body name="torso">
      <freejoint/>
      <geom type="box" size="0.1 0.2 0.3" mass="10"/>
      <body name="left_arm" pos="0 0.25 0">
        <joint name="left_shoulder" axis="1 0 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.04" mass="{left}"/>
      </body>
      <body name="right_arm" pos="0 -0.25 0">
        <joint name="{right_joint}" axis="-1 0 0" damping="{damping}"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.04" mass="2"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="left_shoulder" joint="left_shoulder" ctrlrange="-1 1"/>
    <motor name="right_shoulder" joint="{right_joint}" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


def _xml(left: float = 2.0, right_joint: str = "right_shoulder", damping: float = 0.0) -> str:
    return _ARMS.format(left=left, right_joint=right_joint, damping=damping)


def _model(left: float = 2.0, right_joint: str = "right_shoulder") -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(_xml(left, right_joint))


def test_a_symmetric_xml_maps_its_arms_onto_each_other() -> None:
    m = _model()
    mir = mirror_map(m, derive_layout(m))
    # qpos: 7 of the free joint, then the two shoulders, swapped with the same sign (mirrored axes)
    assert mir.state_index[7:9].tolist() == [8, 7]
    assert mir.state_sign[7:9].tolist() == [1.0, 1.0]


@pytest.mark.parametrize(
    ("left", "right_joint", "named"),
    [(2.0, "right_elbow", "left_shoulder.*right_shoulder"), (3.0, "right_shoulder", "different masses")],
)
def test_an_asymmetric_figure_is_refused_by_name(left: float, right_joint: str, named: str) -> None:
    m = _model(left, right_joint)
    with pytest.raises(MirrorError, match=named):
        mirror_map(m, derive_layout(m))


def test_mirror_images_follow_their_transitions(figure: PhysicalModel) -> None:
    mir = mirror_map(figure.mj_model, figure.layout, figure.spec.forces)
    ex = runner_data.examples(figure, figure.spec.substeps, 50, seed=6, progress=False)
    both = with_mirror_images(mir, ex)
    assert len(both) == 100
    assert np.array_equal(both.states[0::2], ex.states)
    assert np.array_equal(both.next_states[1::2], mir.state(ex.next_states))
    assert np.array_equal(both.forces[1::2], mir.forces(ex.forces))


def test_training_with_mirror_images_refuses_a_model_that_is_not_symmetric() -> None:
    # the lander's thrusters act on sites, not joints: there is no mirror to take
    with pytest.raises(ModelError, match=r"not left-right symmetric.*main_jet.*does not act on a joint"):
        train(catalog.get("lander"), TrainConfig(examples=200, test_examples=50, mirror=True, progress=False))


def test_an_asymmetry_the_names_do_not_show_is_found_by_stepping(tmp_path: Path) -> None:
    """Partners with equal names, axes, anchors and masses but one joint damped: stepping the mirror
    images with MuJoCo finds it and names the joint."""
    for damping, symmetric in ((0.0, True), (5.0, False)):
        path = tmp_path / f"arms{damping}.xml"
        path.write_text(_xml(damping=damping))
        model = load_mjcf(path, substeps=10)
        mir = mirror_map(model.mj_model, model.layout, model.spec.forces)
        rng = np.random.default_rng(0)
        s = np.repeat(model.rest_state()[None], 8, axis=0)
        s[:, model.layout.labels().index("left_shoulder.rate")] = rng.normal(0, 2, 8)
        u = rng.uniform(-1, 1, (8, 2))
        nxt = model.step_held(s, u, None, 10)
        data = Examples(s, u, np.zeros((8, 0)), nxt)
        if symmetric:
            check_mirror(mir, model, data, 10)
        else:
            with pytest.raises(MirrorError, match="shoulder"):
                check_mirror(mir, model, data, 10)
