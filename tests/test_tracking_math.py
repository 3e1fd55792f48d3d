"""The tracking env's torch rotation math against the numpy reference in humimic.transforms."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from humimic import transforms as tf
from humimic.tracking import math as tm


@pytest.fixture
def quats() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 7, 5, 4))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    return a, b, rng.normal(size=(7, 5, 3))


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64)


def test_products_and_rotations_match_numpy(quats: tuple[np.ndarray, ...]) -> None:
    a, b, v = quats
    np.testing.assert_allclose(tm.quat_mul(_t(a), _t(b)).numpy(), tf.quat_mul(a, b), atol=1e-12)
    np.testing.assert_allclose(
        tm.quat_conj_mul(_t(a), _t(b)).numpy(), tf.quat_mul(tf.quat_conj(a), b), atol=1e-12
    )
    np.testing.assert_allclose(tm.quat_conj(_t(a)).numpy(), tf.quat_conj(a), atol=0)
    R = tf.quat_to_matrix(a)
    np.testing.assert_allclose(
        tm.quat_apply(_t(a), _t(v)).numpy(), np.einsum("...ij,...j->...i", R, v), atol=1e-12
    )
    np.testing.assert_allclose(
        tm.quat_apply_inverse(_t(a), _t(v)).numpy(),
        np.einsum("...ji,...j->...i", R, v),
        atol=1e-12,
    )
    np.testing.assert_allclose(tf.quat_apply_inverse(a, v), np.einsum("...ji,...j->...i", R, v))
    np.testing.assert_allclose(
        tm.rot6d_from_quat(_t(a)).numpy(), R[..., :2].reshape(7, 5, 6), atol=1e-12
    )


def test_broadcasting(quats: tuple[np.ndarray, ...]) -> None:
    a, b, _ = quats
    one = _t(a[:, :1])  # (7, 1, 4) against (7, 5, 4)
    np.testing.assert_allclose(
        tm.quat_mul(one, _t(b)).numpy(), tf.quat_mul(np.broadcast_to(a[:, :1], b.shape), b)
    )


def test_angles_and_euler(quats: tuple[np.ndarray, ...]) -> None:
    a, b, _ = quats
    d = tf.quat_mul(tf.quat_conj(a), b)
    angle = np.linalg.norm(tf.quat_to_rotvec(d), axis=-1)
    np.testing.assert_allclose(tm.quat_error_magnitude(_t(a), _t(b)).numpy(), angle, atol=1e-9)
    e = np.random.default_rng(1).uniform(-3, 3, size=(9, 3))
    R = (
        tf.axis_angle_matrix("z", e[:, 2])
        @ tf.axis_angle_matrix("y", e[:, 1])
        @ tf.axis_angle_matrix("x", e[:, 0])
    )
    np.testing.assert_allclose(tf.quat_to_matrix(tf.quat_from_euler_xyz(e)), R, atol=1e-12)
    np.testing.assert_allclose(
        tm.quat_from_euler_xyz(*_t(e).T).numpy(), tf.quat_from_euler_xyz(e), atol=1e-12
    )
    yaw = tm.yaw_quat(_t(a)).numpy()
    heading = np.einsum("...ij,j->...i", tf.quat_to_matrix(a), [1.0, 0.0, 0.0])
    want = np.arctan2(heading[..., 1], heading[..., 0])
    np.testing.assert_allclose(2 * np.arctan2(yaw[..., 3], yaw[..., 0]), want, atol=1e-9)


def test_error_magnitude_small_and_half_turn_angles() -> None:
    """The chord form keeps float32 precision near zero and handles opposite hemispheres."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    angles = np.array([1e-5, 1e-3, 0.5, np.pi - 1e-3, np.pi])
    b = np.concatenate([np.cos(angles / 2)[:, None], np.sin(angles / 2)[:, None] * axis], axis=1)
    a = np.tile([1.0, 0.0, 0.0, 0.0], (len(angles), 1))
    got = tm.quat_error_magnitude(*(torch.as_tensor(x, dtype=torch.float32) for x in (a, b)))
    np.testing.assert_allclose(got.numpy(), angles, rtol=1e-3, atol=2e-6)
    flipped = tm.quat_error_magnitude(_t(a), _t(-b)).numpy()  # -q is the same rotation
    np.testing.assert_allclose(flipped, angles, rtol=1e-9, atol=1e-12)


def test_matrix_forms_match_quaternion_math(quats: tuple[np.ndarray, ...]) -> None:
    """Rotation matrices and the heading-turn matrices the env uses against quaternion math."""
    a, b, v = quats
    np.testing.assert_allclose(tm.matrix_from_quat(_t(a)).numpy(), tf.quat_to_matrix(a), atol=1e-12)
    h = tm.yaw_half_angle(_t(a), _t(b))
    yaw = tm.yaw_quat(tm.quat_mul(_t(a), tm.quat_conj(_t(b)))).numpy()
    np.testing.assert_allclose(h.numpy(), yaw[..., [0, 3]], atol=1e-9)
    turned = np.einsum("...ij,...j->...i", tm.yaw_quat_matrix(h).numpy(), b)
    np.testing.assert_allclose(turned, tf.quat_mul(yaw, b), atol=1e-12)
    rotated = np.einsum("...ij,...j->...i", tm.yaw_rotation_matrix(h).numpy(), v)
    np.testing.assert_allclose(rotated, np.einsum("...ij,...j->...i", tf.quat_to_matrix(yaw), v))


def test_quat_log_matches_mujocos_quaternion_difference() -> None:
    """``quat_log(conj(a) * b)`` is MuJoCo's ``mju_subQuat(b, a)`` (the tangent that the
    ``feedback`` action base feeds its gains), on both sides of a half turn."""
    import mujoco

    rng = np.random.default_rng(4)
    a = rng.normal(size=(50, 4))
    b = rng.normal(size=(50, 4))
    b[:5] = -a[:5] + 0.01 * rng.normal(size=(5, 4))  # Nearly the same rotation, sign flipped.
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    ta, tb = torch.as_tensor(a), torch.as_tensor(b)
    got = tm.quat_log(tm.quat_conj_mul(ta, tb)).numpy()
    want = np.zeros((50, 3))
    for i in range(50):
        mujoco.mju_subQuat(want[i], b[i], a[i])
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert np.linalg.norm(got[:5], axis=1).max() < 0.1  # The short way round.
    assert tm.quat_log(torch.tensor([1.0, 0.0, 0.0, 0.0])).abs().max() == 0.0
