"""The runner: a human figure that the running controller keeps up, standing and running, on MuJoCo."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from neuroanimator import physics
from neuroanimator.physics import runner, runner_control

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


@pytest.fixture(scope="module")
def m() -> mujoco.MjModel:
    return physics.get("runner").mj_model


def _standing_start(m: mujoco.MjModel) -> np.ndarray:
    d = mujoco.MjData(m)
    state = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(m, d, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    return state


def test_the_figure_is_a_70_kg_human_of_35_degrees_of_freedom(m: mujoco.MjModel) -> None:
    model = physics.get("runner")
    assert m.nv == 35 and m.nu == 29
    assert (model.state_size, model.num_controls, model.num_forces) == (71, 29, 0)
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
