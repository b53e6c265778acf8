"""The suite tasks' rewards in torch equal dm_control's own reward code run on MuJoCo's data, their
starts follow the suite's ``initialize_episode``, and the kinematics under them equal MuJoCo's."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch
from dm_control.utils import rewards as suite_rewards

from neuroanimator.control.kinematics import Kinematics
from neuroanimator.control.suite_tasks import SUITE_TASKS, Context, SuiteTask, shaped, tolerance
from neuroanimator.core.state import LayoutGroup
from tests.helpers import mj_state, mjcf_model


def _ids(m: mujoco.MjModel, kind: mujoco.mjtObj, name: str) -> int:
    return mujoco.mj_name2id(m, kind, name)


def _sensor(m: mujoco.MjModel, d: mujoco.MjData, name: str) -> np.ndarray:
    i = _ids(m, mujoco.mjtObj.mjOBJ_SENSOR, name)
    return np.array(d.sensordata[m.sensor_adr[i] : m.sensor_adr[i] + m.sensor_dim[i]])


def reference(task: str, m: mujoco.MjModel, d: mujoco.MjData, params: np.ndarray) -> float:
    """The suite's ``get_reward`` for the task, its quantities read from MuJoCo's own data as the
    suite's ``Physics`` helpers read them (sensors included), through ``dm_control.utils.rewards.tolerance``."""
    body, site, geom = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_GEOM
    tol = suite_rewards.tolerance
    domain = task.split("-")[0]
    small_control = (tol(d.ctrl, margin=1, value_at_margin=0, sigmoid="quadratic").mean() + 4) / 5
    if domain == "hopper":
        height = d.xipos[_ids(m, body, "torso"), 2] - d.xipos[_ids(m, body, "foot"), 2]
        return float(tol(height, (0.6, 2)) * small_control)
    if domain == "walker":
        torso = _ids(m, body, "torso")
        standing = tol(d.xpos[torso, 2], bounds=(1.2, float("inf")), margin=0.6)
        stand = (3 * standing + (1 + d.xmat[torso, 8]) / 2) / 4
        if task == "walker-stand":
            return float(stand)
        vx = _sensor(m, d, "torso_subtreelinvel")[0]
        move = tol(vx, bounds=(1, float("inf")), margin=0.5, value_at_margin=0.5, sigmoid="linear")
        return float(stand * (5 * move + 1) / 6)
    if domain == "humanoid":
        standing = tol(d.xpos[_ids(m, body, "head"), 2], bounds=(1.4, float("inf")), margin=1.4 / 4)
        upright = tol(
            d.xmat[_ids(m, body, "torso"), 8], (0.9, float("inf")), 1.9, "linear", value_at_margin=0
        )
        still = tol(_sensor(m, d, "torso_subtreelinvel")[[0, 1]], margin=2).mean()
        return float(small_control * standing * upright * still)
    if domain == "cheetah":
        vx = _sensor(m, d, "torso_subtreelinvel")[0]
        return float(tol(vx, bounds=(10, float("inf")), margin=10, value_at_margin=0, sigmoid="linear"))
    if domain == "cartpole":
        upright = (d.xmat[_ids(m, body, "pole_1"), 8] + 1) / 2
        centered = (1 + tol(d.qpos[0], margin=2)) / 2
        control = (4 + tol(d.ctrl, margin=1, value_at_margin=0, sigmoid="quadratic")[0]) / 5
        velocity = (1 + tol(d.qvel[1:], margin=5).min()) / 2
        return float(upright * control * velocity * centered)
    if domain == "pendulum":
        return float(tol(d.xmat[_ids(m, body, "pole"), 8], (np.cos(np.deg2rad(8)), 1)))
    if domain == "reacher":
        finger = _ids(m, geom, "finger")
        return float(
            tol(np.linalg.norm(params - d.geom_xpos[finger, :2]), (0, 0.015 + m.geom_size[finger, 0]))
        )
    if domain == "point_mass":
        target, mass = _ids(m, geom, "target"), _ids(m, geom, "pointmass")
        size = m.geom_size[target, 0]
        near = tol(np.linalg.norm(d.geom_xpos[target] - d.geom_xpos[mass]), bounds=(0, size), margin=size)
        control = tol(d.ctrl, margin=1, value_at_margin=0, sigmoid="quadratic").mean()
        return float(near * (control + 4) / 5)
    if domain == "ball_in_cup":
        target = _ids(m, site, "target")
        off = np.abs(d.site_xpos[target][[0, 2]] - d.xpos[_ids(m, body, "ball")][[0, 2]])
        return float(all(off < m.site_size[target][[0, 2]] - m.geom_size[_ids(m, geom, "ball"), 0]))
    assert domain == "acrobot"
    target, tip = _ids(m, site, "target"), _ids(m, site, "tip")
    dist = np.linalg.norm(d.site_xpos[target] - d.site_xpos[tip])
    return float(tol(dist, bounds=(0, m.site_size[target, 0]), margin=1))


