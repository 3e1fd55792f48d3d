"""Batched rotation math in torch (pure math: no simulator imports). Quaternions are wxyz.

Written in vector form (scalar part and vector part, dot and cross products): on the CPU at a
few dozen envs each tensor operation costs its dispatch, not its arithmetic, so these use
about half the operations of the component-wise forms.
"""

from __future__ import annotations

import torch

_CONJ: dict[tuple[torch.device, torch.dtype], torch.Tensor] = {}


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse of a unit quaternion). Shape: (..., 4)."""
    key = (q.device, q.dtype)
    sign = _CONJ.get(key)
    if sign is None:
        sign = _CONJ[key] = torch.tensor([1.0, -1.0, -1.0, -1.0], device=q.device, dtype=q.dtype)
    return q * sign


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b``. Shapes: (..., 4), broadcast."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    w = aw * bw - (av * bv).sum(-1, keepdim=True)
    v = aw * bv + bw * av + torch.linalg.cross(av, bv)
    return torch.cat([w, v], dim=-1)


def quat_conj_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``conj(a) * b`` (the rotation from ``a`` to ``b`` in ``a``'s frame). Shapes broadcast."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    w = aw * bw + (av * bv).sum(-1, keepdim=True)
    v = aw * bv - bw * av - torch.linalg.cross(av, bv)
    return torch.cat([w, v], dim=-1)


def quat_apply(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors ``v`` by unit quaternions ``q``. Shapes: (..., 4), (..., 3)."""
    w, xyz = q[..., :1], q[..., 1:]
    t = 2.0 * torch.linalg.cross(xyz, v)
    return v + w * t + torch.linalg.cross(xyz, t)


def quat_apply_inverse(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate ``v`` by the inverse of ``q`` (world -> body frame). Shapes: (..., 4), (..., 3)."""
    w, xyz = q[..., :1], q[..., 1:]
    t = 2.0 * torch.linalg.cross(xyz, v)
    return v - w * t + torch.linalg.cross(xyz, t)


def quat_error_magnitude(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle [rad] of the rotation between ``a`` and ``b``, in [0, pi]. Shape: (...,)."""
    d = quat_conj_mul(a, b)
    return 2.0 * torch.atan2(torch.linalg.norm(d[..., 1:], dim=-1), d[..., 0].abs())


def yaw_quat(q: torch.Tensor) -> torch.Tensor:
    """The heading (rotation about world z) of ``q``. Shape: (..., 4)."""
    w, x, y, z = q.unbind(-1)
    yaw = torch.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    zeros = torch.zeros_like(yaw)
    return torch.stack([torch.cos(yaw / 2), zeros, zeros, torch.sin(yaw / 2)], dim=-1)


def rot6d_from_quat(q: torch.Tensor) -> torch.Tensor:
    """The first two columns of the rotation matrix, row-major flattened:
    ``[R00, R01, R10, R11, R20, R21]``. Shape: (..., 6)."""
    w, x, y, z = q.unbind(-1)
    x2, y2, z2 = 2.0 * x, 2.0 * y, 2.0 * z
    xx, yy, zz = x * x2, y * y2, z * z2
    xy, xz, yz = x * y2, x * z2, y * z2
    wx, wy, wz = w * x2, w * y2, w * z2
    return torch.stack([1.0 - yy - zz, xy - wz, xy + wz, 1.0 - xx - zz, xz - wy, yz + wx], dim=-1)


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
    return quat_apply_inverse(quat_a, pos_b - pos_a), quat_conj_mul(quat_a, quat_b)
