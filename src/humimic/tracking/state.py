"""The batched tensors that tracking MDP terms read (robot state and the reference frame).

Reward, termination and observation terms are free functions ``f(env, **params)`` that read
``env.state``, a :class:`TrackingState`. Tests build one by hand for a tiny fake env; the
environment allocates it once and writes it in place every step (rsl_rl runs the rollout under
``torch.inference_mode()``). Quaternions are wxyz; ``_w`` world frame, ``_b`` body frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from humimic.errors import UnknownNameError
from humimic.tracking.math import yaw_half_angle, yaw_quat_matrix, yaw_rotation_matrix


@dataclass(kw_only=True, eq=False)
class TrackingState:
    """Robot and reference state of every env. B tracked bodies, J joints, C contact bodies.

    Attributes:
        body_names: Tracked bodies (the anchor among them). Shape: (B,).
        anchor_index: Index of the anchor body in ``body_names``.
        root_index: Index of the floating base in ``body_names``.
        ref_joint_pos: Reference joint positions. Shape: (N, J).
        ref_joint_vel: Shape: (N, J).
        ref_body_pos_w: Reference body positions. Shape: (N, B, 3).
        ref_body_quat_w: Shape: (N, B, 4).
        ref_body_lin_vel_w: Shape: (N, B, 3).
        ref_body_ang_vel_w: Shape: (N, B, 3).
        ref_body_pos_rel_w: The reference bodies moved so that the reference anchor sits at
            the robot anchor's horizontal position and heading (mjlab's
            ``body_pos_relative_w``); its height is the reference's. Refreshed after the
            physics of each step, for rewards and terminations (not after the step's resets).
            Shape: (N, B, 3).
        ref_body_quat_rel_w: Same, orientations. Shape: (N, B, 4).
        body_pos_w: Robot body positions. Shape: (N, B, 3).
        body_quat_w: Shape: (N, B, 4).
        body_lin_vel_w: Shape: (N, B, 3).
        body_ang_vel_w: Shape: (N, B, 3).
        joint_pos: Shape: (N, J). joint_vel: Shape: (N, J).
        default_joint_pos: Shape: (J,).
        soft_joint_limits: Shape: (J, 2).
        action: The current policy action. Shape: (N, J).
        last_action: The previous policy action. Shape: (N, J).
        contact_found: Floor contacts of the undesired-contact bodies. Shape: (N, C).
        foot_force: Floor contact force magnitude on each foot [N]. Shape: (N, F).
        frame: Reference frame index of every env. Shape: (N,), long.
        last_frame: The last frame of every env's clip (a library holds several clips in one
            table). Shape: (N,), long.
        num_frames: Frames in the reference (every clip of a library).
    """

    body_names: tuple[str, ...]
    anchor_index: int
    root_index: int
    ref_joint_pos: torch.Tensor
    ref_joint_vel: torch.Tensor
    ref_body_pos_w: torch.Tensor
    ref_body_quat_w: torch.Tensor
    ref_body_lin_vel_w: torch.Tensor
    ref_body_ang_vel_w: torch.Tensor
    ref_body_pos_rel_w: torch.Tensor
    ref_body_quat_rel_w: torch.Tensor
    body_pos_w: torch.Tensor
    body_quat_w: torch.Tensor
    body_lin_vel_w: torch.Tensor
    body_ang_vel_w: torch.Tensor
    joint_pos: torch.Tensor
    joint_vel: torch.Tensor
    default_joint_pos: torch.Tensor
    soft_joint_limits: torch.Tensor
    action: torch.Tensor
    last_action: torch.Tensor
    contact_found: torch.Tensor
    foot_force: torch.Tensor
    frame: torch.Tensor
    last_frame: torch.Tensor
    num_frames: int
    _ids: dict[tuple[str, ...], torch.Tensor] = field(default_factory=dict, repr=False)

    @classmethod
    def zeros(
        cls,
        *,
        num_envs: int,
        body_names: tuple[str, ...],
        anchor_body: str,
        root_body: str,
        num_joints: int,
        num_contact_bodies: int = 0,
        num_feet: int = 0,
        num_frames: int = 1,
        device: str | torch.device = "cpu",
    ) -> TrackingState:
        """A state with every buffer allocated (identity quaternions, zeros elsewhere)."""
        for name in (anchor_body, root_body):
            if name not in body_names:
                raise UnknownNameError(f"body {name!r} must be one of the tracked bodies")
        n, b, j = num_envs, len(body_names), num_joints

        def z(*shape: int) -> torch.Tensor:
            return torch.zeros(*shape, dtype=torch.float32, device=device)

        def q() -> torch.Tensor:
            t = z(n, b, 4)
            t[..., 0] = 1.0
            return t

        limits = z(j, 2)
        limits[:, 0], limits[:, 1] = -torch.inf, torch.inf
        return cls(
            body_names=tuple(body_names),
            anchor_index=body_names.index(anchor_body),
            root_index=body_names.index(root_body),
            ref_joint_pos=z(n, j),
            ref_joint_vel=z(n, j),
            ref_body_pos_w=z(n, b, 3),
            ref_body_quat_w=q(),
            ref_body_lin_vel_w=z(n, b, 3),
            ref_body_ang_vel_w=z(n, b, 3),
            ref_body_pos_rel_w=z(n, b, 3),
            ref_body_quat_rel_w=q(),
            body_pos_w=z(n, b, 3),
            body_quat_w=q(),
            body_lin_vel_w=z(n, b, 3),
            body_ang_vel_w=z(n, b, 3),
            joint_pos=z(n, j),
            joint_vel=z(n, j),
            default_joint_pos=z(j),
            soft_joint_limits=limits,
            action=z(n, j),
            last_action=z(n, j),
            contact_found=z(n, num_contact_bodies),
            foot_force=z(n, num_feet),
            frame=torch.zeros(n, dtype=torch.long, device=device),
            last_frame=torch.full((n,), num_frames - 1, dtype=torch.long, device=device),
            num_frames=num_frames,
        )

    @property
    def num_envs(self) -> int:
        return int(self.joint_pos.shape[0])

    def body_ids(self, names: tuple[str, ...] | list[str] | None) -> torch.Tensor | slice:
        """Indices of tracked bodies by name (``None``: all of them), cached.

        Raises:
            UnknownNameError: If a name is not tracked.
        """
        if names is None:
            return slice(None)
        key = tuple(names)
        if key not in self._ids:
            missing = [n for n in key if n not in self.body_names]
            if missing:
                raise UnknownNameError(
                    f"bodies {missing} are not tracked; tracked bodies: {list(self.body_names)}"
                )
            self._ids[key] = torch.tensor(
                [self.body_names.index(n) for n in key], device=self.joint_pos.device
            )
        return self._ids[key]

    # Anchor views (Shape: (N, 3) / (N, 4)).
    @property
    def anchor_pos_w(self) -> torch.Tensor:
        return self.body_pos_w[:, self.anchor_index]

    @property
    def anchor_quat_w(self) -> torch.Tensor:
        return self.body_quat_w[:, self.anchor_index]

    @property
    def ref_anchor_pos_w(self) -> torch.Tensor:
        return self.ref_body_pos_w[:, self.anchor_index]

    @property
    def ref_anchor_quat_w(self) -> torch.Tensor:
        return self.ref_body_quat_w[:, self.anchor_index]

    @property
    def root_quat_w(self) -> torch.Tensor:
        return self.body_quat_w[:, self.root_index]

    def update_relative(self) -> None:
        """Recompute ``ref_body_pos_rel_w`` / ``ref_body_quat_rel_w`` in place: the reference
        turned by the heading difference of the anchors about the reference anchor, moved to
        the robot anchor's horizontal position (BeyondMimic). The heading turn is applied as a
        matrix product (one for the quaternions, one for the positions)."""
        ref_anchor_pos = self.ref_anchor_pos_w[:, None]
        h = yaw_half_angle(self.anchor_quat_w, self.ref_anchor_quat_w)
        torch.matmul(
            self.ref_body_quat_w, yaw_quat_matrix(h).transpose(-1, -2), out=self.ref_body_quat_rel_w
        )
        delta_pos = self.anchor_pos_w[:, None].clone()
        delta_pos[..., 2] = ref_anchor_pos[..., 2]
        rel = torch.matmul(self.ref_body_pos_w - ref_anchor_pos, yaw_rotation_matrix(h).mT)
        torch.add(delta_pos, rel, out=self.ref_body_pos_rel_w)