def _model(domain: str) -> tuple[mujoco.MjModel, list[LayoutGroup]]:
    return mjcf_model(f"{domain}.xml")


@pytest.mark.parametrize("name", list(SUITE_TASKS))
def test_rewards_equal_the_suites_own(name: str) -> None:
    task: SuiteTask = SUITE_TASKS[name]
    m, layout = _model(task.domain)
    d, ctx, rng = mujoco.MjData(m), Context(m, layout), np.random.default_rng(3)
    ours, theirs = [], []
    for i in range(120):
        qpos, qvel, params = task.reset(m, rng)
        if i % 2:  # away from the starts: anywhere, and near them
            qpos = qpos + rng.normal(0, 0.3 if i % 4 == 1 else 0.02, m.nq)
            qvel = rng.normal(0, 2, m.nv)
        if task.domain == "reacher" and i % 3 == 0:  # the fingertip near its target, half the time on it
            d.qpos[:] = qpos
            mujoco.mj_forward(m, d)
            params = d.geom_xpos[_ids(m, mujoco.mjtObj.mjOBJ_GEOM, "finger"), :2] + rng.normal(0, 0.02, 2)
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos, qvel, rng.uniform(-1, 1, m.nu)
        mujoco.mj_forward(m, d)
        s = torch.tensor(mj_state(d, layout)[None])
        r = task.reward(
            ctx, s, torch.tensor(d.ctrl[None].copy()), torch.tensor(np.asarray(params)[None]), False
        )
        ours.append(float(r[0]))
        theirs.append(reference(name, m, d, np.asarray(params)))
    np.testing.assert_allclose(ours, theirs, atol=1e-6)  # (the model's constants are held in float32)
    assert max(theirs) > 0  # the sample met the reward somewhere: the comparison is not of zeros
    assert len(set(np.round(theirs, 6))) > 1  # ... and differed: not one value every time


@pytest.mark.parametrize("name", list(SUITE_TASKS))
def test_the_smooth_reward_pays_where_the_exact_one_does_and_has_a_gradient_outside(name: str) -> None:
    task = SUITE_TASKS[name]
    m, layout = _model(task.domain)
    ctx, rng = Context(m, layout), np.random.default_rng(0)
    states, params = [], []
    d = mujoco.MjData(m)
    for _ in range(64):
        qpos, qvel, drawn = task.reset(m, rng)
        d.qpos[:], d.qvel[:] = qpos, qvel
        states.append(mj_state(d, layout))
        params.append(drawn)
    s = torch.tensor(np.array(states), requires_grad=True)
    p = torch.tensor(np.array(params).reshape(64, -1))
    u = torch.zeros(64, m.nu, dtype=torch.float64)
    exact = task.reward(ctx, s, u, p, False)
    smooth = task.reward(ctx, s, u, p, True)
    assert torch.all(smooth >= exact - 1e-12)
    smooth.sum().backward()
    assert s.grad is not None and float(s.grad.abs().sum()) > 0


