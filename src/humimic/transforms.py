"""Rotation and frame math on arrays. Pure numpy: no simulator or file imports.

Quaternions are ``wxyz`` (scalar first) throughout. ``xyzw`` appears only in the named
converters :func:`quat_from_xyzw` and :func:`quat_to_xyzw`.
"""

from __future__ import annotations

import numpy as np

_AXIS = {"x": 0, "y": 1, "z": 2}


def axis_angle_matrix(axis: str, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices about a principal axis.

    Args:
        axis: ``"x"``, ``"y"`` or ``"z"``.
        angle: Angles in radians. Shape: (...,).

    Returns:
        Rotation matrices. Shape: (..., 3, 3).
    """
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((*angle.shape, 3, 3))
    i = _AXIS[axis]
    j, k = (i + 1) % 3, (i + 2) % 3
    out[..., i, i] = 1.0
    out[..., j, j] = c
    out[..., k, k] = c
    out[..., j, k] = -s
    out[..., k, j] = s
    return out


def euler_to_matrix(angles: np.ndarray, order: str) -> np.ndarray:
    """Intrinsic Euler angles to rotation matrices, ``R = R_order[0] @ R_order[1] @ ...``.

    This is the BVH convention: channels listed as ``Zrotation Yrotation Xrotation`` give
    ``R = Rz @ Ry @ Rx``.

    Args:
        angles: Angles in radians, one column per letter of ``order``. Shape: (..., len(order)).
        order: Axis letters, e.g. ``"zyx"``.

    Returns:
        Shape: (..., 3, 3).
    """
    angles = np.asarray(angles, dtype=np.float64)
    out = np.broadcast_to(np.eye(3), (*angles.shape[:-1], 3, 3)).copy()
    for n, axis in enumerate(order.lower()):
        out = out @ axis_angle_matrix(axis, angles[..., n])
    return out


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (wxyz) to rotation matrices. Shape: (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty((*q.shape[:-1], 3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices to unit quaternions (wxyz, w >= 0). Shape: (..., 3, 3) -> (..., 4).

    Vectorized Shepperd's method: each quaternion is computed from its largest component.
    """
    m = np.asarray(m, dtype=np.float64)
    shape = m.shape[:-2]
    r = m.reshape(-1, 3, 3)
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack(
        [
            np.stack(
                [1 + tr, r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]],
                -1,
            ),
            np.stack(
                [
                    r[:, 2, 1] - r[:, 1, 2],
                    1 + m00 - m11 - m22,
                    r[:, 0, 1] + r[:, 1, 0],
                    r[:, 0, 2] + r[:, 2, 0],
                ],
                -1,
            ),
            np.stack(
                [
                    r[:, 0, 2] - r[:, 2, 0],
                    r[:, 0, 1] + r[:, 1, 0],
                    1 - m00 + m11 - m22,
                    r[:, 1, 2] + r[:, 2, 1],
                ],
                -1,
            ),
            np.stack(
                [
                    r[:, 1, 0] - r[:, 0, 1],
                    r[:, 0, 2] + r[:, 2, 0],
                    r[:, 1, 2] + r[:, 2, 1],
                    1 - m00 - m11 + m22,
                ],
                -1,
            ),
        ],
        axis=1,
    )  # (N, 4 candidates, 4)
    k = np.argmax(np.stack([tr, m00, m11, m22], axis=1), axis=1)
    q = cand[np.arange(r.shape[0]), k]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(*shape, 4)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of wxyz quaternions. Shape: (..., 4)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_from_euler_xyz(angles: np.ndarray) -> np.ndarray:
    """Quaternions of extrinsic x-y-z rotations (``R = Rz(yaw) Ry(pitch) Rx(roll)``).

    Args:
        angles: Roll, pitch, yaw [rad]. Shape: (..., 3).

    Returns:
        Shape: (..., 4).
    """
    half = 0.5 * np.asarray(angles, dtype=np.float64)
    cr, cp, cy = np.moveaxis(np.cos(half), -1, 0)
    sr, sp, sy = np.moveaxis(np.sin(half), -1, 0)
    return np.stack(
        [
            cy * cr * cp + sy * sr * sp,
            cy * sr * cp - sy * cr * sp,
            cy * cr * sp + sy * sr * cp,
            sy * cr * cp - cy * sr * sp,
        ],
        axis=-1,
    )


def quat_apply_inverse(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors ``v`` by the inverse of unit quaternions ``q`` (world -> body frame).

    Shapes: (..., 4), (..., 3) -> (..., 3).
    """
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    w, xyz = q[..., :1], -q[..., 1:]
    t = 2.0 * _cross(xyz, v)
    return v + w * t + _cross(xyz, t)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of 3-vectors in components: a few times faster on small arrays (resets
    of a few envs at a time). Shapes: (..., 3), broadcast."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse for unit quaternions). Shape: (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (wxyz) to rotation vectors (axis * angle). Shape: (..., 4) -> (..., 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return v * scale


def quat_slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between wxyz quaternions.

    Args:
        a: Start. Shape: (..., 4).
        b: End. Shape: (..., 4).
        t: Fractions in [0, 1]. Shape: broadcastable to (...,).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-6
    with np.errstate(invalid="ignore", divide="ignore"):
        wa = np.where(small, 1.0 - t, np.sin((1.0 - t) * theta) / np.where(small, 1.0, sin))
        wb = np.where(small, t, np.sin(t * theta) / np.where(small, 1.0, sin))
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def quat_from_xyzw(q: np.ndarray) -> np.ndarray:
    """Convert ``xyzw`` (scipy, ROS) to ``wxyz``."""
    return np.roll(np.asarray(q, dtype=np.float64), 1, axis=-1)


def quat_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Convert ``wxyz`` to ``xyzw`` (scipy, ROS)."""
    return np.roll(np.asarray(q, dtype=np.float64), -1, axis=-1)


def frame_from_axes(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Right-handed frame with x along ``forward`` (made orthogonal to ``up``) and z along ``up``.

    Args:
        forward: Approximate x axis. Shape: (..., 3).
        up: z axis. Shape: (..., 3).

    Returns:
        Rotation matrices whose columns are the frame's axes in the world. Shape: (..., 3, 3).
    """
    up = np.asarray(up, dtype=np.float64)
    z = up / np.linalg.norm(up, axis=-1, keepdims=True)
    f = np.asarray(forward, dtype=np.float64)
    x = f - np.sum(f * z, axis=-1, keepdims=True) * z
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def frame_from_left_up(left: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Right-handed frame with z along ``up`` and y along ``left`` made orthogonal to ``up``.

    The frame's x axis (``y cross z``) points forward. Shape: (..., 3) -> (..., 3, 3).
    """
    up = np.asarray(up, dtype=np.float64)
    z = up / np.linalg.norm(up, axis=-1, keepdims=True)
    lft = np.asarray(left, dtype=np.float64)
    y = lft - np.sum(lft * z, axis=-1, keepdims=True) * z
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Proper rotation (+90 degrees about x) taking a y-up frame to a z-up one: (x, y, z) -> (x, -z, y)."""
