"""A user's reward task (``RewardTaskSpec``) built on a model: each term pays what the suite's
``rewards.tolerance`` pays for the same quantity read from MuJoCo's own data, the starts and the
ground's defaults follow the model, and a term that does not fit it is named."""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np
import pytest
import torch
from dm_control.utils import rewards as suite_rewards
from pydantic import ValidationError

from neuroanimator.contracts.controller import PolicyJobCreate, RewardTaskSpec
from neuroanimator.control.reward_terms import RewardTaskError, build_reward_task, unread_travel
from neuroanimator.control.suite_tasks import Context
from tests.helpers import mj_state, mjcf_model

TORSO_SPEED = "torso_subtreelinvel"


def _spec(*terms: Any, **how: object) -> RewardTaskSpec:
    return RewardTaskSpec.model_validate(
        {"kind": "reward", "model": "walker", "episode_s": 10, "terms": list(terms), **how}
    )


def test_each_term_pays_what_the_suites_tolerance_pays_on_mujocos_data() -> None:
    m, layout = mjcf_model("walker.xml")
    d, ctx, rng = mujoco.MjData(m), Context(m, layout), np.random.default_rng(0)
    torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
    sensor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, TORSO_SPEED)
    tol = suite_rewards.tolerance
    inf = float("inf")
    cases = {  # a term → the suite's own expression of it
        "height": (
            {"kind": "height", "body": "torso", "at_least": 1.2},
            lambda: tol(d.xpos[torso, 2], (1.2, inf), 0.6),
        ),
        "upright": ({"kind": "upright"}, lambda: tol(d.xmat[torso, 8], (0.9, inf), 1.9, "linear", 0)),
        "speed": (
            {"kind": "speed", "at_least": 1.0},
            lambda: tol(d.sensordata[m.sensor_adr[sensor]], (1, inf), 1.0, "linear", 0),
        ),
        "backwards": (
            {"kind": "speed", "at_least": -2.0, "margin": 0.5},
            lambda: tol(d.sensordata[m.sensor_adr[sensor]], (-inf, -2), 0.5, "linear", 0),
        ),
        "control": (
            {"kind": "small_control"},
            lambda: (4 + tol(d.ctrl, margin=1, value_at_margin=0, sigmoid="quadratic").mean()) / 5,
        ),
    }
    for name, (term, theirs) in cases.items():
        task = build_reward_task(_spec(term), m, layout, 10, 0.025, contact=False)
        ours, ref = [], []
        for _ in range(60):
            qpos, _, _ = task.reset(m, rng)
            d.qpos[:] = qpos + rng.normal(0, 0.4, m.nq)  # (the torso lower and higher than it starts)
            d.qvel[:], d.ctrl[:] = rng.normal(0, 2, m.nv), rng.uniform(-1, 1, m.nu)
            mujoco.mj_forward(m, d)
            s, u = torch.tensor(mj_state(d, layout)[None]), torch.tensor(d.ctrl[None].copy())
            ours.append(float(task.reward(ctx, s, u, torch.zeros(1, 0), False)[0]))
            ref.append(float(theirs()))
        np.testing.assert_allclose(ours, ref, atol=1e-6, err_msg=name)
        assert len(set(np.round(ref, 6))) > 1, name  # the sample was not one value every time


def test_terms_combine_as_their_product_or_their_mean_and_controls_are_shares_of_their_range() -> None:
    xml = """<mujoco><worldbody><body name="box" pos="0 0 1"><freejoint/><geom type="box" size=".1 .1 .1"/>
      </body></worldbody><actuator><motor joint="root" gear="0 0 1 0 0 0" ctrlrange="0 2"/></actuator></mujoco>"""
    xml = xml.replace("<freejoint/>", '<freejoint name="root"/>')
    m, layout = mjcf_model(xml)
    ctx, d = Context(m, layout), mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    s = torch.tensor(mj_state(d, layout)[None])
    height = {"kind": "height", "at_least": 2.0, "margin": 1.0}  # the box at 1 m: 0.1 of the way
    terms = (height, {"kind": "small_control"})
    at = {u: torch.tensor([[u]], dtype=torch.float64) for u in (0.0, 1.0, 2.0)}
    product = build_reward_task(_spec(*terms, model="box"), m, layout, 1, 0.002, contact=False)
    mean = build_reward_task(_spec(*terms, model="box", combine="mean"), m, layout, 1, 0.002, contact=False)
    r = {u: float(product.reward(ctx, s, x, torch.zeros(1, 0), False)[0]) for u, x in at.items()}
    assert r[1.0] == pytest.approx(0.1) and r[0.0] == pytest.approx(0.1 * 0.8) == r[2.0]  # mid range: 1
    assert float(mean.reward(ctx, s, at[1.0], torch.zeros(1, 0), False)[0]) == pytest.approx(0.55)


