"""A user's own MJCF file -> PhysicalModel."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from neuroanimator.cli import main
from neuroanimator.sim import sampling
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import ModelError, SimulationDiverged

FREE_BODY = """<mujoco>
  <option gravity="0 0 -9.81"/>
  <worldbody>
    <body name="puck" pos="0 0 1">
      <joint name="root" type="free"/>
      <geom name="puck_geom" type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="lift" joint="root" gear="0 0 1 0 0 0"/>
  </actuator>
</mujoco>
"""


def test_name_comes_from_model_attribute(arm_path: Path) -> None:
    assert load_mjcf(arm_path).name == "myarm"


def test_name_falls_back_to_file_stem(tmp_path: Path) -> None:
    path = tmp_path / "floating_puck.xml"
    path.write_text(FREE_BODY)
    assert load_mjcf(path).name == "floating_puck"


def test_hinge_joints_give_angle_and_rate_groups(arm_path: Path) -> None:
    model = load_mjcf(arm_path)
    kinds = [(g.name, g.kind, g.size, g.source) for g in model.layout]
    assert kinds == [
        ("shoulder.angle", "angle", 1, "qpos"),
        ("elbow.angle", "angle", 1, "qpos"),
        ("shoulder.rate", "scalar", 1, "qvel"),
        ("elbow.rate", "scalar", 1, "qvel"),
    ]
    assert model.state_size == 4


def test_controls_and_ranges_come_from_actuators(arm_path: Path) -> None:
    model = load_mjcf(arm_path)
    assert model.control_names == ["shoulder_motor", "elbow_motor"]
    np.testing.assert_allclose(model.control_range, [[-3.0, 3.0], [-1.5, 2.0]])
    np.testing.assert_allclose(model.control_limits, [[-3.0, 3.0], [-1.5, 2.0]])
    assert model.num_forces == 0


def test_substeps_and_timestep_are_taken_over(arm_path: Path) -> None:
    model = load_mjcf(arm_path, substeps=12)
    assert model.spec.substeps == 12
    assert model.dt == pytest.approx(0.005)


def test_user_model_simulates_and_samples(arm_path: Path) -> None:
    model = load_mjcf(arm_path)
    rng = np.random.default_rng(0)
    s0 = model.initial_states(rng, 3)
    assert s0.shape == (3, 4)
    assert not np.allclose(s0, 0.0)
    u = model.typical_controls(rng, 3, np.arange(200.0) * model.dt)
    assert np.all(np.isfinite(model.simulate(s0, u)))


def test_free_joint_gives_root_groups(tmp_path: Path) -> None:
    path = tmp_path / "puck.xml"
    path.write_text(FREE_BODY)
    model = load_mjcf(path)
    assert [(g.name, g.kind, g.size) for g in model.layout] == [
        ("root.pos", "position", 3),
        ("root.quat", "quaternion", 4),
        ("root.vel", "world_vector", 3),
        ("root.angvel", "local_vector", 3),
    ]
    assert model.frame.rotate  # gravity along z: rotation about z is a symmetry
    assert model.frame.translate == (True, True, True)  # nothing collides with the world
    q = model.initial_states(np.random.default_rng(1), 5)[:, model.layout.slice_of("root.quat")]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)


def test_floor_breaks_vertical_translation(tmp_path: Path) -> None:
    path = tmp_path / "puck_floor.xml"
    path.write_text(
        FREE_BODY.replace("<worldbody>", '<worldbody>\n    <geom name="floor" type="plane" size="5 5 0.1"/>')
    )
    assert load_mjcf(path).frame.translate == (True, True, False)


def test_tilted_gravity_breaks_rotation(tmp_path: Path) -> None:
    path = tmp_path / "puck_tilted.xml"
    path.write_text(FREE_BODY.replace('gravity="0 0 -9.81"', 'gravity="1 0 -9.81"'))
    assert not load_mjcf(path).frame.rotate


def test_malformed_xml_raises_model_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.xml"
    path.write_text('<mujoco model="broken"><worldbody><body name="b">')
    with pytest.raises(ModelError, match=r"broken\.xml is not XML"):
        load_mjcf(path)


def test_invalid_mujoco_content_raises_model_error(tmp_path: Path) -> None:
    path = tmp_path / "bad_element.xml"
    path.write_text('<mujoco model="bad"><worldbody><bogus/></worldbody></mujoco>')
    with pytest.raises(
        ModelError, match=r"MuJoCo cannot load the model: bad_element.xml, line 1 \(<bogus>\)"
    ):
        load_mjcf(path)


def test_wrong_root_element_raises_model_error(tmp_path: Path) -> None:
    path = tmp_path / "notmujoco.xml"
    path.write_text("<robot><link/></robot>")
    with pytest.raises(ModelError, match="<mujoco>"):
        load_mjcf(path)


def test_missing_file_raises_model_error(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="does not exist"):
        load_mjcf(tmp_path / "nowhere.xml")


def test_model_without_joints_raises_model_error(tmp_path: Path) -> None:
    path = tmp_path / "static.xml"
    path.write_text('<mujoco><worldbody><geom type="sphere" size="1"/></worldbody></mujoco>')
    with pytest.raises(ModelError, match="no joints"):
        load_mjcf(path)


def test_a_missing_mesh_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / "mesh.xml"
    path.write_text('<mujoco><asset><mesh name="m" file="m.stl"/></asset><worldbody/></mujoco>')
    with pytest.raises(ModelError, match=r"mesh 'm' file 'm\.stl' is missing"):
        load_mjcf(path)


def test_ball_and_slide_joints_give_their_groups(tmp_path: Path) -> None:
    path = tmp_path / "joints.xml"
    path.write_text(
        """<mujoco model="joints">
  <worldbody>
    <body name="cart">
      <joint name="rail" type="slide" axis="1 0 0"/>
      <geom name="cart_geom" type="box" size="0.2 0.1 0.1" mass="1"/>
      <body name="bob" pos="0 0 -0.5">
        <joint name="socket" type="ball"/>
        <geom name="bob_geom" type="sphere" size="0.1" mass="1"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""
    )
    model = load_mjcf(path)
    assert [(g.name, g.kind, g.size, g.source, g.address) for g in model.layout] == [
        ("rail.pos", "scalar", 1, "qpos", 0),
        ("socket.quat", "local_quaternion", 4, "qpos", 1),
        ("rail.vel", "scalar", 1, "qvel", 0),
        ("socket.angvel", "local_vector", 3, "qvel", 1),
    ]
    assert model.num_controls == 0
    assert not model.frame.rotate and model.frame.translate == ()