def test_the_shaped_reward_still_pulls_just_outside_the_bound() -> None:
    """1 cm outside a bound, the broad margin alone is nearly flat; the shaped one still pulls."""
    at = torch.tensor([0.035], dtype=torch.float64, requires_grad=True)  # 1 cm off a 2.5 cm bound
    broad = tolerance(at, 0.0, 0.025, 0.2)
    (g_broad,) = torch.autograd.grad(broad.sum(), at)
    (g_shaped,) = torch.autograd.grad(shaped(at, 0.0, 0.025, 0.2, 0.02).sum(), at)
    assert float(broad) > 0.98 and float(g_shaped) < 10 * float(g_broad) < 0
    inside = torch.tensor([0.0, 0.01, 0.025], dtype=torch.float64)
    assert torch.all(shaped(inside, 0.0, 0.025, 0.2, 0.02) == 1)


def test_the_reachers_observation_is_the_suites_to_target() -> None:
    """``observe`` gives the policy the suite's ``to_target`` (target less fingertip), in decimetres."""
    task = SUITE_TASKS["reacher-hard"]
    assert task.observe is not None
    m, layout = _model("reacher")
    d, ctx, rng = mujoco.MjData(m), Context(m, layout), np.random.default_rng(5)
    finger, target = _ids(m, mujoco.mjtObj.mjOBJ_GEOM, "finger"), _ids(m, mujoco.mjtObj.mjOBJ_GEOM, "target")
    for _ in range(8):
        qpos, _, params = task.reset(m, rng)
        d.qpos[:] = qpos
        m.geom_pos[target, :2] = params  # the suite places the target by moving its geom
        mujoco.mj_forward(m, d)
        to_target = d.geom_xpos[target, :2] - d.geom_xpos[finger, :2]
        ours = task.observe(ctx, torch.tensor(mj_state(d, layout)[None]), torch.tensor(params[None]))
        np.testing.assert_allclose(ours[0].numpy(), 10 * to_target, atol=1e-6)


def test_tolerance_is_the_suites() -> None:
    x = np.linspace(-3, 3, 121)
    for bounds, margin, sigmoid, at in (
        ((0, 0), 2.0, "gaussian", 0.1),
        ((-0.5, 1), 1.0, "quadratic", 0.0),
        ((0, 1), 0.0, "gaussian", 0.1),
    ):
        ours = tolerance(torch.tensor(x), bounds[0], bounds[1], margin, sigmoid, at).numpy()
        np.testing.assert_allclose(ours, suite_rewards.tolerance(x, bounds, margin, sigmoid, at), atol=1e-12)


@pytest.mark.parametrize("domain", ["cartpole", "reacher", "ball_in_cup", "acrobot", "hopper", "humanoid"])
def test_kinematics_equal_mujocos(domain: str) -> None:
    """Bodies and sites placed from the state as ``mj_kinematics`` places them: hinges with anchors,
    slides, a free root (the humanoid's) and reference positions."""
    m, layout = _model(domain)
    d, kin, rng = mujoco.MjData(m), Kinematics(m, layout), np.random.default_rng(1)
    for _ in range(4):
        d.qpos[:] = m.qpos0 + rng.normal(0, 0.5, m.nq)
        mujoco.mj_normalizeQuat(m, d.qpos)
        mujoco.mj_kinematics(m, d)
        places = kin.places(torch.tensor(mj_state(d, layout)[None]))
        np.testing.assert_allclose(places[0][0].numpy(), d.xpos, atol=1e-5)
        np.testing.assert_allclose(places[1][0].numpy().reshape(-1, 9), d.xmat, atol=1e-5)
        for i in range(m.nsite):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, i)
            np.testing.assert_allclose(
                kin.locator("site", name).position(places)[0].numpy(), d.site_xpos[i], atol=1e-5
            )


def test_places_walked_once_for_a_batch_scored_twice_and_again_when_it_changes() -> None:
    """Outside autograd a planner's two rewards of one batch share one walk of the tree; the same
    batch changed in place, another batch, or a batch under autograd is walked afresh."""
    m, layout = _model("acrobot")
    kin = Kinematics(m, layout)
    s = torch.tensor(np.random.default_rng(2).normal(0, 1, (5, 4)), dtype=torch.float32)
    with torch.no_grad():
        first = kin.places(s)
        assert kin.places(s) is first
        assert kin.places(s.clone()) is not first
        again = kin.places(s)
        s[0, 0] += 1.0  # the same tensor, moved: its places move with it
        moved = kin.places(s)
        assert moved is not again
        assert not torch.allclose(moved[0][0], again[0][0])
    x = s.clone().requires_grad_(True)
    assert kin.places(x) is not kin.places(x)  # autograd's graphs are never shared


