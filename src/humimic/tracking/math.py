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
    """Angle [rad] of the rotation between unit quaternions ``a`` and ``b``, in [0, pi].

    From the chord between them on the same hemisphere, ``angle = 4 asin(|a - s b| / 2)`` with
    ``s = sign(a . b)``: no quaternion product, and accurate at small angles (unlike ``acos``
    of the dot product). Shape: (...,).
    """
    s = torch.where((a * b).sum(-1, keepdim=True) < 0.0, -1.0, 1.0)
    chord = torch.linalg.vector_norm(a - s * b, dim=-1)
    return 4.0 * torch.asin((0.5 * chord).clamp(max=1.0))


def yaw_quat(q: torch.Tensor) -> torch.Tensor:
    """The heading (rotation about world z) of ``q``. Shape: (..., 4)."""
    w, x, y, z = q.unbind(-1)
    yaw = torch.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    zeros = torch.zeros_like(yaw)
    return torch.stack([torch.cos(yaw / 2), zeros, zeros, torch.sin(yaw / 2)], dim=-1)


_ROT6D: dict[tuple[torch.device, torch.dtype], torch.Tensor] = {}


def _rot6d_form(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """The six entries of ``rot6d_from_quat`` as quadratic forms of ``q``: a (16, 6) matrix
    acting on the flattened outer product ``q q^T`` (indices ``4 i + j``, wxyz)."""
    form = _ROT6D.get((device, dtype))
    if form is None:
        w, x, y, z = range(4)
        terms = (
            ((w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)),  # R00
            ((x, y, 2), (w, z, -2)),  # R01
            ((x, y, 2), (w, z, 2)),  # R10
            ((w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)),  # R11
            ((x, z, 2), (w, y, -2)),  # R20
            ((y, z, 2), (w, x, 2)),  # R21
        )
        form = torch.zeros(16, 6, dtype=dtype)
        for col, entries in enumerate(terms):
            for i, j, c in entries:
                form[4 * i + j, col] = c
        form = _ROT6D[(device, dtype)] = form.to(device)
    return form


def rot6d_from_quat(q: torch.Tensor) -> torch.Tensor:
    """The first two columns of the rotation matrix of a unit quaternion, row-major
    flattened: ``[R00, R01, R10, R11, R20, R21]``. One outer product and one matrix product
    (each entry is a quadratic form of ``q``). Shape: (..., 6)."""
    outer = (q.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2)
    return outer @ _rot6d_form(q.device, q.dtype)


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
