"""Rotation and frame math, checked against scipy's independent implementation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from humimic.transforms import (
    Y_UP_TO_Z_UP,
    euler_to_matrix,
    frame_from_axes,
    frame_from_left_up,
    matrix_to_quat,
    quat_from_xyzw,
    quat_mul,
    quat_slerp,
    quat_to_matrix,
    quat_to_rotvec,
    quat_to_xyzw,
)

RNG_SEED = 1234


def _random_rotations(n: int, seed: int = RNG_SEED) -> Rotation:
    return Rotation.random(n, rng=np.random.default_rng(seed))


def _wxyz(r: Rotation) -> np.ndarray:
    """scipy rotation as wxyz quaternions. Shape: (N, 4)."""
    return quat_from_xyzw(r.as_quat())


def _assert_same_quat(a: np.ndarray, b: np.ndarray, atol: float = 1e-12) -> None:
    """Equal up to the sign of each quaternion (q and -q are the same rotation)."""
    dot = np.abs(np.sum(a * b, axis=-1))
    np.testing.assert_allclose(dot, 1.0, atol=atol)


def _assert_rotation(m: np.ndarray, atol: float = 1e-12) -> None:
    eye = np.broadcast_to(np.eye(3), m.shape)
    np.testing.assert_allclose(np.swapaxes(m, -1, -2) @ m, eye, atol=atol)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=atol)


# --- Euler angles ----------------------------------------------------------------------------


@pytest.mark.parametrize("order", ["zyx", "xyz", "yxz", "zxy", "xzy", "yzx", "zxz", "xyx"])
def test_euler_to_matrix_matches_scipy_intrinsic(order: str) -> None:
    rng = np.random.default_rng(RNG_SEED)
    angles = rng.uniform(-np.pi, np.pi, size=(64, 3))
    ours = euler_to_matrix(angles, order)
    ref = Rotation.from_euler(order.upper(), angles).as_matrix()
    np.testing.assert_allclose(ours, ref, atol=1e-12)


def test_euler_to_matrix_is_intrinsic_not_extrinsic() -> None:
    # The lower-case (extrinsic) scipy convention must NOT match for a generic rotation.
    angles = np.array([0.3, -0.7, 1.1])
    ours = euler_to_matrix(angles, "zyx")
    extrinsic = Rotation.from_euler("zyx", angles).as_matrix()
    assert not np.allclose(ours, extrinsic, atol=1e-6)


def test_euler_to_matrix_keeps_batch_shape() -> None:
    angles = np.zeros((2, 5, 3))
    out = euler_to_matrix(angles, "ZYX")
    assert out.shape == (2, 5, 3, 3)
    np.testing.assert_array_equal(out, np.broadcast_to(np.eye(3), (2, 5, 3, 3)))


# --- Quaternions and matrices -----------------------------------------------------------------


def test_quat_to_matrix_matches_scipy() -> None:
    r = _random_rotations(200)
    np.testing.assert_allclose(quat_to_matrix(_wxyz(r)), r.as_matrix(), atol=1e-12)


def test_matrix_quat_round_trip_random() -> None:
    r = _random_rotations(500)
    m = r.as_matrix()
    q = matrix_to_quat(m)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0.0), "matrix_to_quat documents w >= 0"
    _assert_same_quat(q, _wxyz(r))
    np.testing.assert_allclose(quat_to_matrix(q), m, atol=1e-12)


def test_matrix_quat_round_trip_keeps_batch_shape() -> None:
    m = _random_rotations(12).as_matrix().reshape(3, 4, 3, 3)
    q = matrix_to_quat(m)
    assert q.shape == (3, 4, 4)
    np.testing.assert_allclose(quat_to_matrix(q), m, atol=1e-12)


_HALF_TURN_AXES = {
    "x": np.array([1.0, 0.0, 0.0]),
    "y": np.array([0.0, 1.0, 0.0]),
    "z": np.array([0.0, 0.0, 1.0]),
    "diagonal": np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0),
    "oblique": np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5]),
}


@pytest.mark.parametrize("axis_name", list(_HALF_TURN_AXES))
def test_matrix_quat_round_trip_half_turns(axis_name: str) -> None:
    axis = _HALF_TURN_AXES[axis_name]
    for angle in (np.pi, np.pi - 1e-7, -np.pi + 1e-7):
        r = Rotation.from_rotvec(axis * angle)
        m = r.as_matrix()
        q = matrix_to_quat(m)
        np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-12)
        _assert_same_quat(q, _wxyz(r), atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(q), m, atol=1e-12)
    # An exact half turn: w == 0 and the vector part is +-axis.
    q = matrix_to_quat(Rotation.from_rotvec(axis * np.pi).as_matrix())
    assert abs(q[0]) < 1e-12
    np.testing.assert_allclose(np.abs(q[1:] @ axis), 1.0, atol=1e-12)


def test_matrix_to_quat_identity_and_small_angles() -> None:
    np.testing.assert_allclose(matrix_to_quat(np.eye(3)), [1.0, 0.0, 0.0, 0.0], atol=1e-15)
    r = Rotation.from_rotvec([1e-9, -2e-9, 3e-9])
    _assert_same_quat(matrix_to_quat(r.as_matrix()), _wxyz(r), atol=1e-15)


def test_quat_mul_matches_scipy_composition() -> None:
    a = _random_rotations(100, seed=1)
    b = _random_rotations(100, seed=2)
    ours = quat_mul(_wxyz(a), _wxyz(b))
    _assert_same_quat(ours, _wxyz(a * b))
    # Composition order: quat_mul(a, b) rotates by b first, then a.
    np.testing.assert_allclose(quat_to_matrix(ours), a.as_matrix() @ b.as_matrix(), atol=1e-12)


def test_quat_mul_is_not_commutative() -> None:
    qa = _wxyz(Rotation.from_rotvec([0.5, 0.0, 0.0]))
    qb = _wxyz(Rotation.from_rotvec([0.0, 0.5, 0.0]))
    assert not np.allclose(quat_mul(qa, qb), quat_mul(qb, qa))


def test_quat_to_rotvec_matches_scipy() -> None:
    r = _random_rotations(300)
    q = _wxyz(r)
    np.testing.assert_allclose(quat_to_rotvec(q), r.as_rotvec(), atol=1e-12)
    # q and -q give the same rotation vector (the shortest one).
    np.testing.assert_allclose(quat_to_rotvec(-q), r.as_rotvec(), atol=1e-12)


def test_quat_to_rotvec_small_angle_and_identity() -> None:
    np.testing.assert_array_equal(quat_to_rotvec(np.array([1.0, 0.0, 0.0, 0.0])), np.zeros(3))
    rv = np.array([1e-10, -3e-10, 2e-10])
    q = _wxyz(Rotation.from_rotvec(rv))
    np.testing.assert_allclose(quat_to_rotvec(q), rv, atol=1e-20, rtol=1e-9)


def test_quat_slerp_endpoints_and_midpoint() -> None:
    a_rot = _random_rotations(50, seed=3)
    b_rot = _random_rotations(50, seed=4)
    a, b = _wxyz(a_rot), _wxyz(b_rot)
    _assert_same_quat(quat_slerp(a, b, np.zeros(50)), a)
    _assert_same_quat(quat_slerp(a, b, np.ones(50)), b)
    mid = quat_slerp(a, b, np.full(50, 0.5))
    np.testing.assert_allclose(np.linalg.norm(mid, axis=-1), 1.0, atol=1e-12)
    for i in range(50):
        pair = Rotation.concatenate([a_rot[i], b_rot[i]])
        ref = Slerp([0.0, 1.0], pair)([0.5])
        _assert_same_quat(mid[i], _wxyz(ref)[0], atol=1e-10)
    # The midpoint is halfway in angle: equal geodesic distance to both ends.
    d_a = np.linalg.norm(quat_to_rotvec(quat_mul(mid, a * [1, -1, -1, -1])), axis=-1)
    d_b = np.linalg.norm(quat_to_rotvec(quat_mul(mid, b * [1, -1, -1, -1])), axis=-1)
    np.testing.assert_allclose(d_a, d_b, atol=1e-10)


def test_quat_slerp_takes_short_path_and_handles_nearly_equal() -> None:
    a = np.array([1.0, 0.0, 0.0, 0.0])
    b = _wxyz(Rotation.from_rotvec([0.0, 0.0, 0.4]))
    # -b is the same rotation; slerp must still go the short way (0.2 rad at t=0.5).
    mid = quat_slerp(a, -b, np.array(0.5))
    np.testing.assert_allclose(np.abs(quat_to_rotvec(mid)), [0.0, 0.0, 0.2], atol=1e-12)
    c = _wxyz(Rotation.from_rotvec([0.0, 1e-9, 0.0]))
    out = quat_slerp(a, c, np.array(0.5))
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(quat_to_rotvec(out), [0.0, 5e-10, 0.0], atol=1e-15)


def test_xyzw_converters() -> None:
    np.testing.assert_array_equal(quat_from_xyzw(np.array([1.0, 2.0, 3.0, 4.0])), [4, 1, 2, 3])
    np.testing.assert_array_equal(quat_to_xyzw(np.array([4.0, 1.0, 2.0, 3.0])), [1, 2, 3, 4])
    q = np.random.default_rng(0).normal(size=(7, 3, 4))
    np.testing.assert_array_equal(quat_to_xyzw(quat_from_xyzw(q)), q)
    np.testing.assert_array_equal(quat_from_xyzw(quat_to_xyzw(q)), q)
    r = _random_rotations(10)
    np.testing.assert_allclose(quat_to_xyzw(_wxyz(r)), r.as_quat(), atol=0)


# --- Frames -----------------------------------------------------------------------------------


def test_y_up_to_z_up_is_proper_rotation_taking_y_to_z() -> None:
    _assert_rotation(Y_UP_TO_Z_UP, atol=0.0)
    np.testing.assert_array_equal(Y_UP_TO_Z_UP @ np.array([0.0, 1.0, 0.0]), [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(Y_UP_TO_Z_UP @ np.array([1.0, 0.0, 0.0]), [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(Y_UP_TO_Z_UP @ np.array([0.0, 0.0, 1.0]), [0.0, -1.0, 0.0])


def test_frame_from_left_up_is_right_handed_orthonormal() -> None:
    rng = np.random.default_rng(RNG_SEED)
    left = rng.normal(size=(200, 3))
    up = rng.normal(size=(200, 3))
    f = frame_from_left_up(left, up)
    _assert_rotation(f)
    z = up / np.linalg.norm(up, axis=-1, keepdims=True)
    np.testing.assert_allclose(f[..., 2], z, atol=1e-12)
    # y is `left` with its component along z removed, so it keeps left's direction.
    assert np.all(np.sum(f[..., 1] * left, axis=-1) > 0)
    np.testing.assert_allclose(np.cross(f[..., 0], f[..., 1]), f[..., 2], atol=1e-12)


def test_frame_from_left_up_world_aligned_person_gives_identity() -> None:
    # Facing +x: left is +y, up is +z (a slightly tilted "left" is straightened).
    f = frame_from_left_up(np.array([0.0, 2.0, 0.3]), np.array([0.0, 0.0, 5.0]))
    np.testing.assert_allclose(f, np.eye(3), atol=1e-12)


def test_frame_from_axes_is_right_handed_orthonormal() -> None:
    rng = np.random.default_rng(RNG_SEED + 1)
    fwd = rng.normal(size=(100, 3))
    up = rng.normal(size=(100, 3))
    f = frame_from_axes(fwd, up)
    _assert_rotation(f)
    np.testing.assert_allclose(
        f[..., 2], up / np.linalg.norm(up, axis=-1, keepdims=True), atol=1e-12
    )
    assert np.all(np.sum(f[..., 0] * fwd, axis=-1) > 0)