def test_starts_from_random_joints_touch_nothing_and_from_rest_are_the_keyframe_perturbed() -> None:
    m, layout = mjcf_model("humanoid.xml")
    d, rng = mujoco.MjData(m), np.random.default_rng(1)
    task = build_reward_task(_spec({"kind": "upright"}, model="humanoid"), m, layout, 5, 0.025, contact=True)
    for _ in range(10):
        d.qpos[:], qvel, _ = task.reset(m, rng)
        mujoco.mj_forward(m, d)
        assert d.ncon == 0 and not qvel.any()
    rest = build_reward_task(
        _spec({"kind": "upright"}, model="humanoid", starts="rest"), m, layout, 5, 0.025, contact=True
    )
    qpos = np.array([rest.reset(m, rng)[0] for _ in range(20)])
    base = m.key_qpos[0] if m.nkey else m.qpos0
    assert np.abs(qpos - base).max() <= 0.05 and np.ptp(qpos[:, 7:], axis=0).min() > 0
    np.testing.assert_array_equal(qpos[:, :7], np.tile(base[:7], (20, 1)))  # the free root is not moved


def test_the_ground_a_fall_and_the_travel_left_unread_follow_themjcf_model() -> None:
    m, layout = mjcf_model("walker.xml")
    stand = _spec({"kind": "height", "body": "torso", "at_least": 1.2}, {"kind": "upright"}, name="my-stand")
    task = build_reward_task(stand, m, layout, 10, 0.025, contact=True)
    assert (task.name, task.horizon, task.refine_keep > 0, task.episode_steps) == ("my-stand", 8, True, 400)
    assert task.unobserved == ("rootx.pos",) and task.target_return == 0
    assert task.fall is not None and (task.fall.above, task.fall.below) == pytest.approx((0.96, 0.6))
    off = build_reward_task(_spec({"kind": "upright"}), m, layout, 10, 0.025, contact=False)
    assert (off.horizon, off.refine_keep, off.fall, off.name) == (32, 0, None, "custom-walker")
    humanoid, lay = mjcf_model("humanoid.xml")
    assert unread_travel(humanoid, lay) == ()  # a free root's position holds its height: read


def test_a_term_that_does_not_fit_the_model_is_named() -> None:
    m, layout = mjcf_model("walker.xml")
    with pytest.raises(
        RewardTaskError, match=r"terms\[1\]\.body: the model has no body 'head'; its bodies: \['torso'"
    ):
        build_reward_task(
            _spec({"kind": "upright"}, {"kind": "height", "body": "head", "at_least": 1}),
            m,
            layout,
            10,
            0.025,
            False,
        )
    for bad, message in (
        ({"kind": "height"}, "a height term needs at_least"),
        ({"kind": "speed", "at_least": 0}, "must not be 0"),
        ({"kind": "upright", "at_least": 1.5}, r"a cosine in \[-1, 1\)"),
        ({"kind": "height", "at_least": 1, "margin": 0}, "greater than 0"),
        ({"kind": "fly"}, "Input should be 'height'"),
    ):
        with pytest.raises(ValidationError, match=message):
            _spec(bad)
    with pytest.raises(ValidationError, match="terms"):
        _spec()
    job = PolicyJobCreate.model_validate(
        {"task": {"kind": "reward", "model": "walker", "episode_s": 5, "terms": [{"kind": "still"}]}}
    )
    assert (
        isinstance(job.task, RewardTaskSpec) and job.task.starts == "random" and job.task.combine == "product"
    )
    with pytest.raises(ValidationError, match=r"task\.terms\.0\n"):
        PolicyJobCreate.model_validate(
            {"task": {"kind": "reward", "model": "walker", "episode_s": 5, "terms": [{"kind": "height"}]}}
        )
