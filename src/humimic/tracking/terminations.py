"""Termination terms of whole-body motion tracking: ``f(env, **params) -> Tensor[bool]``.

Shape: (num_envs,). Default thresholds are mjlab's (``tracking_env_cfg.py``): anchor height
0.25 m, anchor orientation 0.8 (difference of the z components of projected gravity),
end-effector height 0.25 m for the feet and hands.
"""

from __future__ import annotations

from typing import Protocol

import torch

from humimic.tracking.rewards import HasState


class HasEpisode(HasState, Protocol):
    """An env with an episode counter (the real env, or a fake one)."""

    episode_length_buf: torch.Tensor
    max_episode_length: int


def anchor_height_error(env: HasState, threshold: float) -> torch.Tensor:
    """The anchor's height differs from the reference's by more than ``threshold`` [m]."""
    s = env.state
    return torch.abs(s.ref_anchor_pos_w[:, 2] - s.anchor_pos_w[:, 2]) > threshold


def anchor_ori_error(env: HasState, threshold: float) -> torch.Tensor:
    """Projected gravity z of the anchor differs from the reference's by more than ``threshold``.

    The projected gravity ``g_b = R^T [0, 0, -1]`` has ``z = -cos(tilt)``; against an upright
    reference, 0.8 fires beyond a tilt of ``acos(0.2)``, about 78 degrees.
    """
    s = env.state
    return torch.abs(_gravity_z(s.ref_anchor_quat_w) - _gravity_z(s.anchor_quat_w)) > threshold


def _gravity_z(q: torch.Tensor) -> torch.Tensor:
    """z of the projected gravity ``R^T [0, 0, -1]``: ``-R_zz = 2 (x^2 + y^2) - 1``."""
    return 2.0 * torch.square(q[..., 1:3]).sum(-1) - 1.0


def ee_height_error(env: HasState, threshold: float, body_names: tuple[str, ...]) -> torch.Tensor:
    """Any named body's height differs from the anchor-relative reference by > ``threshold``."""
    s = env.state
    ids = s.body_ids(body_names)
    err = torch.abs(s.ref_body_pos_rel_w[:, ids, 2] - s.body_pos_w[:, ids, 2])
    return torch.any(err > threshold, dim=-1)


def time_out(env: HasEpisode) -> torch.Tensor:
    """The episode reached its length, or its reference clip its last frame."""
    s = env.state
    return (env.episode_length_buf >= env.max_episode_length) | (s.frame >= s.last_frame)
