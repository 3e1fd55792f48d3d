"""The observation terms of the tracking task, and the groups made of them.

A group is a concatenation of terms; each :class:`ObsTerm` says how wide it is (from the
task's dimensions: computed, never counted by hand), which field of
:class:`~humimic.sim.randomization.ObservationNoise` scales its noise (``policy`` only), and
how it is computed from an :class:`ObsFrames` (the state and the frames every term shares,
computed once per step).

* ``policy`` (:data:`POLICY_TERMS`, deployable): the reference's joint positions and
  velocities, the reference anchor pose in the robot anchor frame (position, 6D rotation),
  projected gravity and angular velocity of the base (base frame), joint positions (relative
  to the default) and velocities, the last action.
* ``critic``: ``policy`` without noise, then :data:`CRITIC_EXTRA_TERMS`: the normalized physics
  parameters ``e``, the base linear velocity (base frame), the tracked bodies' positions and
  6D orientations in the robot anchor frame, the feet's floor contact forces.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from humimic.sim.randomization import ObservationNoise
from humimic.tracking.math import quat_apply_inverse, rot6d_from_quat, subtract_frame_transforms
from humimic.tracking.state import TrackingState


@dataclass(frozen=True)
class ObsDims:
    """The task's dimensions the term sizes depend on: joints, tracked bodies, feet, and the
    physics parameters ``e``."""

    joints: int
    bodies: int
    feet: int
    params: int


class ObsFrames:
    """The state, the physics parameters, and the frames the terms share (one rotation of
    three root vectors, the anchor-relative poses), computed once per step.

    Args:
        s: The state.
        params_e: The normalized physics parameters. Shape: (N, P).
        gravity: The gravity direction, world frame. Shape: (N, 3).
    """

    def __init__(self, s: TrackingState, params_e: torch.Tensor, gravity: torch.Tensor) -> None:
        self.s, self.params_e = s, params_e
        self.anchor_pos_b, self.anchor_quat_b = subtract_frame_transforms(
            s.anchor_pos_w, s.anchor_quat_w, s.ref_anchor_pos_w, s.ref_anchor_quat_w
        )
        # Gravity, angular and linear velocity in the root frame: one rotation of three vectors.
        root_vecs = torch.stack(
            [gravity, s.body_ang_vel_w[:, s.root_index], s.body_lin_vel_w[:, s.root_index]],
            dim=1,
        )
        self.gravity_b, self.root_ang_vel_b, self.root_lin_vel_b = quat_apply_inverse(
            s.root_quat_w[:, None], root_vecs
        ).unbind(1)
        self.body_pos_b, self.body_quat_b = subtract_frame_transforms(
            s.anchor_pos_w[:, None], s.anchor_quat_w[:, None], s.body_pos_w, s.body_quat_w
        )


@dataclass(frozen=True)
class ObsTerm:
    """One observation term.

    Attributes:
        name: What it is.
        func: Its value. Shape: (N, ``size(dims)``).
        size: Its width for the task's dimensions.
        noise: The :class:`~humimic.sim.randomization.ObservationNoise` field that is its
            noise's half-width (None: noise-free).
    """

    name: str
    func: Callable[[ObsFrames], torch.Tensor]
    size: Callable[[ObsDims], int]
    noise: str | None = None


def _joints(d: ObsDims) -> int:
    return d.joints


def _body_pos_b(f: ObsFrames) -> torch.Tensor:
    return f.body_pos_b.reshape(-1, 3 * len(f.s.body_names))


def _body_ori_b(f: ObsFrames) -> torch.Tensor:
    return rot6d_from_quat(f.body_quat_b).reshape(-1, 6 * len(f.s.body_names))


POLICY_TERMS: tuple[ObsTerm, ...] = (
    ObsTerm("ref_joint_pos", lambda f: f.s.ref_joint_pos, _joints),
    ObsTerm("ref_joint_vel", lambda f: f.s.ref_joint_vel, _joints),
    ObsTerm("ref_anchor_pos_b", lambda f: f.anchor_pos_b, lambda d: 3, "anchor_pos"),
    ObsTerm(
        "ref_anchor_ori_b", lambda f: rot6d_from_quat(f.anchor_quat_b), lambda d: 6, "anchor_ori"
    ),
    ObsTerm("projected_gravity", lambda f: f.gravity_b, lambda d: 3, "projected_gravity"),
    ObsTerm("base_ang_vel", lambda f: f.root_ang_vel_b, lambda d: 3, "base_ang_vel"),
    ObsTerm("joint_pos_rel", lambda f: f.s.joint_pos - f.s.default_joint_pos, _joints, "joint_pos"),
    ObsTerm("joint_vel", lambda f: f.s.joint_vel, _joints, "joint_vel"),
    ObsTerm("last_action", lambda f: f.s.action, _joints),
)
"""The ``policy`` group, in order."""

CRITIC_EXTRA_TERMS: tuple[ObsTerm, ...] = (
    ObsTerm("physics", lambda f: f.params_e, lambda d: d.params),
    ObsTerm("base_lin_vel", lambda f: f.root_lin_vel_b, lambda d: 3),
    ObsTerm("body_pos_b", _body_pos_b, lambda d: 3 * d.bodies),
    ObsTerm("body_ori_b", _body_ori_b, lambda d: 6 * d.bodies),
    ObsTerm("foot_force", lambda f: f.s.foot_force, lambda d: d.feet),
)
"""What the ``critic`` group adds after the noise-free ``policy`` group, in order."""


def group_size(terms: tuple[ObsTerm, ...], dims: ObsDims) -> int:
    """The width of a group of ``terms``."""
    return sum(t.size(dims) for t in terms)


def offset(terms: tuple[ObsTerm, ...], name: str, dims: ObsDims) -> int:
    """Where the term ``name`` starts in a group of ``terms``."""
    names = [t.name for t in terms]
    return group_size(terms[: names.index(name)], dims)


def noise_scale(
    terms: tuple[ObsTerm, ...], noise: ObservationNoise | None, dims: ObsDims
) -> torch.Tensor | None:
    """The noise half-width of each entry of a group of ``terms`` (None without noise)."""
    if noise is None:
        return None
    return torch.cat(
        [
            torch.zeros(t.size(dims)) if t.noise is None
            else torch.full((t.size(dims),), getattr(noise, t.noise))
            for t in terms
        ]
    )  # fmt: skip


def observe(frames: ObsFrames) -> tuple[torch.Tensor, torch.Tensor]:
    """The noise-free ``policy`` and ``critic`` groups (pure tensor math)."""
    policy = torch.cat([t.func(frames) for t in POLICY_TERMS], dim=-1)
    critic = torch.cat([policy, *(t.func(frames) for t in CRITIC_EXTRA_TERMS)], dim=-1)
    return policy, critic


__all__ = [
    "CRITIC_EXTRA_TERMS",
    "POLICY_TERMS",
    "ObsDims",
    "ObsFrames",
    "ObsTerm",
    "group_size",
    "noise_scale",
    "observe",
]
