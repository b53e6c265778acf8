"""The runner: a human figure that the running controller keeps up, standing and running, on MuJoCo."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.catalog.runner import body as runner
from neuroanimator.catalog.runner import gait as runner_control

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


@pytest.fixture(scope="module")
def m() -> mujoco.MjModel:
    return catalog.get("runner").mj_model


def _standing_start(m: mujoco.MjModel) -> np.ndarray:
    d = mujoco.MjData(m)
    state = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(m, d, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    return state


def test_the_figure_is_a_70_kg_human_of_35_degrees_of_freedom(m: mujoco.MjModel) -> None:
    model = catalog.get("runner")
    assert m.nv == 35 and m.nu == 29
    assert (model.state_size, model.num_controls, model.num_forces) == (
        71,
        29,
        2,
    )  # a push on the torso, x and y
    assert model.control_names == list(runner.JOINTS)
    assert m.body_subtreemass[1] == pytest.approx(70.0, abs=0.05)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    top = d.geom("head").xpos[2] + m.geom("head").size[0]
    assert top == pytest.approx(1.75, abs=0.02)
    feet = [d.geom(f"{side}_foot").xpos[2] - m.geom(f"{side}_foot").size[2] for side in runner.SIDES]
    np.testing.assert_allclose(feet, 0.0, atol=1e-9)  # the rest pose stands on the floor


def test_the_controller_keeps_the_figure_standing_for_5_s(m: mujoco.MjModel) -> None:
    result = runner_control.run(m, _standing_start(m), 0.0, 5.0)
    assert not result.fell.any()
    pelvis = result.final_qpos[0]
    assert pelvis[2] > 0.9
    assert np.hypot(pelvis[0], pelvis[1]) < 0.1  # stood on the spot
    assert abs(pelvis[3]) > 0.99  # upright: the quaternion is near identity


def test_contact_forces_appear_in_the_data(m: mujoco.MjModel) -> None:
    """Standing, the feet carry the body's weight; running, they take turns and both leave the floor."""
    standing = runner_control.run(m, _standing_start(m), 0.0, 1.0)
    touch = runner_control.RunnerController(m).feet_touch(standing.sensordata[0, -10:])
    weight = 70.0 * 9.81
    np.testing.assert_allclose(touch.sum(axis=1), weight, rtol=0.05)
    assert np.all(touch > 0.2 * weight)  # both feet bear part of it
    running = runner_control.run(m, runner_control.running_start(m, 2.5), 2.5, 3.0)
    touch = runner_control.RunnerController(m).feet_touch(running.sensordata[0])
    down = touch > 10.0
    assert (down[:, 0] & ~down[:, 1]).mean() > 0.1  # left alone on the floor
    assert (down[:, 1] & ~down[:, 0]).mean() > 0.1  # right alone
    assert touch.max() > 1.5 * weight  # running impacts exceed the weight


def test_a_short_run_stays_upright_and_moves_forward(m: mujoco.MjModel) -> None:
    result = runner_control.run(m, runner_control.running_start(m, 2.5), 2.5, 4.0)
    assert not result.fell.any()
    q = result.final_qpos[0]
    assert q[0] > 4.0 * 1.6  # at least 1.6 m/s on average, from the start
    assert abs(q[1]) < 1.5  # kept its heading
    up = runner_control.Attitude.of(q[None], np.zeros((1, m.nv)), np.zeros((1, 3)))
    assert abs(up.pitch[0]) < 0.6 and abs(up.roll[0]) < 0.4


def test_the_gait_stays_up_from_perturbed_starts(m: mujoco.MjModel) -> None:
    """The running loop is chaotic: a gait that runs from one start can fall from a start 0.01 m/s away.
    The default gait keeps running from perturbed starts, with the controller as on the emulator
    (every 6 physical steps, kinematic sensors), at a speed between two trained ones and at one of them."""
    rng = np.random.default_rng(3)
    for speed in (2.0, 2.2):
        start = runner_control.perturbed_starts(m, speed, 8, rng)
        result = runner_control.run(m, start, speed, 12.0, control_every=6, kinematic=True, record=False)
        assert not result.fell.any(), f"fell at {result.fell_at[result.fell]} s at {speed} m/s"
        assert np.all(result.final_qpos[:, 0] > 12.0 * 1.5)  # kept running forward


def test_runs_in_a_batch_equal_runs_alone(m: mujoco.MjModel) -> None:
    """Data generation steps many runs at once; each run of a batch is the run it would be alone."""
    start = runner_control.running_start(m, 2.0)
    both = runner_control.run(m, start, np.array([2.0, 3.0]), 0.5)
    alone = runner_control.run(m, start, 3.0, 0.5)
    np.testing.assert_array_equal(both.states[1], alone.states[0])
    np.testing.assert_array_equal(both.controls[1], alone.controls[0])
    assert not np.array_equal(both.states[0], both.states[1])


def test_the_control_period_is_a_parameter(m: mujoco.MjModel) -> None:
    seconds = 60 * 6 * m.opt.timestep  # 60 control periods of 6 steps
    fine = runner_control.run(m, _standing_start(m), 0.0, seconds, control_every=1)
    coarse = runner_control.run(m, _standing_start(m), 0.0, seconds, control_every=6)
    assert (fine.states.shape[1], coarse.states.shape[1]) == (360, 60)
    assert fine.dt == pytest.approx(m.opt.timestep)
    assert not (fine.fell.any() or coarse.fell.any())


