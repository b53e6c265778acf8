"""Rollout errors in physical units: metres, degrees and radians, from known differences."""

from __future__ import annotations

import math

import numpy as np

from neuroanimator import catalog
from neuroanimator.core import quaternion
from neuroanimator.core.state import StateGroup, StateLayout
from neuroanimator.evaluation import physical_errors


def test_lander_position_and_attitude_errors_in_metres_and_degrees() -> None:
    layout = catalog.get("lander").layout
    truth = np.tile(catalog.get("lander").rest_state(), (2, 3, 1))  # (N=2, M=3, S)
    pred = truth.copy()
    pos, att = layout.slice_of("position"), layout.slice_of("orientation")
    pred[0, :, pos] += [3.0, 4.0, 0.0]  # 5 m away
    pred[1, :, att] = quaternion.from_axis_angle(np.array([0.0, 1.0, 0.0]), math.radians(10.0))
    pred[1, 2, att] *= -1.0  # the same rotation written as −q
    series = physical_errors.error_series(layout, pred, truth)
    np.testing.assert_allclose(series["root_position_m"], [[5.0] * 3, [0.0] * 3], atol=1e-12)
    np.testing.assert_allclose(series["attitude_deg"], [[0.0] * 3, [10.0] * 3], atol=1e-6)
    assert "joint_angle_rad" not in series


def test_headings_and_hinges_are_compared_on_the_circle() -> None:
    layout = StateLayout.of(
        [
            StateGroup(name="heading", kind="heading", size=1, source="qpos", address=0),
            StateGroup(name="knee", kind="angle", size=2, source="qpos", address=1),
        ]
    )
    truth = np.array([[[math.pi - 0.01, 0.0, 2 * math.pi]]])
    pred = np.array([[[-math.pi + 0.01, 0.3, 0.1]]])
    series = physical_errors.error_series(layout, pred, truth)
    np.testing.assert_allclose(series["attitude_deg"], [[math.degrees(0.02)]], atol=1e-9)
    np.testing.assert_allclose(series["joint_angle_rad"], [[(0.3 + 0.1) / 2]], atol=1e-9)


def test_summary_reports_mean_and_p90_at_the_times_reached_and_null_for_a_divergence() -> None:
    err = np.tile(np.arange(1.0, 41.0), (10, 1))  # error k + 1 after k + 1 super-steps of 0.5 s
    err[9, 39] = np.nan  # one trial diverged by 20 s
    summary = physical_errors.summarize({"root_position_m": err}, 0.5, (1.0, 5.0, 20.0, 30.0))
    rows = summary.root_position_m
    assert rows is not None
    assert [r.t_s for r in rows] == [1.0, 5.0, 20.0]  # 30 s is beyond the rollouts
    assert rows[0].mean == 2.0 and rows[1].p90 == 10.0
    assert rows[2].mean is None and rows[2].p90 is None  # infinite, as JSON can say it: null
    assert summary.at("root_position_m", 5.0) == rows[1] and summary.attitude_deg is None
    assert any("inf" in line for line in physical_errors.format_table(summary))
    # and it survives its JSON file (a NaN or infinity would not read back)
    assert type(summary).model_validate_json(summary.model_dump_json()) == summary


def test_slide_joints_are_compared_in_metres() -> None:
    cartpole = StateLayout.of(
        [
            StateGroup(name="slider.pos", kind="scalar", size=1, source="qpos", address=0),
            StateGroup(name="hinge.angle", kind="angle", size=1, source="qpos", address=1),
            StateGroup(name="slider.vel", kind="scalar", size=1, source="qvel", address=0),
        ]
    )
    truth = np.zeros((1, 2, 3))
    pred = np.array([[[0.25, 0.1, 9.0], [-0.5, 0.0, -9.0]]])  # velocities are not positions
    series = physical_errors.error_series(cartpole, pred, truth)
    np.testing.assert_allclose(series["joint_position_m"], [[0.25, 0.5]], atol=1e-12)
    np.testing.assert_allclose(series["joint_angle_rad"], [[0.1, 0.0]], atol=1e-12)
    assert "root_position_m" not in series
    table = physical_errors.format_table(physical_errors.summarize(series, 0.5, (1.0,)))
    assert any(line.startswith("joint_position_m") and "in m:" in line for line in table)