def test_starts_follow_the_suites_episodes() -> None:
    rng = np.random.default_rng(0)
    m, _ = _model("cartpole")
    qpos = np.array([SUITE_TASKS["cartpole-swingup"].reset(m, rng)[0] for _ in range(200)])
    assert np.all(np.abs(qpos[:, 1] - np.pi) < 0.06) and np.all(np.abs(qpos[:, 0]) < 0.06)
    m, _ = _model("reacher")
    params = np.array([SUITE_TASKS["reacher-hard"].reset(m, rng)[2] for _ in range(200)])
    radius = np.linalg.norm(params, axis=1)
    assert radius.min() >= 0.05 and radius.max() <= 0.2
    m, _ = _model("ball_in_cup")
    d = mujoco.MjData(m)
    for _ in range(50):
        d.qpos[:], _, _ = SUITE_TASKS["ball_in_cup-catch"].reset(m, rng)
        mujoco.mj_forward(m, d)
        assert d.ncon == 0  # never inside the cup's walls


def test_a_humanoid_starts_turned_anywhere_and_touching_nothing() -> None:
    """``humanoid.Humanoid.initialize_episode``: joints and the free root's orientation drawn (its
    position kept), again until no geoms touch."""
    task = SUITE_TASKS["humanoid-stand"]
    m, _ = _model("humanoid")
    d, rng = mujoco.MjData(m), np.random.default_rng(5)
    qpos = []
    for _ in range(20):
        d.qpos[:], qvel, _ = task.reset(m, rng)
        mujoco.mj_forward(m, d)
        assert d.ncon == 0 and not qvel.any()
        qpos.append(np.array(d.qpos))
    q = np.array(qpos)
    np.testing.assert_array_equal(q[:, :3], np.tile(m.qpos0[:3], (20, 1)))
    np.testing.assert_allclose(np.linalg.norm(q[:, 3:7], axis=1), 1.0)
    assert (q[:, 3:7] >= 0).all() and np.ptp(q[:, 3:7], axis=0).min() > 0.3  # the suite's draw
    limited = m.jnt_limited.astype(bool)[1:]
    assert np.ptp(q[:, 7:], axis=0)[limited].min() > 0  # every limited joint drawn


