"""Reward terms of whole-body motion tracking (BeyondMimic): free functions
``f(env, **params) -> Tensor`` of Shape: (num_envs,), reading ``env.state`` (a
:class:`~humimic.tracking.state.TrackingState`). The environment multiplies each by its term's
weight (and by the policy step, as mjlab does); the default terms, stds and weights are
:func:`humimic.tracking.config.default_rewards`.
"""

from __future__ import annotations

from typing import Protocol

import torch

from humimic.tracking.math import quat_error_magnitude
from humimic.tracking.state import TrackingState


class HasState(Protocol):
    """Anything with a :class:`TrackingState` (the env, or a fake env in tests)."""

    @property
    def state(self) -> TrackingState: ...


def anchor_pos_error_exp(env: HasState, std: float) -> torch.Tensor:
    """``exp(-|p_ref - p|^2 / std^2)`` of the anchor position (world frame). Shape: (N,)."""
    s = env.state
    err = torch.sum(torch.square(s.ref_anchor_pos_w - s.anchor_pos_w), dim=-1)
    return torch.exp(-err / std**2)


def anchor_ori_error_exp(env: HasState, std: float) -> torch.Tensor:
    """``exp(-angle(q_ref, q)^2 / std^2)`` of the anchor orientation. Shape: (N,)."""
    s = env.state
    err = quat_error_magnitude(s.ref_anchor_quat_w, s.anchor_quat_w) ** 2
    return torch.exp(-err / std**2)


def body_pos_error_exp(
    env: HasState, std: float, body_names: tuple[str, ...] | None = None
) -> torch.Tensor:
    """Body positions against the anchor-relative reference, mean squared error. Shape: (N,)."""
    s = env.state
    ids = s.body_ids(body_names)
    err = torch.sum(torch.square(s.ref_body_pos_rel_w[:, ids] - s.body_pos_w[:, ids]), dim=-1)
    return torch.exp(-err.mean(-1) / std**2)


def body_ori_error_exp(
    env: HasState, std: float, body_names: tuple[str, ...] | None = None
) -> torch.Tensor:
    """Body orientations against the anchor-relative reference (mean squared angle). Shape: (N,)."""
    s = env.state
    ids = s.body_ids(body_names)
    err = quat_error_magnitude(s.ref_body_quat_rel_w[:, ids], s.body_quat_w[:, ids]) ** 2
    return torch.exp(-err.mean(-1) / std**2)


def body_lin_vel_error_exp(
    env: HasState, std: float, body_names: tuple[str, ...] | None = None
) -> torch.Tensor:
    """Body linear velocities (world frame), mean squared error. Shape: (N,)."""
    s = env.state
    ids = s.body_ids(body_names)
    err = torch.sum(torch.square(s.ref_body_lin_vel_w[:, ids] - s.body_lin_vel_w[:, ids]), dim=-1)
    return torch.exp(-err.mean(-1) / std**2)


def body_ang_vel_error_exp(
    env: HasState, std: float, body_names: tuple[str, ...] | None = None
) -> torch.Tensor:
    """Body angular velocities (world frame), mean squared error. Shape: (N,)."""
    s = env.state
    ids = s.body_ids(body_names)
    err = torch.sum(torch.square(s.ref_body_ang_vel_w[:, ids] - s.body_ang_vel_w[:, ids]), dim=-1)
    return torch.exp(-err.mean(-1) / std**2)


def action_rate_l2(env: HasState) -> torch.Tensor:
    """``|a_t - a_{t-1}|^2``. Shape: (N,)."""
    s = env.state
    return torch.sum(torch.square(s.action - s.last_action), dim=-1)


def joint_pos_limits(env: HasState) -> torch.Tensor:
    """Sum over joints of how far each is outside its soft limits [rad]. Shape: (N,)."""
    s = env.state
    lower, upper = s.soft_joint_limits[:, 0], s.soft_joint_limits[:, 1]
    below = (lower - s.joint_pos).clamp(min=0.0)
    above = (s.joint_pos - upper).clamp(min=0.0)
    return torch.sum(below + above, dim=-1)


def undesired_contacts(env: HasState) -> torch.Tensor:
    """Number of undesired-contact bodies (not feet, not hands) touching the floor. Shape: (N,).

    mjlab's tracking task has this term commented out (weight -10 on contact forces above
    1 N); humimic counts contacting bodies and uses weight -0.1 by default.
    """
    return torch.sum((env.state.contact_found > 0).float(), dim=-1)
