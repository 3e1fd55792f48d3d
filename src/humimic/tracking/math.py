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


def quat_log(q: torch.Tensor) -> torch.Tensor:
    """The rotation vector of a unit quaternion, on the short path (angle in [0, pi]; as
    ``mju_quat2Vel`` with a unit time). Shape: (..., 4) -> (..., 3)."""
    q = torch.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    scale = torch.where(s > 1e-8, angle / s.clamp(min=1e-8), torch.full_like(s, 2.0))
    return v * scale


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


_FORMS: dict[tuple[str, torch.device, torch.dtype], torch.Tensor] = {}

# Rotation-matrix entries of a unit quaternion as quadratic forms of (w, x, y, z): each entry is
# a list of (i, j, coefficient) over the products q_i q_j.
_W, _X, _Y, _Z = range(4)
_MATRIX_TERMS = (
    ((_W, _W, 1), (_X, _X, 1), (_Y, _Y, -1), (_Z, _Z, -1)),  # R00
    ((_X, _Y, 2), (_W, _Z, -2)),  # R01
    ((_X, _Z, 2), (_W, _Y, 2)),  # R02
    ((_X, _Y, 2), (_W, _Z, 2)),  # R10
    ((_W, _W, 1), (_X, _X, -1), (_Y, _Y, 1), (_Z, _Z, -1)),  # R11
    ((_Y, _Z, 2), (_W, _X, -2)),  # R12
    ((_X, _Z, 2), (_W, _Y, -2)),  # R20
    ((_Y, _Z, 2), (_W, _X, 2)),  # R21
    ((_W, _W, 1), (_X, _X, -1), (_Y, _Y, -1), (_Z, _Z, 1)),  # R22
)
_FORM_ENTRIES = {
    "matrix": tuple(range(9)),  # R, row-major.
    "rot6d": (0, 1, 3, 4, 6, 7),  # R[:, :2], row-major.
    "heading": (0, 3),  # R00, R10: the rotated x axis in the horizontal plane.
}


def _form(name: str, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """The (16, k) matrix of the rotation-matrix entries ``_FORM_ENTRIES[name]`` as quadratic
    forms acting on the flattened outer product ``q q^T`` (indices ``4 i + j``, wxyz)."""
    key = (name, device, dtype)
    form = _FORMS.get(key)
    if form is None:
        entries = _FORM_ENTRIES[name]
        form = torch.zeros(16, len(entries), dtype=dtype)
        for col, entry in enumerate(entries):
            for i, j, c in _MATRIX_TERMS[entry]:
                form[4 * i + j, col] = c
        form = _FORMS[key] = form.to(device)
    return form


def _quadratic(q: torch.Tensor, name: str) -> torch.Tensor:
    outer = (q.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2)
    return outer @ _form(name, q.device, q.dtype)


def rot6d_from_quat(q: torch.Tensor) -> torch.Tensor:
    """The first two columns of the rotation matrix of a unit quaternion, row-major
    flattened: ``[R00, R01, R10, R11, R20, R21]``. One outer product and one matrix product
    (each entry is a quadratic form of ``q``). Shape: (..., 6)."""
    return _quadratic(q, "rot6d")


def matrix_from_quat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of unit quaternions, as :func:`rot6d_from_quat` computes them.
    Shape: (..., 4) -> (..., 3, 3)."""
    return _quadratic(q, "matrix").unflatten(-1, (3, 3))


def yaw_half_angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``[cos(t / 2), sin(t / 2)]`` of the heading ``t`` of ``a * conj(b)``: the angle about
    world z of :func:`yaw_quat` of that product, without forming the quaternion. Shape:
    (..., 4) -> (..., 2)."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    w = aw * bw + (av * bv).sum(-1, keepdim=True)
    v = bw * av - aw * bv - torch.linalg.cross(av, bv)
    c, s = _quadratic(torch.cat([w, v], dim=-1), "heading").unbind(-1)
    half = 0.5 * torch.atan2(s, c)
    return torch.stack([torch.cos(half), torch.sin(half)], dim=-1)


_YAW: dict[tuple[torch.device, torch.dtype], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}


def _yaw_forms(
    device: torch.device, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For ``h = [c, s]`` of a yaw quaternion ``(c, 0, 0, s)``: its left-multiplication
    matrix is ``h @ L`` (L: (2, 16)); its rotation matrix is ``(h h^T) @ M + E`` (M: (4, 9),
    E: the constant 1 at R22)."""
    forms = _YAW.get((device, dtype))
    if forms is None:
        # (c, 0, 0, s) * q = [c qw - s qz, c qx - s qy, c qy + s qx, c qz + s qw].
        left = torch.zeros(2, 4, 4, dtype=dtype)
        left[0] = torch.eye(4, dtype=dtype)
        left[1, 0, 3], left[1, 1, 2], left[1, 2, 1], left[1, 3, 0] = -1.0, -1.0, 1.0, 1.0
        # cos t = c^2 - s^2, sin t = 2 c s (outer product indices: cc 0, cs 1, sc 2, ss 3).
        rot = torch.zeros(4, 3, 3, dtype=dtype)
        rot[0, 0, 0], rot[3, 0, 0], rot[0, 1, 1], rot[3, 1, 1] = 1.0, -1.0, 1.0, -1.0
        rot[1, 1, 0], rot[2, 1, 0], rot[1, 0, 1], rot[2, 0, 1] = 1.0, 1.0, -1.0, -1.0
        const = torch.zeros(9, dtype=dtype)
        const[8] = 1.0
        forms = _YAW[(device, dtype)] = (
            left.reshape(2, 16).to(device),
            rot.reshape(4, 9).to(device),
            const.to(device),
        )
    return forms


def yaw_quat_matrix(h: torch.Tensor) -> torch.Tensor:
    """Left-multiplication matrix of the yaw quaternion ``(h0, 0, 0, h1)``: ``yaw * q`` is
    ``matrix @ q``. Shape: (..., 2) -> (..., 4, 4)."""
    left, _, _ = _yaw_forms(h.device, h.dtype)
    return (h @ left).unflatten(-1, (4, 4))


def yaw_rotation_matrix(h: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the yaw quaternion ``(h0, 0, 0, h1)``. Shape: (..., 2) -> (..., 3, 3)."""
    _, rot, const = _yaw_forms(h.device, h.dtype)
    outer = (h.unsqueeze(-1) * h.unsqueeze(-2)).flatten(-2)
    return torch.addmm(const, outer.reshape(-1, 4), rot).reshape(*h.shape[:-1], 3, 3)


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
