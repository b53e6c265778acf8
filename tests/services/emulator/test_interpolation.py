"""Frame interpolation: endpoints exact, linear in between, unit quaternions by slerp."""

from __future__ import annotations

import numpy as np

from neuroanimator.core import quaternion as quat
from services.emulator.interpolation import frames


def test_linear_groups_and_exact_endpoints() -> None:
    s = np.array([[0.0, 10.0], [1.0, 20.0], [3.0, 0.0]])
    fr = frames(s, 4, [])
    assert fr.shape == (9, 2)
    np.testing.assert_array_equal(fr[[0, 4, 8]], s.astype(np.float32))
    np.testing.assert_allclose(fr[2], [0.5, 15.0])
    np.testing.assert_allclose(fr[6], [2.0, 10.0])


def test_quaternions_are_slerped_and_unit() -> None:
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), 2.0)
    s = np.stack([np.r_[0.0, q0], np.r_[1.0, q1]])
    fr = frames(s, 8, [slice(1, 5)])
    np.testing.assert_allclose(np.linalg.norm(fr[:, 1:5], axis=1), 1.0, atol=1e-6)
    angles = quat.angle_between(np.broadcast_to(q0, (9, 4)), fr[:, 1:5].astype(np.float64))
    np.testing.assert_allclose(angles, np.linspace(0, 2.0, 9), atol=1e-5)  # constant angular rate
    np.testing.assert_array_equal(fr[-1], s[-1].astype(np.float32))


def test_one_frame_per_step_is_the_states() -> None:
    s = np.random.default_rng(0).normal(size=(4, 3))
    np.testing.assert_array_equal(frames(s, 1, []), s.astype(np.float32))


def test_a_wrapped_heading_turns_the_shorter_way() -> None:
    """3.0 rad to -3.0 rad is a turn of 0.28 rad through ±π, not one of -6 rad through 0."""
    s = np.array([[0.0, 3.0], [1.0, -3.0]])
    fr = frames(s, 4, [], angle_columns=[1])
    heading = fr[:, 1].astype(np.float64)
    assert np.all(np.abs(heading) <= np.pi + 1e-6)  # float32 frames: -π rounds to just below it
    turned = np.diff(np.unwrap(heading))
    np.testing.assert_allclose(turned, (2 * np.pi - 6.0) / 4, atol=1e-6)
    np.testing.assert_allclose(fr[:, 0], np.linspace(0, 1, 5), atol=1e-7)  # other columns: linear
