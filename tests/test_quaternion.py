"""Quaternion algebra (thesis appendix D), checked against independent formulas."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuroanimator.core import quaternion as quat


def random_unit(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """R(q) for a unit quaternion [w, x, y, z], written out from the textbook formula."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


def test_multiply_matches_matrix_form(rng: np.random.Generator) -> None:
    a, b = rng.normal(size=(8, 4)), rng.normal(size=(8, 4))
    expected = np.einsum("bij,bj->bi", quat.matrix(a), b)
    np.testing.assert_allclose(quat.multiply(a, b), expected, atol=1e-12)


def test_multiply_matches_scalar_vector_formula(rng: np.random.Generator) -> None:
    a, b = rng.normal(size=(8, 4)), rng.normal(size=(8, 4))
    w = a[:, 0] * b[:, 0] - np.sum(a[:, 1:] * b[:, 1:], axis=1)
    v = a[:, :1] * b[:, 1:] + b[:, :1] * a[:, 1:] + np.cross(a[:, 1:], b[:, 1:])
    np.testing.assert_allclose(quat.multiply(a, b), np.concatenate([w[:, None], v], axis=1), atol=1e-12)


def test_matrix_shape_is_batched(rng: np.random.Generator) -> None:
    assert quat.matrix(rng.normal(size=(2, 3, 4))).shape == (2, 3, 4, 4)


def test_conjugate_is_inverse_of_unit_quaternion(rng: np.random.Generator) -> None:
    q = random_unit(rng, 10)
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (10, 1))
    np.testing.assert_allclose(quat.multiply(q, quat.conjugate(q)), identity, atol=1e-12)
    np.testing.assert_allclose(quat.multiply(quat.conjugate(q), q), identity, atol=1e-12)


def test_rotate_equals_rotation_matrix(rng: np.random.Generator) -> None:
    q = random_unit(rng, 20)
    v = rng.normal(size=(20, 3))
    expected = np.stack([rotation_matrix(qi) @ vi for qi, vi in zip(q, v, strict=True)])
    np.testing.assert_allclose(quat.rotate(q, v), expected, atol=1e-12)


def test_rotate_composes_like_multiply(rng: np.random.Generator) -> None:
    a, b = random_unit(rng, 5), random_unit(rng, 5)
    v = rng.normal(size=(5, 3))
    np.testing.assert_allclose(
        quat.rotate(quat.multiply(a, b), v), quat.rotate(a, quat.rotate(b, v)), atol=1e-12
    )


def test_from_axis_angle_rotates_about_axis() -> None:
    q = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    np.testing.assert_allclose(quat.rotate(q, np.array([1.0, 0.0, 0.0])), [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0)


def test_slerp_endpoints(rng: np.random.Generator) -> None:
    q0, q1 = random_unit(rng, 6), random_unit(rng, 6)
    q1 = np.where(np.sum(q0 * q1, axis=1, keepdims=True) < 0, -q1, q1)  # same hemisphere
    np.testing.assert_allclose(quat.slerp(q0, q1, 0.0), q0, atol=1e-12)
    np.testing.assert_allclose(quat.slerp(q0, q1, 1.0), q1, atol=1e-12)


def test_slerp_stays_unit_and_moves_at_constant_rate(rng: np.random.Generator) -> None:
    q0, q1 = random_unit(rng, 1)[0], random_unit(rng, 1)[0]
    total = quat.angle_between(q0, q1)
    for t in np.linspace(0.0, 1.0, 11):
        q = quat.slerp(q0, q1, t)
        np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-12)
        np.testing.assert_allclose(quat.angle_between(q0, q), t * total, atol=1e-9)


def test_slerp_takes_the_short_arc(rng: np.random.Generator) -> None:
    q0, q1 = random_unit(rng, 8), random_unit(rng, 8)
    for t in (0.1, 0.5, 0.9):
        a = quat.slerp(q0, q1, t)
        b = quat.slerp(q0, -q1, t)
        sign = np.sign(np.sum(a * b, axis=1, keepdims=True))
        np.testing.assert_allclose(a, sign * b, atol=1e-12)
        # the short arc never turns further than the whole (short) rotation
        assert np.all(quat.angle_between(q0, a) <= quat.angle_between(q0, q1) + 1e-9)


def test_slerp_of_nearly_equal_quaternions_is_finite() -> None:
    q = np.array([1.0, 0.0, 0.0, 0.0])
    out = quat.slerp(q, q, 0.3)
    np.testing.assert_allclose(out, q, atol=1e-12)


def test_angle_between_ignores_sign(rng: np.random.Generator) -> None:
    q0, q1 = random_unit(rng, 4), random_unit(rng, 4)
    np.testing.assert_allclose(quat.angle_between(q0, q1), quat.angle_between(q0, -q1), atol=1e-12)


def test_torch_inputs_give_numpy_results(rng: np.random.Generator) -> None:
    a, b = random_unit(rng, 7), random_unit(rng, 7)
    v = rng.normal(size=(7, 3))
    ta, tb, tv = (torch.from_numpy(x) for x in (a, b, v))
    for fn, args, targs in (
        (quat.multiply, (a, b), (ta, tb)),
        (quat.conjugate, (a,), (ta,)),
        (quat.matrix, (a,), (ta,)),
        (quat.rotate, (a, v), (ta, tv)),
    ):
        out = fn(*targs)
        assert isinstance(out, torch.Tensor)
        np.testing.assert_allclose(out.numpy(), fn(*args), atol=1e-12)


def test_torch_rotate_is_differentiable(rng: np.random.Generator) -> None:
    q = torch.from_numpy(random_unit(rng, 3)).requires_grad_(True)
    v = torch.from_numpy(rng.normal(size=(3, 3)))
    quat.rotate(q, v).sum().backward()
    assert q.grad is not None and torch.isfinite(q.grad).all()
