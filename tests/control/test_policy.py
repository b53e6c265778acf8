"""Policies learned through the emulator: tasks, goals from MuJoCo, the network, training, storage."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import policies, registry
from neuroanimator.catalog import lander, pendulum, quadrotor, truck
from neuroanimator.catalog.tasks import POLICY_TASKS
from neuroanimator.cli import main as neuro
from neuroanimator.control.policy import PolicyResult, PolicySettings, PolicyTrainer, Schedule, TargetDistance
from neuroanimator.control.policy_data import GoalsUnreachable, reached_goals, sample_starts
from neuroanimator.control.policy_job import PolicyJobError, emulator_for, policy_task, run_policy_job
from neuroanimator.control.policy_net import PolicyNet, PolicyShape, describe_columns
from neuroanimator.control.policy_store import load_policy_net
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.goals.policy_task import GoalSpec
from neuroanimator.sim.operating import hold_controls

TINY = PolicySettings(
    seconds=120, max_iterations=6, batch=32, refine=False, refine_every=1.0, refine_runs=8, evaluate_runs=8
)


def test_every_catalog_policy_task_has_an_emulator_at_its_super_step() -> None:
    roots = registry.Roots.default()
    assert set(POLICY_TASKS) == {"pendulum-swing", "lander-landing", "truck-parking", "quadrotor-follow"}
    for task in POLICY_TASKS.values():
        manifest = registry.read_manifest(emulator_for(roots, task))
        assert manifest.substeps == task.substeps and manifest.model == task.model
        assert list(task.labels) == manifest.state_labels, task.name


def test_a_task_names_its_wrong_sizes_and_unknown_goal_variables() -> None:
    with pytest.raises(ValueError, match="target_state must have 13 values"):
        dataclasses.replace(lander.POLICY_LANDING, target_state=(0.0,))
    with pytest.raises(ValueError, match=r"goal variables \['position.w'\] are not state labels"):
        dataclasses.replace(
            lander.POLICY_LANDING, goal=GoalSpec(variables=("position.w",), low=(0.0,), high=(1.0,))
        )
    with pytest.raises(PolicyJobError, match="unknown policy task 'lander-hop'; built-in: pendulum-swing"):
        policy_task("lander-hop")


def test_goals_are_states_mujoco_reaches_within_the_box() -> None:
    model = catalog.CATALOG["pendulum-active"]()
    task = pendulum.POLICY_SWING
    pool = reached_goals(model, task, task.substeps, np.random.default_rng(0), count=16, runs=64)
    assert pool.goals.shape == (16, 3)
    assert np.all(np.abs(pool.goals) <= 1.5)
    assert pool.mujoco_steps > 0 and np.all(pool.state_scale > 0)
    # each a pose the motors hold still, within their ±2 N·m
    for g in pool.goals:
        full = model.to_physics(np.concatenate([g, np.zeros(3)])[None])[0]
        controls, _, left = hold_controls(model.mj_model, full[model.qpos_slice])
        assert left < 1e-3 and np.all(np.abs(controls) <= 2.0)
    # a goal box nothing reaches is refused, naming the variables and the box
    far = dataclasses.replace(
        task, goal=GoalSpec(variables=("angles.j0",), low=(10.0,), high=(11.0,), at_rest=True, holdable=True)
    )
    with pytest.raises(GoalsUnreachable, match=r"angles.j0'\] within \[10.0\]..\[11.0\]"):
        reached_goals(model, far, task.substeps, np.random.default_rng(0), count=8, runs=8)


def test_a_moving_goal_moves_at_most_its_max_move() -> None:
    model = catalog.CATALOG["quadrotor"]()
    task = quadrotor.POLICY_FOLLOW
    pool = reached_goals(model, task, task.substeps, np.random.default_rng(1), count=256, runs=64)
    goals = pool.draw_moving(np.random.default_rng(2), 50, 4, task.goal.max_move)
    assert goals.shape == (50, 4, 3)
    assert np.all(np.linalg.norm(np.diff(goals, axis=1), axis=2) <= 3.0 + 1e-9)


def test_starts_are_in_the_box_with_unit_quaternions_tilted_at_most_as_told() -> None:
    model = catalog.CATALOG["lander"]()
    task = lander.POLICY_LANDING
    s = sample_starts(model, task, np.random.default_rng(0), 200)
    assert np.all(s[:, 0:3] >= np.asarray(task.starts.low[:3])) and np.all(s[:, 0:3] <= task.starts.high[:3])
    q = s[:, 3:7]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    tilt = 2 * np.arccos(np.clip(np.sqrt(q[:, 0] ** 2 + q[:, 3] ** 2), 0, 1))  # angle of the body z from up
    assert tilt.max() <= task.starts.max_tilt + 1e-9


def _shape(timed: bool = False) -> PolicyShape:
    manifest = registry.read_manifest(emulator_for(registry.Roots.default(), truck.POLICY_PARKING))
    goal_cols = truck.POLICY_PARKING.goal_columns
    angles, plain, goal_angles, heading, planar = describe_columns(manifest.layout, goal_cols)
    return PolicyShape(
        state_size=6, mean=(0.0,) * 6, scale=(1.0,) * 6, angle_columns=tuple(angles),
        plain_columns=tuple(plain), goal_columns=tuple(goal_cols), goal_scale=(5.0, 5.0, 1.0),
        goal_angles=tuple(goal_angles), heading=heading, planar=tuple(planar), low=(-10.0, -2.0),
        high=(10.0, 5.0), limit_low=(-10.0, -2.0), limit_high=(10.0, 5.0), timed=timed, hidden=(16,),
    )  # fmt: skip


def test_the_network_reads_the_heading_as_an_angle_and_the_goal_in_the_trucks_frame() -> None:
    shape = _shape()
    assert shape.angle_columns == (2,) and shape.goal_angles == (False, False, True)
    assert shape.heading == 2 and shape.planar == (0, 1)
    net = PolicyNet(shape)
    feats = net.features
    state = torch.tensor([[0.0, 0.0, math.pi - 0.01, 0, 0, 0]])
    goal = torch.tensor([[3.0, 0.0, -math.pi + 0.01]])
    f = feats(state, goal, torch.zeros(1, 1))
    # sin, cos of the heading, 5 plain values, 3 goal offsets, 2 planar ones
    assert f.shape == (1, 2 + 5 + 3 + 2)
    assert abs(float(f[0, 9])) == pytest.approx(0.02, abs=1e-5)  # the heading's offset wrapped: 0.02, not 2π
    # the goal 3 m along world x lies behind a truck facing −x: ahead = −3/5, left = 0
    assert float(f[0, 10]) == pytest.approx(-0.6, abs=1e-2) and abs(float(f[0, 11])) < 1e-2


def test_controls_stay_within_the_limits_and_the_onnx_graph_equals_torch(tmp_path: Path) -> None:
    from neuroanimator.export.policy import policy_to_onnx

    for timed in (False, True):
        net = PolicyNet(_shape(timed))
        with torch.no_grad():
            for p in net.mlp.parameters():
                p.normal_(0, 3)  # large weights: saturated outputs
        rng = np.random.default_rng(0)
        state = rng.normal(0, 5, (64, 6)).astype(np.float32)
        goal = rng.normal(0, 5, (64, 3)).astype(np.float32)
        left = rng.random((64, 1)).astype(np.float32)
        with torch.no_grad():
            u = net(torch.from_numpy(state), torch.from_numpy(goal), torch.from_numpy(left)).numpy()
        assert (
            np.all(u[:, 0] >= -10)
            and np.all(u[:, 0] <= 10)
            and np.all(u[:, 1] >= -2)
            and np.all(u[:, 1] <= 5)
        )
        sess = ort.InferenceSession(policy_to_onnx(net, 6, 3, timed))
        feed = {"state": state, "goal": goal} | ({"time_left": left} if timed else {})
        assert [i.name for i in sess.get_inputs()] == list(feed)
        (out,) = sess.run(None, feed)
        if timed:
            np.testing.assert_allclose(out, u, atol=1e-4)
        else:
            with torch.no_grad():
                ref = net(torch.from_numpy(state), torch.from_numpy(goal), torch.zeros(64, 1)).numpy()
            np.testing.assert_allclose(out, ref, atol=1e-4)


def test_the_distance_wraps_angles_and_takes_the_nearer_quaternion() -> None:
    path = emulator_for(registry.Roots.default(), lander.POLICY_LANDING)
    dist = TargetDistance(registry.read_manifest(path), (1.0,) * 13)
    a = torch.tensor([[0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0.0]])
    b = a.clone()
    b[0, 3] = -1.0  # the same orientation
    assert float(dist(a, b)) == pytest.approx(0.0, abs=1e-2)


def test_the_schedule_checks_after_each_move_and_weighs_each_goal_alike() -> None:
    sch = Schedule(quadrotor.POLICY_FOLLOW, 0.125)
    assert (sch.steps, sch.per_goal, sch.check, sch.goals) == (160, 40, 16, 4)
    assert sch.check_steps() == [16, 56, 96, 136]
    assert sch.weights.reshape(4, 40).sum(axis=1) == pytest.approx([1.0] * 4)
    timed = Schedule(dataclasses.replace(pendulum.POLICY_SWING, settle_s=0.0, timed=True), 0.25)
    assert timed.time_left(0) == 1.0 and timed.time_left(79) == pytest.approx(1 / 80)
    assert timed.weights[:60].sum() == 0.0  # a timed task counts only arriving on time


def test_training_lowers_the_loss_on_starts_and_goals_it_never_saw() -> None:
    path = emulator_for(registry.Roots.default(), lander.POLICY_LANDING)
    trainer = PolicyTrainer(
        lander.POLICY_LANDING, path, dataclasses.replace(TINY, max_iterations=20, batch=64)
    )
    starts, goals = trainer.draw(128)
    with torch.no_grad():
        before = float(trainer.rollout_loss(starts, goals))
    r = trainer.train()
    with torch.no_grad():
        after = float(trainer.rollout_loss(starts, goals))
    assert r.iterations == 20 and after < 0.9 * before


def test_a_trained_policy_is_stored_and_read_back() -> None:
    roots = registry.Roots.default()
    done = run_policy_job("lander-landing", roots, TINY)
    r = done.result
    assert isinstance(r, PolicyResult)
    assert r.iterations == 6 and r.success_history == [(6, r.success_history[0][1])]
    assert 0.0 <= r.success_physics <= 1.0 and r.evaluate_runs == 8
    assert r.mujoco_steps > 0
    # stored in the data directory, never among the committed defaults
    assert done.folder is not None and done.folder.is_relative_to(roots.data)
    assert not done.folder.is_relative_to(registry.DEFAULTS_DIR)
    found = policies.resolve_policy(roots, "lander", "lander-landing")
    assert found == done.folder
    m = policies.read_policy(found)
    assert m.emulator_version == registry.latest_version(roots, "lander", 25)
    assert m.goal_variables == ["position.x", "position.y"] and len(m.goal_default) == 2
    assert all(lo <= hi for lo, hi in zip(m.goal_low, m.goal_high, strict=True))
    assert [p.name for p in policies.list_policies(roots, "lander")] == ["lander-landing"]
    net = load_policy_net(found)
    sess = ort.InferenceSession(str(found / policies.POLICY_ONNX))
    state = np.asarray([lander.POLICY_LANDING.starts.high], dtype=np.float32)
    goal = np.asarray([m.goal_default], dtype=np.float32)
    left = np.asarray([[0.5]], dtype=np.float32)  # the landing is timed: the policy reads the time left
    assert m.timed
    (u,) = sess.run(None, {"state": state, "goal": goal, "time_left": left})
    with torch.no_grad():
        ref = net(torch.from_numpy(state), torch.from_numpy(goal), torch.from_numpy(left)).numpy()
    np.testing.assert_allclose(u, ref, atol=1e-5)
    with pytest.raises(policies.PolicyError, match="policy 'lander-hop' for model 'lander' not found"):
        policies.resolve_policy(roots, "lander", "lander-hop")
    with pytest.raises(policies.PolicyError, match="not a plain name"):
        policies.resolve_policy(roots, "lander", "lander-landing", "../x")


def test_a_policy_refined_on_its_runs_is_stored_with_the_emulator_it_refined() -> None:
    """The emulator refined on the policy's MuJoCo runs is stored as a version of its own in the data
    directory (the catalog's lander is a read-only default, left as it was), the version the policy
    names; its graph is the refined emulator, and the model's latest version is still the one it was
    refined from."""
    roots = registry.Roots.default()
    latest = registry.latest_version(roots, "lander", 25)
    defaults = sorted(p.name for p in (registry.DEFAULTS_DIR / "lander").iterdir())
    refined = dataclasses.replace(TINY, max_iterations=2, refine=True, refine_gap=-1.0, refine_seconds=1.0)
    done = run_policy_job("lander-landing", roots, refined)
    r = done.result
    assert isinstance(r, PolicyResult) and r.refinements == 1 and r.emulator is not None
    assert done.folder is not None
    m = policies.read_policy(done.folder)
    assert m.emulator_version.startswith(f"{latest}-tuned-")
    served = registry.resolve(roots, "lander", m.emulator_version)
    assert served.parent == roots.data / "lander"
    stored = registry.read_manifest(served)
    assert stored.tuned is not None and (stored.tuned.from_version, stored.tuned.task) == (
        latest,
        "lander-landing",
    )
    assert stored.envelope is not None and stored.model == "lander" and stored.version == m.emulator_version
    assert registry.latest_version(roots, "lander", 25) == latest
    assert sorted(p.name for p in (registry.DEFAULTS_DIR / "lander").iterdir()) == defaults
    state = np.asarray([lander.POLICY_LANDING.starts.high], dtype=np.float32)
    u = np.asarray([[0.5, 0.5, 0.2, 0.1]], dtype=np.float32)
    with torch.no_grad():
        want = r.emulator(torch.from_numpy(state), torch.from_numpy(u)).numpy()
    np.testing.assert_allclose(
        OnnxEmulator(served / registry.ONNX_FILE).step(state, u), want, rtol=1e-4, atol=1e-4
    )
    assert registry.load_physical_model(served).name == "lander"


def test_a_cancelled_training_stops_and_says_so() -> None:
    path = emulator_for(registry.Roots.default(), truck.POLICY_PARKING)
    calls: list[int] = []
    trainer = PolicyTrainer(
        truck.POLICY_PARKING,
        path,
        dataclasses.replace(TINY, max_iterations=None),
        on_progress=lambda p: calls.append(p["iteration"]),
        should_stop=lambda: len(calls) >= 3,
    )
    r = trainer.train()
    assert r.stop == "cancelled" and r.iterations == 3 and calls == [1, 2, 3]


def test_neuro_policy_trains_and_reports(capsys: pytest.CaptureFixture[str]) -> None:
    assert neuro(["policy", "truck-parking", "--seconds", "3", "--no-refine", "--json"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["task"] == "truck-parking" and 0.0 <= row["success_physics"] <= 1.0
    assert Path(row["policy"]).is_relative_to(registry.Roots.default().data)
    assert neuro(["policy", "truck-hop"]) == 2


def test_a_free_body_reads_the_goal_and_its_velocity_in_its_own_frame() -> None:
    from neuroanimator.control.policy_net import describe_body_frame, rotate_into
    from neuroanimator.core import quaternion as quat

    manifest = registry.read_manifest(emulator_for(registry.Roots.default(), quadrotor.POLICY_FOLLOW))
    q_col, spatial, velocity = describe_body_frame(manifest.layout, quadrotor.POLICY_FOLLOW.goal_columns)
    assert (q_col, spatial, velocity) == (3, [0, 1, 2], [7, 8, 9])
    rng = np.random.default_rng(0)
    q = rng.normal(size=(16, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    v = rng.normal(size=(16, 3))
    expected = quat.rotate(quat.conjugate(q), v)  # the world vector seen from the body
    got = rotate_into(torch.from_numpy(q), torch.from_numpy(v)).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # a model without a free body has no body frame
    truck_layout = registry.read_manifest(emulator_for(registry.Roots.default(), truck.POLICY_PARKING)).layout
    assert describe_body_frame(truck_layout, [0, 1, 2]) == (-1, [], [])
