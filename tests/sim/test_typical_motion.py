"""Typical motion around a model's operating point: starts, controls, the operating spec's checks,
diverged runs dropped or narrowed around the point, spin-up seen (models nobody here wrote)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from neuroanimator.core.operating_spec import OperatingSpec
from neuroanimator.sim import sampling
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import SimulationDiverged
from neuroanimator.sim.operating import OperatingSpecError
from neuroanimator.training.motion import cut_spin_up, fastest_motion

DATA = Path(__file__).resolve().parents[1] / "data"
SUITE = Path(str(importlib.util.find_spec("dm_control").origin)).parent / "suite"  # type: ignore[union-attr]
HOVER = 3.24956  # the X2's hover keyframe's thrust, as its MJCF is read back (6 significant digits)


def _x2(spec: OperatingSpec | None = None, keyframe: str | None = None, stabilise: bool = False):
    return load_mjcf(
        DATA / "skydio_x2", entry="x2.xml", operating_spec=spec, keyframe=keyframe, stabilise=stabilise
    )


def test_a_drone_with_a_hover_keyframe_is_driven_around_its_hover() -> None:
    model = _x2()
    op = model.spec.operating
    assert op is not None and op.source == "keyframe" and op.keyframes == ["hover"]
    assert np.allclose(op.control_centres, [[HOVER] * 4])
    assert np.allclose(op.control_spread, 0.05 * 13.0)  # ±5 % of the 0-13 range
    rng = np.random.default_rng(0)
    u = model.typical_controls(rng, 200, np.arange(300) * model.dt)  # (200, 300, 4)
    assert u.min() >= HOVER - 0.65 - 1e-9 and u.max() <= HOVER + 0.65 + 1e-9
    held = np.all(u == u[:, :1, :1], axis=(1, 2))  # every control of the run at the hover thrust
    assert 0.1 < held.mean() < 0.3 and np.allclose(u[held], HOVER)
    starts = model.initial_states(rng, 400)
    key = np.asarray(model.spec.initial.centres[0])
    level = np.all(np.abs(starts[:, 4:6]) < 1e-12, axis=1)  # the quaternion turned about z only (yaw)
    exact = level & np.all(starts[:, 7:] == key[7:], axis=1)
    assert 0.1 < exact.mean() < 0.3
    assert np.abs(starts[:, 7:] - key[7:]).max() <= 0.3 + 1e-9  # velocities within their spread


def test_the_spec_sets_bands_time_scale_and_run_length() -> None:
    spec = OperatingSpec.model_validate(
        {
            "controls": {"thrust1": {"range": [3, 4]}, "thrust2": {"spread": 0.1}},
            "control_spread": 0.02,
            "time_scale_s": 0.5,
            "run_s": 3,
            "held_share": 0,
            "start": {"velocity_spread": 0.1, "tilt": 0.05},
        }
    )
    model = _x2(spec)
    op = model.spec.operating
    assert op is not None and op.source == "keyframe" and op.spec == spec
    assert op.control_centres == [[3.5, HOVER, HOVER, HOVER]]
    assert np.allclose(op.control_spread, [0.5, 0.1, 0.26, 0.26])
    assert model.spec.episode_s == 3 and model.spec.control_spacing_s == 0.5 and op.held_share == 0
    assert model.spec.initial.max_tilt == 0.05 and max(model.spec.initial.high) == pytest.approx(0.1)
    assert np.allclose(model.control_range[0], [3, 4])


@pytest.mark.parametrize(
    ("spec", "keyframe", "field", "said"),
    [
        ({"controls": {"thrust9": {"centre": 3}}}, None, "controls.thrust9", "thrust1"),
        ({"controls": {"thrust1": {"range": [0, 20]}}}, None, "controls.thrust1", r"ctrlrange \[0, 13\]"),
        ({"controls": {"thrust1": {"centre": 12.5, "spread": 1}}}, None, "controls.thrust1", "outside"),
        ({"keyframe": "cruise"}, None, "keyframe", "'hover'"),
        ({}, "cruise", "keyframe", "'hover'"),
        ({"keyframe": "hover"}, "landing", "keyframe", "differ"),
        ({"start": {"joints": {"elbow": 0.1}}}, None, "start.joints.elbow", "no joint 'elbow'"),
    ],
)
def test_a_spec_that_does_not_fit_the_model_names_the_field(
    spec: dict[str, object], keyframe: str | None, field: str, said: str
) -> None:
    with pytest.raises(OperatingSpecError, match=said) as caught:
        _x2(OperatingSpec.model_validate(spec), keyframe)
    assert caught.value.field == field and field in str(caught.value)


def test_a_model_without_an_operating_point_is_sampled_as_before() -> None:
    """dm_control's cartpole: no keyframe, nothing to hold at qpos0: controls over the whole range from
    ±0.3 around qpos0 (the suite's results stand)."""
    model = load_mjcf(SUITE / "cartpole.xml", stabilise=False)
    op = model.spec.operating
    assert op is not None and op.source == "none" and not op.control_centres and op.held_share == 0
    assert not model.spec.initial.centres
    assert model.spec.initial.high == [0.3] * model.state_size
    assert np.allclose(model.control_range, [[-1, 1]])


def test_runs_that_diverge_are_dropped_and_counted(tmp_path: Path) -> None:
    """A hinge whose starts sit now and then against a stiffness it cannot simulate (unactuated: at rest it
    stays put): those runs are dropped and counted, the rest sampled; where many are, sampling stops and
    says so."""
    path = tmp_path / "stiff.xml"
    path.write_text(
        """<mujoco model="stiff"><option timestep="0.01"/><worldbody><body>
        <joint name="stiff" type="hinge" axis="0 0 1" stiffness="1e9"/>
        <geom type="sphere" size="0.1" mass="1e-6"/></body></worldbody></mujoco>"""
    )
    model = load_mjcf(path, substeps=5, stabilise=False)
    zero = np.zeros(model.state_size)
    pushed = zero.copy()
    pushed[0] = 1.0  # against a stiffness of 1e9: MuJoCo gives up at once
    init = model.spec.initial.model_copy(
        update={"centres": [zero.tolist()] * 39 + [pushed.tolist()], "low": [], "high": []}
    )
    model.spec = model.spec.model_copy(update={"initial": init})
    runs = sampling.generate_sequences(model, 5, 400, 4, seed=0, progress=False)
    assert len(runs) == 400 and 0 < runs.diverged < 0.05 * 420
    assert np.abs(runs.states).max() < 1.0  # none of the diverged runs' states kept
    init = init.model_copy(update={"centres": [zero.tolist(), pushed.tolist()]})
    model.spec = model.spec.model_copy(update={"initial": init})
    with pytest.raises(SimulationDiverged, match=r"joint 'stiff'.*diverged in \d+ of \d+ runs"):
        sampling.generate_sequences(model, 5, 400, 4, seed=0, progress=False)


def test_motion_that_diverges_is_narrowed_around_the_operating_point(tmp_path: Path) -> None:
    """A spring pushed by up to 3 kN: most runs overrun a thousand times their start; a quarter of the
    push is simulated, and the record says so."""
    path = tmp_path / "spring.xml"
    path.write_text(
        """<mujoco model="spring"><option timestep="0.01"/><worldbody><body>
        <joint name="slide" type="slide" axis="1 0 0" stiffness="1" damping="1"/>
        <geom type="sphere" size="0.1" mass="1"/></body></worldbody>
        <actuator><motor name="push" joint="slide" ctrlrange="-3000 3000"/></actuator></mujoco>"""
    )
    model = load_mjcf(path)
    op = model.spec.operating
    assert op is not None and op.narrowed is not None and "0.25×" in op.narrowed
    assert np.allclose(model.control_range, [[-750, 750]])


def test_a_drone_driven_around_its_hover_is_seen_to_spin_up_and_its_runs_are_cut() -> None:
    model = _x2()
    motion = fastest_motion(model)
    seen = motion.spin_up()
    assert motion.group == "joint0.angvel" and seen is not None and "spins up" in seen[1]
    said = cut_spin_up(model, motion, 10)
    assert said is not None and "runs cut to" in said and model.spec.episode_s < 20
    pendulum = load_mjcf(SUITE / "pendulum.xml", stabilise=False)
    assert fastest_motion(pendulum).spin_up() is None  # no free body: nothing to tumble


def test_an_arm_starts_around_its_home_with_a_spread_per_joint() -> None:
    """Menagerie's UR5e: its home keyframe, and a spec that lets its wrist turn further than the rest."""
    spec = OperatingSpec.model_validate({"start": {"joints": {"wrist_3_joint": 0.5}}})
    model = load_mjcf(DATA / "universal_robots_ur5e", entry="ur5e.xml", operating_spec=spec, stabilise=False)
    op = model.spec.operating
    assert op is not None and op.source == "keyframe" and op.keyframes == ["home"]
    wrist = model.layout.slice_of("wrist_3_joint.angle")
    high = np.asarray(model.spec.initial.high)
    assert high[wrist] == [0.5] and np.allclose(np.delete(high[: model.state_size // 2], wrist), 0.1)


def test_a_divergence_mujoco_did_not_place_names_the_joint_whose_state_blew_up(tmp_path: Path) -> None:
    """A run caught by its values (MuJoCo named no degree of freedom) still names the joint to fix."""
    path = tmp_path / "stiff.xml"
    path.write_text(
        """<mujoco model="stiff"><option timestep="0.01"/><worldbody><body>
        <joint name="stiff" type="hinge" axis="0 0 1" stiffness="1e9"/>
        <geom type="sphere" size="0.1" mass="1e-6"/></body></worldbody></mujoco>"""
    )
    model = load_mjcf(path, substeps=5, stabilise=False)
    start = np.zeros((2, model.state_size))
    traj = np.zeros((2, 3, model.state_size))
    traj[1, 1, 1] = np.nan  # the hinge's rate, at the second step
    err = model._diverged(start, traj, -1)
    assert "joint 'stiff'" in str(err) and "0.02 s into" in str(err)
    # reset by MuJoCo before any value grew: the step where it was seen, and still the joint
    err = model._diverged(start, np.zeros((2, 3, model.state_size)), -1, step=1)
    assert "joint 'stiff'" in str(err) and "0.02 s into" in str(err)