@pytest.mark.parametrize("domain", ["walker", "cheetah", "humanoid"])
def test_subtree_velocity_and_centres_of_mass_equal_mujocos(domain: str) -> None:
    """The torso's subtree's centre-of-mass velocity (the suite's ``subtreelinvel`` sensor) and each
    body's centre of mass, from the state, as MuJoCo computes them: slides and hinges, a free root."""
    m, layout = _model(domain)
    d, kin, rng = mujoco.MjData(m), Kinematics(m, layout), np.random.default_rng(2)
    torso = _ids(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
    for _ in range(4):
        d.qpos[:] = m.qpos0 + rng.normal(0, 0.5, m.nq)
        mujoco.mj_normalizeQuat(m, d.qpos)
        d.qvel[:] = rng.normal(0, 2, m.nv)
        mujoco.mj_forward(m, d)
        mujoco.mj_subtreeVel(m, d)
        s = torch.tensor(mj_state(d, layout)[None])
        np.testing.assert_allclose(
            kin.subtree_velocity(s, "torso")[0].numpy(), d.subtree_linvel[torso], atol=1e-6
        )
        places = kin.places(s)
        for b in range(1, m.nbody):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
            np.testing.assert_allclose(
                kin.locator("inertial", name).position(places)[0].numpy(), d.xipos[b], atol=1e-5
            )
    with pytest.raises(KeyError, match="no body named"):
        kin.subtree_velocity(s, "tail")


def test_tolerance_with_an_open_bound_is_the_suites_and_finite_in_its_gradient() -> None:
    x = torch.linspace(-4, 14, 181, dtype=torch.float64, requires_grad=True)
    for lower, margin, sigmoid, at in (
        (10.0, 10.0, "linear", 0.0),
        (1.0, 0.5, "linear", 0.5),
        (1.2, 0.6, "gaussian", 0.1),
    ):
        ours = tolerance(x, lower, math.inf, margin, sigmoid, at)
        theirs = suite_rewards.tolerance(x.detach().numpy(), (lower, float("inf")), margin, sigmoid, at)
        np.testing.assert_allclose(ours.detach().numpy(), theirs, atol=1e-12)
        (grad,) = torch.autograd.grad(ours.sum(), x)
        assert torch.isfinite(grad).all()


@pytest.mark.parametrize("name", [n for n, t in SUITE_TASKS.items() if t.unobserved])
def test_the_groups_a_policy_does_not_read_are_in_its_domainsmj_state(name: str) -> None:
    task = SUITE_TASKS[name]
    _, layout = _model(task.domain)
    assert set(task.unobserved) <= {g.name for g in layout}


def test_a_body_on_the_ground_learns_through_short_paths_and_keeps_its_emulators_past() -> None:
    """The ground tasks' training defaults (``suite_tasks._ground``), the others' unchanged."""
    for task in SUITE_TASKS.values():
        ground = task.fall is not None
        assert (task.horizon, task.refine_keep > 0) == ((8, True) if ground else (32, False)), task.name


def test_the_cheetah_starts_settled_on_the_floor() -> None:
    """``cheetah.Cheetah.initialize_episode``: limited joints drawn, then 200 steps at rest."""
    task = SUITE_TASKS["cheetah-run"]
    m, _ = _model("cheetah")
    rng = np.random.default_rng(4)
    starts = [task.reset(m, rng) for _ in range(6)]
    qpos = np.array([q for q, _, _ in starts])
    assert np.ptp(qpos[:, 3:], axis=0).min() > 0  # the joints were drawn, not left at rest
    assert np.abs(np.array([v for _, v, _ in starts])).max() < 1.0  # and settled


def test_a_fall_is_going_down_after_having_been_up() -> None:
    """``Fall.first``: the first state below ``below`` after one at ``above`` or higher; a body that
    never got up has not fallen. On the walker: its torso's height from the state."""
    fall = SUITE_TASKS["walker-stand"].fall
    assert fall is not None
    m, layout = _model("walker")
    ctx, d = Context(m, layout), mujoco.MjData(m)
    rootz = _ids(m, mujoco.mjtObj.mjOBJ_JOINT, "rootz")

    def state(height_change: float) -> np.ndarray:
        d.qpos[:] = m.qpos0
        d.qpos[m.jnt_qposadr[rootz]] = height_change  # the torso stands at 1.3 m at qpos0
        return mj_state(d, layout)

    up, half, down = state(0.0), state(-0.45), state(-1.0)
    episodes = np.array(
        [[down, up, half, down, up], [down, half, down, down, down], [up, half, up, half, up]]
    )
    np.testing.assert_array_equal(fall.first(ctx, episodes), [3, -1, -1])
    # a start drawn standing drops before a policy could hold it: being up counts from ``settle`` on
    dropped = np.array([[up, half, down, down, down], [up, down, up, up, down]])
    np.testing.assert_array_equal(fall.first(ctx, dropped), [2, 1])
    np.testing.assert_array_equal(fall.first(ctx, dropped, settle=2), [-1, 4])
    # up again for good after the fall: the first state back at ``above`` after the last one under
    # ``below``; none for one that stayed down, fell again and lay, or never fell
    np.testing.assert_array_equal(fall.up_again(ctx, episodes, fall.first(ctx, episodes)), [4, -1, -1])
    np.testing.assert_array_equal(fall.up_again(ctx, dropped, fall.first(ctx, dropped)), [-1, -1])
    twice = np.array([[up, down, up, down, half], [up, down, up, down, up], [up, half, up, up, up]])
    np.testing.assert_array_equal(fall.up_again(ctx, twice, fall.first(ctx, twice)), [-1, 4, -1])
