"""The motion command of the tracking task: the reference clip as tensors, the states episodes
start from, and BeyondMimic's adaptive sampling of start frames.

:class:`MotionCommand` holds what every step reads of the reference (one packed table, one
gather per step) and the failure statistics that choose where episodes start: the clip is cut
into bins, each bin's failure rate is an exponential average of the episodes that failed
there, smoothed forward by a kernel (a failure is often caused a little earlier), and start
frames are drawn in proportion (Liao et al., "BeyondMimic", 2025).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import torch

from humimic import transforms as tf
from humimic.errors import InputError
from humimic.motion import Motion
from humimic.tracking.actions import STORED_BASES, stored_states
from humimic.tracking.config import TrackingConfig


class MotionCommand:
    """The reference motion of a tracking task, in the env's joint and tracked-body order.

    Args:
        cfg: The task (its tracked bodies, action base, adaptive sampling, start frame).
        motion: The reference clip, at the policy rate.
        joint_names: The env's joints (the backend's order).
        root_body: The robot's root body.
        device: Torch device of the tables.

    Raises:
        InputError: If the motion lacks a joint or tracked body of the task.
    """

    def __init__(
        self,
        cfg: TrackingConfig,
        motion: Motion,
        joint_names: Sequence[str],
        root_body: str,
        device: torch.device,
    ) -> None:
        try:
            jidx = [motion.joint_names.index(j) for j in joint_names]
            bidx = [motion.body_names.index(b) for b in cfg.body_names]
            root_m = motion.body_names.index(root_body)
        except ValueError as e:
            raise InputError(f"the motion lacks a joint or body of the task: {e}") from None
        self.cfg, self.device, self.joint_index = cfg, device, jidx
        self.num_frames = T = motion.num_frames
        fields = [
            motion.joint_pos[:, jidx], motion.joint_vel[:, jidx], motion.body_pos_w[:, bidx],
            motion.body_quat_w[:, bidx], motion.body_lin_vel_w[:, bidx],
            motion.body_ang_vel_w[:, bidx],
        ]  # fmt: skip
        tables = [self._tensor(f) for f in fields]
        self.joint_pos = tables[0]
        """The reference's joint positions. Shape: (T, J)."""
        # One packed table of what every step reads: one gather per step instead of six.
        self.packed = torch.cat([x.reshape(T, -1) for x in tables], dim=1)
        self.split = [x.reshape(T, -1).shape[1] for x in tables]
        """The widths of the fields in :attr:`packed`: joint positions and velocities, tracked
        bodies' positions, orientations, linear and angular velocities (world frame)."""
        self._motion, self._root_m = motion, root_m
        # Adaptive sampling: failure rates per bin of the clip.
        ad = cfg.adaptive
        self.bin_count = int(T // max(ad.bin_s / cfg.step_dt, 1.0)) + 1
        self.bin_failed = torch.zeros(self.bin_count, device=device)
        kernel = torch.tensor([ad.kernel_lambda**i for i in range(ad.kernel_size)], device=device)
        self._kernel = (kernel / kernel.sum()).view(1, 1, -1)
        self.weights = torch.zeros(self.bin_count, device=device)
        """Start-bin sampling probabilities. Shape: (bins,)."""

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(x), dtype=torch.float32, device=self.device)

    def gather(self, frame: torch.Tensor, out: torch.Tensor) -> None:
        """The packed reference at each env's ``frame`` into ``out`` (one gather)."""
        torch.index_select(self.packed, 0, frame, out=out)

    @functools.cached_property
    def start(self) -> dict[str, np.ndarray]:
        """The reference states episodes start from (float64): the motion's frames and their
        finite-difference velocities, or, with a stored base (``feedforward``, ``feedback``),
        the simulated states the stored controls continue from
        (:func:`~humimic.tracking.actions.stored_states`). Read after the action base is
        built (:class:`~humimic.tracking.bases.BaseTargets`), which checks the motion's
        dynamic section."""
        motion, jidx, root_m = self._motion, self.joint_index, self._root_m
        if self.cfg.action_base in STORED_BASES:
            states = stored_states(motion, self.cfg.decimation)
            assert states is not None  # BaseTargets' base_table has checked the section.
            qpos, qvel = states
            quat = qpos[:, 3:7] / np.linalg.norm(qpos[:, 3:7], axis=-1, keepdims=True)
            rot = tf.quat_to_matrix(quat)
            return {
                "root_pos": qpos[:, :3].copy(),
                "root_quat": quat,
                "root_rot": rot,
                "root_lin_vel": qvel[:, :3].copy(),
                "root_ang_vel": np.einsum("nij,nj->ni", rot, qvel[:, 3:6]),
                "joint_pos": np.ascontiguousarray(qpos[:, 7:]),
                "joint_vel": np.ascontiguousarray(qvel[:, 6:]),
            }
        root_quat = motion.qpos[:, 3:7].astype(np.float64)
        root_quat /= np.linalg.norm(root_quat, axis=-1, keepdims=True)
        return {
            "root_pos": motion.qpos[:, :3].astype(np.float64),
            "root_quat": root_quat,
            "root_rot": tf.quat_to_matrix(root_quat),
            "root_lin_vel": motion.body_lin_vel_w[:, root_m].astype(np.float64),
            "root_ang_vel": motion.body_ang_vel_w[:, root_m].astype(np.float64),
            "joint_pos": np.ascontiguousarray(motion.joint_pos[:, jidx], dtype=np.float64),
            "joint_vel": np.ascontiguousarray(motion.joint_vel[:, jidx], dtype=np.float64),
        }

    # ------------------------------------------------------------------ adaptive sampling

    def sample_frames(self, n: int, gen: torch.Generator) -> torch.Tensor:
        """``n`` start frames: the task's fixed start frame, or drawn by the sampling
        weights (uniformly without adaptive sampling)."""
        T, dev = self.num_frames, self.device
        if self.cfg.start_frame is not None:
            return torch.full((n,), min(self.cfg.start_frame, T - 2), device=dev)
        if self.cfg.adaptive.enabled:
            bins = torch.multinomial(self.weights, n, replacement=True, generator=gen)
            u = torch.rand(n, generator=gen, device=dev)
            frames = ((bins.float() + u) / self.bin_count * (T - 1)).long()
        else:
            frames = torch.randint(0, T - 1, (n,), generator=gen, device=dev)
        return frames.clamp(0, T - 2)

    def fold_failures(self, frame: torch.Tensor, failed: torch.Tensor) -> None:
        """Fold one step's failures (``failed``: 1.0 per env whose episode failed at its
        ``frame``) into the failure rate of each bin and recompute the sampling weights (no
        host sync: a scatter, not a test for failures)."""
        bins = torch.div(frame * self.bin_count, self.num_frames, rounding_mode="floor")
        now = torch.zeros_like(self.bin_failed).scatter_add_(
            0, bins.clamp(0, self.bin_count - 1), failed
        )
        a = self.cfg.adaptive.alpha
        self.bin_failed.mul_(1.0 - a).add_(a * now)
        self.weights.copy_(self._compute_weights())

    def _compute_weights(self) -> torch.Tensor:
        ad = self.cfg.adaptive
        n = self.bin_count
        if not ad.enabled:
            return torch.full((n,), 1.0 / n, device=self.device)
        p = self.bin_failed + ad.uniform_ratio / n
        padded = torch.cat([p, p[-1:].expand(ad.kernel_size - 1)])
        out = torch.nn.functional.conv1d(padded.view(1, 1, -1), self._kernel).view(n)
        return out / out.sum()

    def sampling_entropy(self) -> torch.Tensor:
        """The sampling weights' entropy over its maximum (1: uniform)."""
        p = self.weights
        h = -(p * (p + 1e-12).log()).sum()
        return h / math.log(self.bin_count) if self.bin_count > 1 else h * 0 + 1


__all__ = ["MotionCommand"]