def test_actuators_without_ctrlrange_are_named_with_the_range_assumed(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "free.xml"
    path.write_text(
        """<mujoco model="loose"><worldbody><body><joint name="j" type="hinge"/>
        <geom type="sphere" size="0.1"/></body></worldbody>
        <actuator><motor name="push" joint="j" ctrllimited="false"/><motor name="held" joint="j" ctrlrange="-2 2"/>
        </actuator></mujoco>"""
    )
    with caplog.at_level(logging.WARNING):
        model = load_mjcf(path)
    assert "push" in caplog.text and "held" not in caplog.text and "[-1, 1]" in caplog.text
    np.testing.assert_allclose(model.control_range, [[-1.0, 1.0], [-2.0, 2.0]])


def test_a_model_that_diverges_is_refused_with_the_time_and_joint(tmp_path: Path) -> None:
    """Training data of an unstable model: the error says when and at which joint, nothing is written."""
    path = tmp_path / "unstable.xml"
    path.write_text(
        """<mujoco model="unstable"><option timestep="0.05"/><worldbody><body>
        <joint name="stiff" type="hinge" axis="0 0 1" stiffness="1e9"/>
        <geom type="capsule" fromto="0 0 0 1 0 0" size="0.05"/></body></worldbody>
        <actuator><motor name="m" joint="stiff" ctrlrange="-1 1"/></actuator></mujoco>"""
    )
    out = tmp_path / "artifacts"
    said = r"diverged .* s into .*joint 'stiff'.*smaller timestep.*Narrowing .* did not help.*0.125× the spread: 64"
    with pytest.raises(SimulationDiverged, match=said):  # refused as it is read, saying what was tried
        load_mjcf(path, substeps=5)
    model = load_mjcf(path, substeps=5, stabilise=False)
    with pytest.raises(SimulationDiverged, match=r"diverged .* s into .*joint 'stiff'.*smaller timestep"):
        sampling.generate(model, 5, 50, seed=0, progress=False)
    assert main(["train", "--mjcf", str(path), "--substeps", "5", "--out", str(out), "--quiet"]) == 2
    assert not out.exists()


def test_one_unstable_run_among_stable_ones_is_caught_wherever_it_runs(tmp_path: Path) -> None:
    """MuJoCo resets an unstable run, and rollout clears a thread's warnings before each of its runs:
    a run that diverges before others on its thread is caught from its reset clock, naming the joint
    (dm_control's dog: a few runs of thousands sampled their reset poses as data before)."""
    path = tmp_path / "stiff.xml"
    path.write_text(
        """<mujoco model="stiff"><option timestep="0.01"/><worldbody><body>
        <joint name="stiff" type="hinge" axis="0 0 1" stiffness="1e9"/>
        <geom type="sphere" size="0.1" mass="1e-6"/></body></worldbody>
        <actuator><motor name="m" joint="stiff" ctrlrange="-1 1"/></actuator></mujoco>"""
    )
    model = load_mjcf(path, substeps=5, stabilise=False)  # (refused when read: see above)
    states = np.zeros((8, model.state_size))
    assert np.isfinite(model.simulate(states, nstep=20, check=True)).all()  # at rest: stable
    for first in (0, 3, 7):  # first, in the middle, last (the case the warnings alone caught)
        pushed = states.copy()
        pushed[first, 0] = 1.0  # one run displaced against a stiffness of 1e9
        with pytest.raises(SimulationDiverged, match=r"diverged 0.01 s into .*joint 'stiff'"):
            model.simulate(pushed, nstep=20, check=True)
        assert model.simulate(pushed, nstep=20).shape == (
            8,
            20,
            model.state_size,
        )  # unchecked: as MuJoCo gives


def test_an_arena_too_small_for_the_contacts_is_named(tmp_path: Path) -> None:
    """Two boxes stacked on a floor in an MJCF that gives MuJoCo 12 KB: stepping them overflows its
    arena. On the calling thread that is a ``ModelError`` naming the arena and what to give the MJCF,
    not a crash (rollout's worker threads still end the process: MuJoCo's error there is fatal)."""
    path = tmp_path / "stack.xml"
    path.write_text(
        """<mujoco model="stack"><size memory="12K"/><worldbody><geom type="plane" size="5 5 .1"/>
        <body pos="0 0 0.05"><joint name="lift" type="slide" axis="0 0 1"/><geom type="box" size=".2 .2 .05"/></body>
        <body pos="0 0 0.16"><freejoint/><geom type="box" size=".2 .2 .05"/></body></worldbody>
        <actuator><motor name="m" joint="lift" ctrlrange="-1 1"/></actuator></mujoco>"""
    )
    model = load_mjcf(path, substeps=10, stabilise=False)
    rest = np.repeat(model.rest_state()[None], 4, axis=0)
    with pytest.raises(ModelError, match=r"ran out of arena memory \(12,288 bytes\).*<size memory="):
        model.simulate(rest, nstep=50, check=True, threads=1)
    path.write_text(path.read_text().replace('memory="12K"', 'memory="1M"'))
    roomy = load_mjcf(path, substeps=10)
    assert np.isfinite(roomy.simulate(rest, nstep=50, check=True)).all()


def test_velocities_too_violent_for_a_small_model_are_narrowed_until_it_samples(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """dm_control's fish (10 cm in water 5 times denser than ours) diverges from ±0.3 m/s: the typical
    initial velocities shrink, with a warning saying so, and sampling from them stays stable."""
    suite = pytest.importorskip("dm_control.suite")
    with caplog.at_level(logging.WARNING):
        fish = load_mjcf(Path(suite.__file__).parent / "fish.xml")
    assert "typical initial velocities narrowed" in caplog.text
    assert "MuJoCo:" not in caplog.text  # the probe's expected instabilities are not warnings
    velocity = [sl for g, sl in fish.layout.group_slices() if g.source == "qvel"]
    high = np.asarray(fish.spec.initial.high)
    assert all(0.0 <= v < 0.3 for sl in velocity for v in high[sl])
    hinges = [sl for g, sl in fish.layout.group_slices() if g.kind == "angle"]
    assert all(v == 0.3 for sl in hinges for v in high[sl])  # positions keep their spread
    data = sampling.generate(fish, 50, 3000, seed=1, progress=False)
    data.check_finite()


def test_a_model_stable_at_the_default_spread_keeps_it(arm_path: Path) -> None:
    arm = load_mjcf(arm_path)
    velocity = [sl for g, sl in arm.layout.group_slices() if g.source == "qvel"]
    assert all(arm.spec.initial.high[i] == 0.3 for sl in velocity for i in range(sl.start, sl.stop))