def test_a_push_moves_the_torso(m: mujoco.MjModel) -> None:
    start = _standing_start(m)
    push = runner_control.Push(force=(0.0, 150.0, 0.0), start_s=0.2, duration_s=0.1)
    pushed = runner_control.run(m, start, 0.0, 0.4, push=push)
    still = runner_control.run(m, start, 0.0, 0.4)
    assert pushed.final_qpos[0, 1] - still.final_qpos[0, 1] > 0.005  # pushed along +y (leftwards)


def test_kinematic_sensors_read_what_mujoco_reads_and_the_feet_as_mujoco_touches_them(
    m: mujoco.MjModel,
) -> None:
    """The controller's readings from positions and velocities alone (what an emulated state offers):
    every kinematic sensor exactly, and each foot down at the same physical steps as its touch sensor
    nearly always."""
    result = runner_control.run(m, runner_control.running_start(m, 2.0), 2.0, 2.0, control_every=1)
    st = result.states[0, :-1]
    sensors = runner_control.KinematicSensors(m)
    read = sensors.read(st[:, 1 : 1 + m.nq], st[:, 1 + m.nq : 1 + m.nq + m.nv])
    true = result.sensordata[0, 1:]  # a step's sensors are those of the state it started from
    touch = sorted(sensors.touch_at.values())
    kinematic = np.setdiff1d(np.arange(m.nsensordata), touch)
    np.testing.assert_allclose(read[:, kinematic], true[:, kinematic], atol=1e-9)
    ctl = runner_control.RunnerController(m)
    down_read, down_true = ctl.feet_touch(read) > 50.0, ctl.feet_touch(true) > 50.0
    assert (down_read == down_true).mean() > 0.97
    assert down_true[:, 0].any() and down_true[:, 1].any()


def test_noise_and_per_run_pushes_perturb_the_runs(m: mujoco.MjModel) -> None:
    start = runner_control.running_start(m, 2.0)
    plain = runner_control.run(m, start, np.array([2.0, 2.0]), 0.3, control_every=6, kinematic=True)
    np.testing.assert_array_equal(plain.states[0], plain.states[1])
    push = runner_control.Push(
        force=np.array([[0.0, 0.0, 0.0], [0.0, 200.0, 0.0]]), start_s=0.0, duration_s=0.2
    )
    pushed = runner_control.run(
        m, start, np.array([2.0, 2.0]), 0.3, control_every=6, kinematic=True, push=push
    )
    np.testing.assert_array_equal(pushed.states[0], plain.states[0])  # run 0 had no push
    assert pushed.final_qpos[1, 1] - plain.final_qpos[1, 1] > 0.005  # run 1 went leftwards
    noisy = runner_control.run(
        m, start, 2.0, 0.3, control_every=6, kinematic=True, control_noise=0.05, seed=1
    )
    assert not np.array_equal(noisy.controls[0], plain.controls[0])
    again = runner_control.run(
        m, start, 2.0, 0.3, control_every=6, kinematic=True, control_noise=0.05, seed=1
    )
    np.testing.assert_array_equal(noisy.states, again.states)  # the noise comes from the seed


def test_training_data_come_from_running_its_neighbourhood_and_pushes() -> None:
    from neuroanimator.catalog.runner import data as runner_data

    model = catalog.get("runner")
    ex = runner_data.examples(model, 6, 600, seed=2, progress=False)
    assert ex.states.shape == (600, 71) and ex.forces.shape == (600, 2)
    ex.check_finite()
    speed = ex.states[:, model.layout.slice_of("root.vel").start]
    assert np.median(speed) > 1.0  # running forward
    z = ex.states[:, model.layout.slice_of("root.pos").start + 2]
    assert z.min() > 0.55  # nothing from after a fall
    runs = runner_data._batch(model, 6, np.random.default_rng(0))
    pushed = np.any(np.abs(runs.forces) > 0, axis=2)  # (R, T)
    assert 0 < pushed.any(axis=1).sum() < runs.forces.shape[0]  # some runs are pushed, not all
    periods = runner_data.PUSH_S / (6 * model.dt)  # 0.2 s: 12 or 13 control periods, by when it starts
    counts = pushed.sum(axis=1)
    assert set(counts[counts > 0]) <= {math.floor(periods), math.ceil(periods)}
    first = pushed.argmax(axis=1)[pushed.any(axis=1)]
    assert len(set(first)) > 1  # each run is pushed at its own time
    kicked = runs.states[:, 1:] - runs.ends[:, :-1]  # each period starts a little off where the last ended
    assert np.abs(kicked).max() > 0


def test_rollout_windows_replayed_open_loop_are_the_runs_they_came_from(m: mujoco.MjModel) -> None:
    """A window of a closed-loop run, its servo targets and pushes replayed without the controller,
    is the same window: what training over rollouts compares the emulator with."""
    from neuroanimator.catalog.runner import data as runner_data

    model = catalog.get("runner")
    seq = runner_data.sequences(model, 6, 8, 4, seed=3, progress=False)
    assert (
        seq.states.shape == (8, 5, 71) and seq.controls.shape == (8, 4, 29) and seq.forces.shape == (8, 4, 2)
    )
    u = np.repeat(seq.controls, 6, axis=1)
    f = np.repeat(seq.forces, 6, axis=1)
    replay = model.simulate(seq.states[:, 0], u, f)[:, 5::6]
    # equal but for the constraint solver's warm start, which a state does not carry
    np.testing.assert_allclose(replay, seq.states[:, 1:], atol=1e-4)
