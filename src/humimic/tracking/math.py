"""Batched rotation math in torch (pure math: no simulator imports). Quaternions are wxyz."""

from __future__ import annotations

import torch


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse of a unit quaternion). Shape: (..., 4)."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b``. Shapes: (..., 4), broadcast."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_apply(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v`` by unit quaternions ``q``. Shapes: (..., 4), (..., 3)."""
    w, xyz = q[..., :1], q[..., 1:]
    t = 2.0 * torch.cross(xyz, v, dim=-1)
    return v + w * t + torch.cross(xyz, t, dim=-1)


def quat_apply_inverse(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate ``v`` by the inverse of ``q`` (world -> body frame). Shapes: (..., 4), (..., 3)."""
    return quat_apply(quat_conj(q), v)


def quat_error_magnitude(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle [rad] of the rotation between ``a`` and ``b``, in [0, pi]. Shape: (...,)."""
    d = quat_mul(quat_conj(a), b)
    return 2.0 * torch.atan2(torch.linalg.norm(d[..., 1:], dim=-1), d[..., 0].abs())


def yaw_quat(q: torch.Tensor) -> torch.Tensor:
    """The heading (rotation about world z) of ``q``. Shape: (..., 4)."""
    w, x, y, z = q.unbind(-1)
    yaw = torch.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    zeros = torch.zeros_like(yaw)
    return torch.stack([torch.cos(yaw / 2), zeros, zeros, torch.sin(yaw / 2)], dim=-1)


def matrix_from_quat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of unit quaternions. Shape: (..., 3, 3)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def rot6d_from_quat(q: torch.Tensor) -> torch.Tensor:
    """The first two columns of the rotation matrix, row-major flattened. Shape: (..., 6)."""
    return matrix_from_quat(q)[..., :2].reshape(*q.shape[:-1], 6)


def quat_from_euler_xyz(roll: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Quaternion of extrinsic x-y-z rotations (``R = Rz(yaw) Ry(pitch) Rx(roll)``). Shape: (..., 4)."""
    cr, sr = torch.cos(roll / 2), torch.sin(roll / 2)
    cp, sp = torch.cos(pitch / 2), torch.sin(pitch / 2)
    cy, sy = torch.cos(yaw / 2), torch.sin(yaw / 2)
    return torch.stack(
        [
            cy * cr * cp + sy * sr * sp,
            cy * sr * cp - sy * cr * sp,
            cy * cr * sp + sy * sr * cp,
            sy * cr * cp - cy * sr * sp,
        ],
        dim=-1,
    )


def subtract_frame_transforms(
    pos_a: torch.Tensor, quat_a: torch.Tensor, pos_b: torch.Tensor, quat_b: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose of frame b expressed in frame a (``T_ab = T_wa^-1 T_wb``). Shapes broadcast."""
    inv = quat_conj(quat_a)
    return quat_apply(inv, pos_b - pos_a), quat_mul(inv, quat_b)
